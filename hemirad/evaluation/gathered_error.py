"""The solution's error, measured by the solution itself: at points sampled over the
surfaces, the displayed radiosity against a final gather of the solved radiosity
(docs/DESIGN.md §3.8).

What a user is shown at a point x of element k is the Gouraud interpolation of vertex
values (``output.display``). What the solution says x receives is a final gather: a
hemicube at x, every pixel's delta form factor times the radiosity of the element it sees,
so B(x) = E_k + rho_k sum_j F_xj B_j (``lighting.sensors``). The gather resolves what the
mesh cannot: a shadow edge or a penumbra inside an element, light falling off over a large
wall element, a contact line; and it does not trust the element's own value. The
difference of the two, over points sampled uniformly by area, estimates the picture's
relative RMS error over all surfaces; measured against path-traced references, which see
what their cameras see, it reads about 1-2x the error there (figures/accuracy_converged.md),
and within 5% of the error a closed form measures (tests/test_gathered_error.py). What the
gather cannot see is the error of the radiosity it gathers.

Points that see back faces over most of their hemisphere lie inside a solid or under an
object standing on them (a block's footprint, unmeshed contacts): no view shows them, and
their gather (dark) says nothing of the picture; they are left out. Emitting elements are
not sampled.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from hemirad.core.colour import luminance
from hemirad.geometry.mesh import Mesh
from hemirad.lighting.sensors import final_gather, sensor_renderer
from hemirad.output import display

#: The share of a sample's (cosine-weighted) hemisphere in which it sees back faces above
#: which it counts as hidden: inside a closed solid that share is 1, under a one-sided
#: lamp or beside an open object a few per cent.
HIDDEN_BACK_SHARE = 0.5
#: Samples per estimate by default: 1,000 give the estimate to about 10% (its standard
#: error, reported with it) in 2-5 s on a 2-core machine for 3,000-10,000 elements.
DEFAULT_SAMPLES = 1000


@dataclass(frozen=True)
class GatheredError:
    """The estimate and its statistics.

    Attributes:
        relative_rms: sqrt(sum e^2 / sum L^2) over the kept samples: e the displayed less the
            gathered luminance, L the gathered luminance (area-weighted by the sampling).
        standard_error: of ``relative_rms`` (delta method over the samples).
        samples: the samples kept (not hidden).
    """

    relative_rms: float
    standard_error: float
    samples: int


def sample_points(mesh: Mesh, among: torch.Tensor, count: int, seed: int = 0
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` points uniform by area over the elements ``among`` (T,) bool, stratified
    along the elements' cumulative area (so every part of the surfaces gets its share).

    Returns:
        (N,) the element of each point, (N, 3) its barycentric coordinates, (N, 3) the point.
    """
    generator = torch.Generator().manual_seed(seed)
    mesh = mesh.to("cpu")
    candidates = torch.nonzero(among.cpu()).flatten()
    cumulative = torch.cumsum(mesh.areas.index_select(0, candidates), 0)
    u = (torch.arange(count, dtype=torch.float64)
         + torch.rand(count, generator=generator, dtype=torch.float64)) / count * cumulative[-1]
    element = candidates[torch.searchsorted(cumulative, u).clamp(max=len(candidates) - 1)]
    r1, r2 = torch.rand(2, count, generator=generator, dtype=torch.float64)
    s = r1.sqrt()  # uniform over the triangle
    barycentric = torch.stack([1 - s, s * (1 - r2), s * r2], 1)
    points = (mesh.corners.index_select(0, element) * barycentric[:, :, None]).sum(1)
    return element, barycentric, points


def gathered_error(mesh: Mesh, radiosity: torch.Tensor, emission: torch.Tensor, reflectance: torch.Tensor,
                   samples: int = DEFAULT_SAMPLES, resolution: int = 128, seed: int = 0) -> GatheredError | None:
    """Estimate the displayed solution's relative RMS error by final gathers at ``samples``
    points (see the module's docstring); None where no non-emitting surface is sampled.

    Args:
        mesh: the solved mesh (T elements); radiosity: (T, 3) the display radiosity.
        emission, reflectance: (T, 3) each element's.
        resolution: the gathers' hemicube resolution.
        seed: of the sampling: the same mesh and seed give the same points.
    """
    mesh = mesh.to("cpu")
    radiosity, emission, reflectance = (torch.as_tensor(t, dtype=torch.float64).cpu()
                                        for t in (radiosity, emission, reflectance))
    among = ~(emission > 0).any(1) & (mesh.areas > 0)
    if samples <= 0 or not bool(among.any()):
        return None
    element, barycentric, points = sample_points(mesh, among, samples, seed)
    vertex = display.conforming_vertex_values(mesh, display.vertex_values(mesh, radiosity))  # (V, 3)
    shown = luminance((vertex[mesh.triangles.index_select(0, element)] * barycentric[:, :, None]).sum(1))
    normals = mesh.normals.index_select(0, element)
    with sensor_renderer(mesh, points.numpy(), resolution) as renderer:
        gather = final_gather(mesh, radiosity, points.numpy(), normals.numpy(), renderer=renderer)
    gathered = luminance(emission.index_select(0, element) + reflectance.index_select(0, element) * gather.irradiance)
    kept = (gather.coverage - gather.front_coverage) <= HIDDEN_BACK_SHARE
    e2, L2 = (shown - gathered)[kept].pow(2), gathered[kept].pow(2)
    n = len(e2)
    if n == 0 or float(L2.sum()) <= 0:
        return None
    ratio = float(e2.sum() / L2.sum())
    # delta method for a ratio of means: var(r) ~ var(e2 - r L2) / (n mean(L2)^2)
    spread = float((e2 - ratio * L2).var()) if n > 1 else 0.0
    ratio_error = math.sqrt(spread / n) / float(L2.mean())
    relative_rms = math.sqrt(ratio)
    return GatheredError(relative_rms, ratio_error / (2 * relative_rms) if relative_rms > 0 else 0.0, n)
