"""A solution's radiosity at given surface points, for comparison with values a path tracer
computed there (the furnished room of ``scripts/peer_room.py``).

A point belongs to the element whose triangle contains it (within ``tolerance`` of its
plane, facing the point's normal); the element's own constant value is what the solve
computed there, without the display's interpolation.
"""
from __future__ import annotations

import torch

from hemirad.geometry.mesh import Mesh


def elements_at(mesh: Mesh, points: torch.Tensor, normals: torch.Tensor, tolerance: float = 1e-4) -> torch.Tensor:
    """(N,) int64 the element under each of the (N, 3) ``points`` whose unit normal agrees
    with ``normals`` (N, 3); -1 where no element contains the point. ``tolerance`` is a
    distance relative to the mesh's bounding box diagonal."""
    corners = mesh.corners.to(points.dtype)  # (T, 3, 3)
    element_normals = mesh.normals.to(points.dtype)  # (T, 3)
    extent = float((mesh.vertices.amax(0) - mesh.vertices.amin(0)).norm())
    eps = tolerance * extent
    out = torch.full((len(points),), -1, dtype=torch.int64)
    a, e1, e2 = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    # barycentric coordinates of each point in each triangle's plane (Gram matrix solve)
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    det = d11 * d22 - d12 * d12
    for i, (p, n) in enumerate(zip(points, normals)):
        facing = (element_normals @ n) > 0.9
        offset = p - a
        on_plane = (offset * element_normals).sum(1).abs() < eps
        q1, q2 = (offset * e1).sum(1), (offset * e2).sum(1)
        u = (d22 * q1 - d12 * q2) / det
        v = (d11 * q2 - d12 * q1) / det
        slack = 1e-6
        inside = facing & on_plane & (u >= -slack) & (v >= -slack) & (u + v <= 1 + slack)
        hits = torch.nonzero(inside).reshape(-1)
        if len(hits):
            out[i] = int(hits[0])
    return out
