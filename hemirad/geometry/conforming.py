"""A quality triangulation of a planar region whose outline and given lines are element edges.

The region (a shapely Polygon or MultiPolygon, holes allowed) and the lines inside it make
a planar straight-line graph; Shewchuk's Triangle (the ``triangle`` package) meshes it as
a constrained Delaunay triangulation refined to a minimum angle and a maximum area, so no
triangle straddles a line or the outline and none is a sliver. Deterministic: the same
input gives the same triangles.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
import triangle
from scipy.spatial import cKDTree
from shapely.geometry.base import BaseGeometry

#: Triangle's quality bound: no angle under this many degrees (it terminates up to ~33.8),
#: so none over 180 - 2 x 30 = 120 either, except where the outline itself has a smaller angle.
MIN_ANGLE = 30.0

#: The largest triangle, in units of element_size^2: a grid's cell of side element_size
#: makes two triangles of 0.5; quality refinement leaves most triangles well under the
#: bound, so this one gives about the grid's element count (measured: 0.9-1.1 times).
MAX_AREA = 0.8


def triangulate(region: BaseGeometry, lines: list[np.ndarray], element_size: float,
                tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh ``region`` with triangles of about ``element_size``, its outline and ``lines``
    ((2, 2) segments inside it) as element edges.

    Args:
        region: a Polygon or MultiPolygon in 2D.
        lines: segments inside the region that must be element edges (contact lines).
        element_size: target edge length: outline and lines are divided into pieces no
            longer than it, triangles are no larger than ``MAX_AREA`` element_size^2.
        tolerance: points closer than this are one point.

    Returns:
        points: (N, 2) float64.
        triangles: (T, 3) int64, counter-clockwise, every one inside the region.
    """
    points, segments = _graph(region, lines, tolerance)
    points, segments = _divide(points, segments, element_size)
    unique, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    if len(unique) < len(points):  # a division point on another point: one point, kept first
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        points, segments = points[np.sort(first)], rank[inverse.reshape(-1)][segments]
        segments = np.unique(np.sort(segments[segments[:, 0] != segments[:, 1]], axis=1), axis=0)
    # Triangle reads its area bound as digits and a point (no exponent), so it meshes the
    # region scaled to element_size 1; the input points keep their exact coordinates.
    centre = points.min(axis=0)
    scaled = (points - centre) / element_size
    # No hole points: the wrapper hands Triangle's output the input's hole list and frees
    # both (a double free). Holes are meshed too and their triangles dropped below.
    out = triangle.triangulate({"vertices": scaled, "segments": segments}, f"pq{MIN_ANGLE:g}a{MAX_AREA:g}Q")
    found = np.asarray(out["vertices"], dtype=np.float64) * element_size + centre
    found[:len(points)] = points  # Triangle keeps the input points first, in order
    tris = np.asarray(out["triangles"], dtype=np.int64).reshape(-1, 3)
    corners = found[tris]
    signed = _signed_areas(corners)
    tris = np.where((signed < 0)[:, None], tris[:, [0, 2, 1]], tris)
    # every triangle is on one side of every segment, so its centroid tells where it lies
    inside = shapely.contains_xy(region, *corners.mean(axis=1).T)
    tris = tris[inside & (np.abs(signed) > 0)]
    used, index = np.unique(tris, return_inverse=True)
    return found[used], index.reshape(-1, 3).astype(np.int64)


def _signed_areas(corners: np.ndarray) -> np.ndarray:
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _graph(region: BaseGeometry, lines: list[np.ndarray], tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) points and (S, 2) segments: the region's rings and the lines, with points
    closer than ``tolerance`` merged and line ends that fall on a ring's edge splitting it."""
    rings = [np.asarray(ring.coords)[:-1] for polygon in shapely.get_parts(region)
             for ring in (polygon.exterior, *polygon.interiors)]
    points = [p for ring in rings for p in ring]
    edges = []
    start = 0
    for ring in rings:
        n = len(ring)
        edges += [[start + i, start + (i + 1) % n] for i in range(n)]
        start += n
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    for line in lines:
        ends = []
        for p in line:
            index = _merge(points, p, tolerance)
            if index is None:
                points = np.vstack([points, p])
                index = len(points) - 1
                edges = _split_edge_at(points, edges, index, tolerance)
            ends.append(index)
        if ends[0] != ends[1]:
            edges = np.vstack([edges, ends])
    # merge what still lies within tolerance (rings that touch), keeping the first of each group
    if len(points) > 1:
        pairs = np.asarray(sorted(cKDTree(points).query_pairs(tolerance)), dtype=np.int64).reshape(-1, 2)
        target = np.arange(len(points))
        for i, j in pairs:  # i < j: every point goes to the smallest index in reach
            target[j] = min(target[j], target[i])
        edges = target[edges]
    edges = np.sort(edges, axis=1)
    edges = np.unique(edges[edges[:, 0] != edges[:, 1]], axis=0)
    # only the points the segments use, each once: Triangle (through its wrapper) crashes
    # on a duplicate point
    used, index = np.unique(edges, return_inverse=True)
    return points[used], index.reshape(-1, 2).astype(np.int64)


def _merge(points: np.ndarray, p: np.ndarray, tolerance: float) -> int | None:
    d = np.linalg.norm(points - p, axis=1)
    i = int(np.argmin(d)) if len(d) else -1
    return i if i >= 0 and d[i] <= tolerance else None


def _split_edge_at(points: np.ndarray, edges: np.ndarray, index: int, tolerance: float) -> np.ndarray:
    """Edges with the one that point ``index`` lies on (within ``tolerance``) split there."""
    p = points[index]
    a, b = points[edges[:, 0]], points[edges[:, 1]]
    ab = b - a
    t = ((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-300)
    distance = np.linalg.norm(a + np.clip(t, 0, 1)[:, None] * ab - p, axis=1)
    hit = np.flatnonzero((distance <= tolerance) & (t > 0) & (t < 1))
    if not len(hit):
        return edges
    k = int(hit[0])
    first, second = [edges[k, 0], index], [index, edges[k, 1]]
    return np.vstack([np.delete(edges, k, axis=0), [first, second]])


def _divide(points: np.ndarray, edges: np.ndarray, element_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Every segment cut into equal pieces no longer than ``element_size``."""
    new_points, new_edges = [points], []
    count = len(points)
    for a, b in edges:
        length = float(np.linalg.norm(points[b] - points[a]))
        n = max(1, math.ceil(length / element_size - 1e-9))
        if n == 1:
            new_edges.append([[a, b]])
            continue
        t = np.arange(1, n)[:, None] / n
        new_points.append(points[a] + t * (points[b] - points[a]))
        chain = np.concatenate([[a], np.arange(count, count + n - 1), [b]])
        new_edges.append(np.stack([chain[:-1], chain[1:]], axis=1))
        count += n - 1
    return np.concatenate(new_points), np.concatenate(new_edges).astype(np.int64).reshape(-1, 2)
