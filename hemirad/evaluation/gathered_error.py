"""The solution's error, measured by the solution itself: at points sampled over the
surfaces, the displayed radiosity against a final gather of the solved radiosity
(docs/DESIGN.md §3.8).

What a user is shown at a point x of element k is the picture's shading there
(``output.shading``: the fitted quadratics around the element's corners, blended). What
the solution says x receives is a final gather: a hemicube at x, every pixel's delta form
factor times the radiosity of the element it sees, so B(x) = E_k + rho_k sum_j F_xj B_j
(``lighting.sensors``). The gather resolves what the
mesh cannot: a shadow edge or a penumbra inside an element, light falling off over a large
wall element, a contact line; and it does not trust the element's own value. The relative
RMS difference of the two over sampled points estimates the displayed solution's error:
``gathered_error`` samples every surface by area (the solution, as any view may show it);
``image_gathered_error`` the points a camera's pixels see (the picture, weighted as a
per-pixel comparison with a rendered reference weighs it, ``metrics.relative_mse``). Both
read within 5% of the error a closed form measures (tests/test_gathered_error.py); against
the path-traced references see figures/accuracy_converged.md. What the gather cannot see
is the error of the radiosity it gathers.

The error of a refined or contact-meshed solution sits in a small part of the surfaces (a
penumbra, a crease), so a few samples carry most of the squared error and the estimate's
spread is wide. Given a ``guide`` (each element's expected error: the interpolation
estimate, ``adaptive.answer.element_errors``), ``GUIDE_SHARE`` of the sampling density
follows its square, the rest the area (or the pixels), each sample weighted by the two
densities' ratio: the same expectation, and a sample in the penumbra counts for less where
more of them are drawn (defensive importance sampling: a weight is at most
1 / (1 - ``GUIDE_SHARE``), so a guide that is wrong costs at most that factor in variance).

Points that see back faces over most of their hemisphere lie inside a solid or under an
object standing on them (a block's footprint, unmeshed contacts): no view shows them, and
their gather (dark) says nothing of the picture; they are left out. Emitting elements are
not sampled.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from hemirad.core.colour import luminance
from hemirad.geometry.mesh import Mesh, barycentric
from hemirad.lighting.sensors import final_gather
from hemirad.output.render import pixel_points
from hemirad.output.shading import Shading, picture_shading
from hemirad.scene.model import Camera

#: The share of a sample's (cosine-weighted) hemisphere in which it sees back faces above
#: which it counts as hidden: inside a closed solid that share is 1, under a one-sided
#: lamp or beside an open object a few per cent.
HIDDEN_BACK_SHARE = 0.5
#: Samples per estimate by default: 1,000 give the estimate to about 10% (its standard
#: error, reported with it) in 1-4 s on a 2-core machine for 2,600-22,000 elements.
DEFAULT_SAMPLES = 1000
#: The share of the sampling density that follows the ``guide``'s square (module docstring).
#: Measured (the picture's estimate over the path-traced references' pixels, 1,000 samples,
#: six seeds; estimate / measured): office uniform 11,170 elements 0.78-1.64 by pixel,
#: 1.43-1.46 with half the density guided, 1.40-1.46 with three quarters; office refined from
#: x1 (4,265 and 23,483 elements) 0.80-1.57 and 1.01-1.63 by pixel, 1.26-1.33 and 1.31-1.40
#: guided; floating and the Cornell box 0.84-1.31 by pixel, 0.88-1.18 guided.
GUIDE_SHARE = 0.5
#: A point is gathered at least this barycentric share inside its element. A pixel centre on
#: a room's corner line lies, to rounding, on the other wall's plane, and a gather there sees
#: a third of its hemisphere outside the room: three such points on floating's corner made
#: 91% of the picture's estimate after three rounds from x2 (0.41 gathered against 0.65
#: shown and path-traced), which read 2.7 times the measured error. Points drawn over the
#: surfaces too: one on the ceiling 0.5 mm beside the rim of floating's lamp (which hangs
#: 1 mm below it) saw the lamp's back over 45% of its hemisphere and made 82% of the
#: surfaces' estimate after one round from x2 (0.0196 +/- 0.0082, 4.4 times the picture's
#: measured error): a dark band a millimetre wide that no view resolves.
EDGE_INSET = 1e-2


@dataclass(frozen=True)
class GatheredError:
    """The estimate and its statistics.

    Attributes:
        relative_rms: sqrt(sum e^2 / sum L^2) over the kept samples: e the displayed less the
            gathered luminance, L the gathered luminance (weighted as the points were
            drawn: by area, or by pixel).
        standard_error: of ``relative_rms`` (delta method over the samples).
        samples: the samples kept (not hidden).
    """

    relative_rms: float
    standard_error: float
    samples: int


def _stratified(count: int, generator: torch.Generator) -> torch.Tensor:
    """(count,) float64 in [0, 1): one uniform draw in each of ``count`` equal strata."""
    return (torch.arange(count, dtype=torch.float64)
            + torch.rand(count, generator=generator, dtype=torch.float64)) / count


def _draw(density: torch.Tensor, guide: torch.Tensor | None, count: int, generator: torch.Generator
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` draws among N items, stratified along their cumulative probability: by
    ``density`` (N,) (unnormalised), or with a ``guide`` (N,) (expected errors) by its mixture
    with the guide's square times the density (``GUIDE_SHARE``).

    Returns:
        (count,) the items drawn and (count,) float64 their weights: the density's
        probability over the one drawn from (1 without a guide).
    """
    p = density.to(torch.float64) / density.sum()
    q = p
    if guide is not None:
        emphasis = p * guide.to(torch.float64).square()
        if float(emphasis.sum()) > 0:
            q = (1 - GUIDE_SHARE) * p + GUIDE_SHARE * emphasis / emphasis.sum()
    cumulative = torch.cumsum(q, 0)
    drawn = torch.searchsorted(cumulative, _stratified(count, generator) * cumulative[-1]).clamp(max=len(q) - 1)
    return drawn, (p.index_select(0, drawn) / q.index_select(0, drawn))


def sample_points(mesh: Mesh, among: torch.Tensor, count: int, seed: int = 0, guide: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` points over the elements ``among`` (T,) bool, uniform by area, or with a
    ``guide`` (T,) (each element's expected error) partly by its square (``_draw``),
    stratified along the elements' cumulative probability (so every part of the surfaces
    gets its share), each at least ``EDGE_INSET`` inside its element as a pixel's point is.

    Returns:
        (N,) the element of each point, (N, 3) its barycentric coordinates, (N, 3) the point,
        (N,) its weight (1 without a guide).
    """
    generator = torch.Generator().manual_seed(seed)
    mesh = mesh.to("cpu")
    candidates = torch.nonzero(among.cpu()).flatten()
    drawn, weights = _draw(mesh.areas.index_select(0, candidates), None if guide is None else
                           guide.cpu().index_select(0, candidates), count, generator)
    element = candidates.index_select(0, drawn)
    r1, r2 = torch.rand(2, count, generator=generator, dtype=torch.float64)
    s = r1.sqrt()  # uniform over the triangle
    coordinates = inset_coordinates(torch.stack([1 - s, s * (1 - r2), s * r2], 1))
    points = (mesh.corners.index_select(0, element) * coordinates[:, :, None]).sum(1)
    return element, coordinates, points, weights


def gathered_error(mesh: Mesh, radiosity: torch.Tensor, emission: torch.Tensor, reflectance: torch.Tensor,
                   samples: int = DEFAULT_SAMPLES, resolution: int = 128, seed: int = 0,
                   shading: Shading | None = None, guide: torch.Tensor | None = None) -> GatheredError | None:
    """Estimate the displayed solution's relative RMS error by final gathers at ``samples``
    points over the non-emitting surfaces, by area (and ``guide``) (see the module's
    docstring); None where there are none.

    Args:
        mesh: the solved mesh (T elements); radiosity: (T, 3) the display radiosity.
        emission, reflectance: (T, 3) each element's.
        resolution: the gathers' hemicube resolution.
        seed: of the sampling: the same mesh and seed give the same points.
        shading: the picture drawn from ``radiosity`` (``output.shading``; default: the
            quadratic ``picture_shading``): the estimate is of what is shown.
        guide: (T,) each element's expected error, which part of the samples follow
            (``GUIDE_SHARE``); None: by area alone.
    """
    mesh = mesh.to("cpu")
    emission = torch.as_tensor(emission, dtype=torch.float64).cpu()
    among = ~(emission > 0).any(1) & (mesh.areas > 0)
    if samples <= 0 or not bool(among.any()):
        return None
    element, coordinates, points, weights = sample_points(mesh, among, samples, seed, guide)
    return _compare(mesh, radiosity, emission, reflectance, element, coordinates, points, weights, resolution,
                    shading)


def image_gathered_error(mesh: Mesh, radiosity: torch.Tensor, emission: torch.Tensor, reflectance: torch.Tensor,
                         camera: Camera, samples: int = DEFAULT_SAMPLES, resolution: int = 128,
                         seed: int = 0, mask: np.ndarray | None = None,
                         shading: Shading | None = None, guide: torch.Tensor | None = None) -> GatheredError | None:
    """As ``gathered_error``, at the surface points seen by ``samples`` pixels drawn evenly
    (stratified, seeded; with a ``guide``, partly by its square at the pixel's element) from
    those of ``camera``'s view that show a non-emitting element (and are in ``mask`` (H, W)
    bool, when given: a comparison's pixels): the error of the picture, weighted as a
    per-pixel comparison weighs it."""
    mesh = mesh.to("cpu")
    emission = torch.as_tensor(emission, dtype=torch.float64).cpu()
    element, points = pixel_points(mesh, camera)
    if mask is not None:
        element = torch.where(torch.as_tensor(np.asarray(mask, dtype=bool).reshape(-1)), element, -1)
    valid = torch.nonzero(element >= 0).flatten()
    valid = valid[~(emission[element[valid]] > 0).any(1)]
    if samples <= 0 or len(valid) == 0:
        return None
    drawn, weights = _draw(torch.ones(len(valid), dtype=torch.float64), None if guide is None else
                           guide.cpu().index_select(0, element.index_select(0, valid)), samples,
                           torch.Generator().manual_seed(seed))
    pick = valid.index_select(0, drawn)
    element, points = element[pick], points[pick]
    corners = mesh.corners.index_select(0, element)
    coordinates = inset_coordinates(barycentric(corners, points))
    points = (corners * coordinates[:, :, None]).sum(1)
    return _compare(mesh, radiosity, emission, reflectance, element, coordinates, points, weights, resolution,
                    shading)


def inset_coordinates(coordinates: torch.Tensor, inset: float = EDGE_INSET) -> torch.Tensor:
    """(N, 3) barycentric ``coordinates`` moved into their triangle: each at least ``inset``
    (a pixel centre on an edge may round outside it; ``EDGE_INSET``)."""
    coordinates = coordinates.clamp(min=0)
    coordinates = coordinates / coordinates.sum(1, keepdim=True)
    return inset + (1 - 3 * inset) * coordinates


def _compare(mesh: Mesh, radiosity, emission: torch.Tensor, reflectance, element: torch.Tensor,
             coordinates: torch.Tensor, points: torch.Tensor, weights: torch.Tensor, resolution: int,
             shading: Shading | None) -> GatheredError | None:
    """The estimate from N sampled points: (N,) their elements, (N, 3) their barycentric
    ``coordinates`` there, (N, 3) the points and (N,) their weights."""
    radiosity, reflectance = (torch.as_tensor(t, dtype=torch.float64).cpu() for t in (radiosity, reflectance))
    shading = picture_shading(mesh, radiosity) if shading is None else shading
    shown = luminance(shading.at(mesh, element, coordinates))
    normals = mesh.normals.index_select(0, element)
    gather = final_gather(mesh, radiosity, points.numpy(), normals.numpy(), resolution)
    gathered = luminance(emission.index_select(0, element) + reflectance.index_select(0, element) * gather.irradiance)
    kept = (gather.coverage - gather.front_coverage) <= HIDDEN_BACK_SHARE
    weights = weights[kept]
    e2, L2 = weights * (shown - gathered)[kept].pow(2), weights * gathered[kept].pow(2)
    n = len(e2)
    if n == 0 or float(L2.sum()) <= 0:
        return None
    ratio = float(e2.sum() / L2.sum())
    # delta method for a ratio of means: var(r) ~ var(e2 - r L2) / (n mean(L2)^2)
    spread = float((e2 - ratio * L2).var()) if n > 1 else 0.0
    ratio_error = math.sqrt(spread / n) / float(L2.mean())
    relative_rms = math.sqrt(ratio)
    return GatheredError(relative_rms, ratio_error / (2 * relative_rms) if relative_rms > 0 else 0.0, n)
