"""Where triangles cross planes: the segments along which a surface is cut.

A surface crosses a plane where it has triangles on both sides of it:

* a triangle with corners farther than the tolerance on both sides crosses it along the
  segment joining its corners on the plane and the points where its edges pass through.
  An edge's point is interpolated from its corner above the plane towards the one below,
  so two triangles sharing the edge (and the plane) get the same point to the last bit,
  and their segments meet exactly;
* where the crossing runs along the triangles' own edges (a shelf whose grid has a line
  of vertices just where a box's side is), an edge lying in the plane with a triangle
  rising on each side of it.

What only touches the plane, triangles on one side of it (a box's side standing on a
floor, a lamp's barrel ending on the ceiling), is not a crossing: a contact is not a cut,
and contact meshing (``footprints``) deals with it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def crossing_segments(origins: np.ndarray, normals: np.ndarray, corners: np.ndarray, tolerance: float,
                      planes: np.ndarray | None = None, along_edges: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Row by row, triangle ``corners[n]`` (N, 3, 3) against the plane through
    ``origins[n]`` (N, 3) with unit normal ``normals[n]`` (N, 3) (broadcast: one plane
    for all rows is fine). ``planes`` (N,) int says which rows share a plane (default: all
    do); an edge in the plane counts where rows of that plane rise from it on both sides.
    ``along_edges=False`` leaves those out: only the triangles that pass through.

    Returns:
        rows: (M,) int64 the row each segment comes from.
        segments: (M, 2, 3) float64 where the surfaces cross the planes.
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 3, 3)
    origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), (len(corners), 3))
    normals = np.broadcast_to(np.asarray(normals, dtype=np.float64), (len(corners), 3))
    height = np.einsum("nki,ni->nk", corners - origins[:, None], normals)  # (N, 3)
    side = np.where(height > tolerance, 1, np.where(height < -tolerance, -1, 0))
    crossing = np.flatnonzero((side.max(axis=1) == 1) & (side.min(axis=1) == -1))
    rows, segments = [crossing], [_through(corners[crossing], height[crossing], side[crossing])]
    if along_edges:
        plane = np.zeros(len(corners), dtype=np.int64) if planes is None else np.asarray(planes)
        edge_rows, edges = _edges_risen_from_both_sides(corners, side, plane, tolerance)
        rows.append(edge_rows)
        segments.append(edges)
    return np.concatenate(rows).astype(np.int64), np.concatenate(segments).reshape(-1, 2, 3)


def _through(c: np.ndarray, h: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(M, 2, 3) the segments where (M, 3, 3) triangles ``c`` with corner heights ``h`` and
    sides ``s`` (M, 3) (-1, 0, 1), each with corners on both sides, pass through the plane."""
    if not len(c):
        return np.zeros((0, 2, 3))
    nxt = [1, 2, 0]
    a, b = c, c[:, nxt]  # (M, 3, 3): edge k runs from corner k to corner k + 1
    ha, hb = h, h[:, nxt]
    through = s * s[:, nxt] == -1  # (M, 3): the edge passes through the plane
    above_first = ha > 0
    top = np.where(above_first[..., None], a, b)
    bottom = np.where(above_first[..., None], b, a)
    h_top = np.where(above_first, ha, hb)
    h_bottom = np.where(above_first, hb, ha)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(through, h_top / (h_top - h_bottom), 0.0)
    edge_points = top + t[..., None] * (bottom - top)
    points = np.concatenate([edge_points, c], axis=1)  # (M, 6, 3): three edge points, three corners
    valid = np.concatenate([through, s == 0], axis=1)  # exactly two per crossing triangle
    pick = np.argsort(~valid, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(points, pick[..., None], axis=1)


def _edges_risen_from_both_sides(corners: np.ndarray, side: np.ndarray, plane: np.ndarray,
                                 tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows (M,) and edges (M, 2, 3) lying in their plane with a triangle of the same
    plane (``plane`` (N,) ids) rising on the other side of the same edge (its ends within
    ``tolerance``), once each: from the triangle above."""
    lying = np.flatnonzero(((side == 0).sum(axis=1) == 2) & (side != 0).any(axis=1))
    none = (np.zeros(0, dtype=np.int64), np.zeros((0, 2, 3)))
    if not len(lying):
        return none
    off = np.argmax(side[lying] != 0, axis=1)  # the corner off the plane
    ends = np.stack([corners[lying, (off + 1) % 3], corners[lying, (off + 2) % 3]], axis=1)  # (L, 2, 3)
    up = side[lying, off] > 0
    if not up.any() or up.all():
        return none
    # an edge is the same edge either way round; the plane id apart by more than any coordinate
    apart = plane[lying, None] * 4.0 * (1.0 + np.abs(ends).max())
    above, below = np.flatnonzero(up), np.flatnonzero(~up)
    tree = cKDTree(np.concatenate([ends[below].reshape(-1, 6), apart[below]], axis=1))
    matched = np.zeros(len(above), dtype=bool)
    for order in ([0, 1], [1, 0]):
        key = np.concatenate([ends[above][:, order].reshape(-1, 6), apart[above]], axis=1)
        matched |= tree.query(key, distance_upper_bound=2 * tolerance)[0] < np.inf
    chosen = above[matched]
    return lying[chosen], ends[chosen]
