"""Where a surface lies in partial shadow: the share of the emitters each point sees.

Used to check that refinement follows shadow edges. From a point on a surface, the
hemicube's form factor to the emitters divided by Lambert's unoccluded one is the visible
fraction of the light (cosine-weighted): 1 in full light, 0 in the umbra, in between in the
penumbra.
"""
from __future__ import annotations

import numpy as np
import torch

from hemirad.geometry.analytic import point_to_triangles
from hemirad.geometry.mesh import Mesh
from hemirad.scene.meshing import build_mesh
from hemirad.scene.model import Scene
from hemirad.transport.formfactor import delta_form_factors
from hemirad.transport.hemicube import Hemicube, tangent_frame
from hemirad.transport.renderer import clip_planes


def visible_light_fraction(mesh: Mesh, emitting: torch.Tensor, points: torch.Tensor, normal: torch.Tensor,
                           resolution: int = 64) -> torch.Tensor:
    """Share of the emitters' unoccluded form factor that each point actually sees.

    Args:
        mesh: the scene.
        emitting: (T,) bool, the emitting elements.
        points: (N, 3) positions on one surface; normal: (3,) its unit normal.
    Returns:
        (N,) float64 in [0, 1] (NaN where no emitter is above the point's horizon).
    """
    weights = delta_form_factors(resolution)
    lamp = mesh.corners[emitting]
    near, far = clip_planes(mesh)
    normal = torch.as_tensor(normal, dtype=torch.float64)
    frame = tangent_frame(normal.numpy(), np.array([1.0, 0.0, 0.0]) + np.array([0.0, 0.0, 1e-3]))
    hemicube = Hemicube(resolution)
    try:
        hemicube.set_geometry(mesh.vertices, mesh.triangles)
        out = torch.empty(len(points), dtype=torch.float64)
        for i, p in enumerate(points):
            eye = p + near * normal
            element, front = (torch.from_numpy(x) for x in hemicube.render(eye.numpy(), frame, near, far))
            sees_light = front & (element >= 0) & emitting[element.clamp(min=0)]
            unoccluded = point_to_triangles(eye, normal, lamp).sum()
            out[i] = weights[sees_light].sum() / unoccluded if unoccluded > 0 else float("nan")
    finally:
        hemicube.release()
    return out.clamp(0.0, 1.0)


def surface_grid(mesh: Mesh, surface: int, count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A count x count grid of cell centres over a planar surface's bounding rectangle.

    Returns:
        points (count^2, 3), the surface's unit normal (3,), and the in-plane axes (2, 3)
        along which the grid runs (for locating other points in it, ``grid_cell``).
    """
    corners = mesh.corners[mesh.surface == surface]
    normal = mesh.normals[mesh.surface == surface].mean(0)
    normal = normal / normal.norm()
    u = torch.linalg.cross(normal, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    if u.norm() < 1e-6:
        u = torch.linalg.cross(normal, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    u = u / u.norm()
    v = torch.linalg.cross(normal, u)
    axes = torch.stack([u, v])
    flat = corners.reshape(-1, 3)
    coords = flat @ axes.T  # (M, 2)
    lo, hi = coords.min(0).values, coords.max(0).values
    offset = float(flat[0] @ normal)
    t = (torch.arange(count, dtype=torch.float64) + 0.5) / count
    a, b = torch.meshgrid(lo[0] + t * (hi[0] - lo[0]), lo[1] + t * (hi[1] - lo[1]), indexing="ij")
    points = a.reshape(-1, 1) * u + b.reshape(-1, 1) * v + offset * normal
    return points, normal, axes


def grid_cell(points: torch.Tensor, grid: torch.Tensor, axes: torch.Tensor, count: int) -> torch.Tensor:
    """(N,) index of the cell of a ``surface_grid`` that each point falls in."""
    g = grid @ axes.T
    lo, hi = g.min(0).values, g.max(0).values
    step = (hi - lo) / max(count - 1, 1)
    ij = torch.round((points @ axes.T - lo) / step).long().clamp(0, count - 1)
    return ij[:, 0] * count + ij[:, 1]


def floor_penumbra(scene: Scene, count: int, band: tuple[float, float], resolution: int = 128
                   ) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The penumbra on ``scene``'s floor (the surface whose name ends in ``floor``): a
    ``count`` x ``count`` grid over it (``surface_grid``) and which of its points see
    between ``band`` of the emitters' unoccluded form factor (``visible_light_fraction``, on
    the scene's unrefined mesh).

    Returns:
        (count, count, 3) the grid's points, (count, count) bool the band, and the floor's
        surface index (the same in refined meshes: refinement keeps surfaces).
    """
    mesh = build_mesh(scene)
    floor = next(i for i, name in enumerate(mesh.surface_names) if name.endswith("floor"))
    emitting = (scene.emission_table()[mesh.material] > 0).any(1)
    points, normal, _ = surface_grid(mesh, floor, count)
    seen = visible_light_fraction(mesh, emitting, points, normal, resolution)
    return points.reshape(count, count, 3), ((seen > band[0]) & (seen < band[1])).reshape(count, count), floor
