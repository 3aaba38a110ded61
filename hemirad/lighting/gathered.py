"""The solution finished by final gathers (``solver.final_gather``): chosen elements take the
light a hemicube at their centroid gathers from the solved radiosity, in place of what the
shots delivered (docs/DESIGN.md §3.8).

A shot delivers a patch's light as its eye sees the receivers: a receiver that the eye sees
but a part of the patch does not gets that part's light too. Beside a contact line (a block
standing on the floor) the standing object hides much of the room at a steep angle, and the
line that divides what a receiver sees from what it does not crosses many patches:
on the Cornell box refined by the answer to 17,958 elements, floor points 1 cm outside the
tall block read up to +7% (green +15-20%) against the path tracer, most of it from
back-wall patches whose eyes see past the block's edge where a third of each patch does
not. A gather looks from the receiver itself, so no shooter's eye stands in for it: the
same points within 2.4% (``tests/test_contacts.py``). It does not resolve what the mesh
cannot; it costs one hemicube per gathered element.

``contacts`` gathers the elements within ``CONTACT_BAND`` of the initial mesh's element
side of a hole's rim in a planar surface (``geometry.patches.hole_rims``: a footprint, a lamp
hung under a ceiling); ``all`` every element (the second pass of two-pass methods).
The gathered radiosity replaces the solution's; the shots' power bookkeeping (absorbed,
escaped, unshot) stays the solve's, and stats.json says what the gathers changed.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from hemirad.geometry.footprints import point_segment_distances
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.patches import hole_rims
from hemirad.lighting.sensors import final_gather, sensor_renderer

#: ``contacts`` gathers the elements whose centroids lie within this share of the side of the
#: initial element along a rim. Measured on the Cornell box refined by the answer to 17,958
#: elements (``tests/test_contacts.py``'s 26 floor points 1 cm outside the blocks, as drawn):
#: 0.5, 1,364 elements gathered in 7.7 s, every point within 5%, the worst 2.4%, median
#: 0.8%; 1.0, 2,384 in 12.0 s, the worst 2.4%, median 0.6%; none, 23 of 26, the worst 7.3%.
#: Bands counted in the refined elements' own sides miss finer elements beside the line
#: (one side: 24 of 26; three: 26 at 1,613).
CONTACT_BAND = 0.5
#: Element-edge distances ``contact_band`` takes in one pass at most (memory: 24 bytes each).
_PAIRS_AT_ONCE = 1 << 20
#: Gathers between two calls of the ``progress`` callback.
REPORT_EVERY = 256


@dataclass(frozen=True)
class GatherReport:
    """How far the final gathers are: ``gathered`` of ``elements``, after ``seconds``."""

    gathered: int
    elements: int
    seconds: float


def contact_band(initial: Mesh, mesh: Mesh, share: float = CONTACT_BAND) -> torch.Tensor:
    """(T,) bool the elements of ``mesh`` (``initial`` or a refinement of it, with the same
    surfaces) whose centroids lie within ``share`` of an initial rim element's side
    (sqrt(2 x area)) of that element's rim edge, in the same surface."""
    rims = hole_rims(initial)  # on the initial mesh: a refined one's hanging vertices read as rims
    vertices = initial.vertices.cpu().numpy()
    sides = np.sqrt(2.0 * initial.areas.cpu().numpy())
    centroids = mesh.centroids.cpu().numpy()
    surface = mesh.surface.cpu().numpy()
    chosen = np.zeros(len(centroids), dtype=bool)
    for rim in rims:
        edges = np.stack([vertices[rim.a], vertices[rim.b]], axis=1)  # (m, 2, 3)
        reach = share * sides[rim.element][None]  # (1, m)
        own = np.flatnonzero(surface == rim.surface)
        for part in np.array_split(own, max(1, -(-len(own) * len(rim.a) // _PAIRS_AT_ONCE))):
            chosen[part] |= (point_segment_distances(centroids[part], edges) < reach).any(1)
    return torch.from_numpy(chosen)


def finished_radiosity(mode: str, initial: Mesh, mesh: Mesh, radiosity: torch.Tensor, emission: torch.Tensor,
                       reflectance: torch.Tensor, ambient: torch.Tensor, resolution: int,
                       progress: Callable[[GatherReport], None] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, 3) the solution's ``radiosity`` finished as ``solver.final_gather`` ``mode``
    (``contacts`` or ``all``) asks, on ``mesh`` refined from ``initial``, and the (n,) int64
    elements gathered. The other arguments as ``gathered_radiosity``'s."""
    chosen = contact_band(initial, mesh) if mode == "contacts" else torch.ones(mesh.num_elements, dtype=torch.bool)
    elements = torch.nonzero(chosen).flatten()
    return gathered_radiosity(mesh, radiosity, emission, reflectance, ambient, elements, resolution, progress), elements


def gathered_radiosity(mesh: Mesh, radiosity: torch.Tensor, emission: torch.Tensor, reflectance: torch.Tensor,
                       ambient: torch.Tensor, elements: torch.Tensor, resolution: int,
                       progress: Callable[[GatherReport], None] | None = None) -> torch.Tensor:
    """(T, 3) ``radiosity`` with the ``elements`` (n,) int64 given the light a hemicube at their
    centroids gathers: B_k = E_k + rho_k sum_j F_kj (B_j + rho_j a) - rho_k a, so that what is
    shown (B + rho a, with the ambient radiosity ``ambient`` (3,)) is what the gather sees.

    Args:
        mesh: the solved mesh (T elements); radiosity, emission, reflectance: (T, 3) float64.
        resolution: the hemicubes' (their top face's side in pixels).
        progress: called with a ``GatherReport`` every ``REPORT_EVERY`` gathers and at the end.
    """
    radiosity = radiosity.clone()
    elements = torch.as_tensor(elements, dtype=torch.int64)
    if len(elements) == 0:
        return radiosity
    start = time.perf_counter()
    shown = radiosity + reflectance * ambient
    points = mesh.centroids[elements].cpu().numpy()
    normals = mesh.normals[elements].cpu().numpy()
    irradiance = []
    with sensor_renderer(mesh, points, resolution) as renderer:
        for first in range(0, len(points), REPORT_EVERY):
            part = slice(first, first + REPORT_EVERY)
            irradiance.append(final_gather(mesh, shown, points[part], normals[part], renderer=renderer).irradiance)
            if progress is not None:
                progress(GatherReport(min(first + REPORT_EVERY, len(points)), len(points), time.perf_counter() - start))
    rho = reflectance[elements]
    radiosity[elements] = emission[elements] + rho * torch.cat(irradiance) - rho * ambient
    return radiosity
