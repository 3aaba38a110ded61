"""A solution's radiosity at given surface points, for comparison with values a path tracer
computed there (the furnished room of ``scripts/peer_room.py``).

A point belongs to the element whose triangle contains it (within ``tolerance`` of its
plane, facing the point's normal); the element's own constant value is what the solve
computed there, without the display's interpolation.
"""
from __future__ import annotations

import torch

from hemirad.geometry.mesh import Mesh, barycentric


def elements_at(mesh: Mesh, points: torch.Tensor, normals: torch.Tensor, tolerance: float = 1e-4) -> torch.Tensor:
    """(N,) int64 the element under each of the (N, 3) ``points`` whose unit normal agrees
    with ``normals`` (N, 3); -1 where no element contains the point. ``tolerance`` is a
    distance relative to the mesh's bounding box diagonal."""
    corners = mesh.corners.to(points.dtype)  # (T, 3, 3)
    element_normals = mesh.normals.to(points.dtype)  # (T, 3)
    extent = float((mesh.vertices.amax(0) - mesh.vertices.amin(0)).norm())
    eps = tolerance * extent
    slack = 1e-6
    out = torch.full((len(points),), -1, dtype=torch.int64)
    for i, (p, n) in enumerate(zip(points, normals)):
        facing = (element_normals @ n) > 0.9
        on_plane = ((p - corners[:, 0]) * element_normals).sum(1).abs() < eps
        candidates = torch.nonzero(facing & on_plane).reshape(-1)
        coordinates = barycentric(corners.index_select(0, candidates), p.expand(len(candidates), 3))
        hits = candidates[(coordinates >= -slack).all(1)]
        if len(hits):
            out[i] = int(hits[0])
    return out
