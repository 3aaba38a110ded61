"""A triangulation of a planar region whose outline and given lines are element edges.

The region (a shapely Polygon or MultiPolygon, holes allowed) and the lines inside it make
a planar straight-line graph. Its segments are cut into pieces of at most ``element_size``;
the interior gets the Steiner points it is given (the surface's own element grid) that lie
inside the region and more than half an element from every segment, so the triangles beside
a segment are not slivers. The Delaunay triangulation of all these points (scipy's Qhull)
is made *conforming*: a segment that is not an edge of it is split at its midpoint and the
points triangulated again, until every segment is a union of edges. A Delaunay
triangulation that has every segment as edges is the constrained Delaunay triangulation of
its points, so no triangle straddles a segment, and a triangle's centroid tells whether it
lies in the region (the ones in holes and footprints are dropped). Deterministic: the same
input gives the same triangles.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
from scipy.spatial import Delaunay, cKDTree
from shapely.geometry.base import BaseGeometry

#: Steiner points closer than this many element sizes to a segment are left out: a grid
#: point just beside an outline would make a sliver with two of its points.
CLEARANCE = 0.5

#: Rounds of splitting the segments a Delaunay triangulation misses: each round halves
#: them, and the bundled scenes need none or one.
MAX_ROUNDS = 40

#: Triangles with a smaller angle (degrees) get a point at their circumcentre.
MIN_ANGLE = 28.0

#: At most this many rounds of such points.
QUALITY_ROUNDS = 12


def triangulate(region: BaseGeometry, lines: list[np.ndarray], interior: np.ndarray, element_size: float,
                tolerance: float, quality_rounds: int = QUALITY_ROUNDS,
                min_angle: float = MIN_ANGLE, thin: BaseGeometry | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mesh ``region`` with triangles of about ``element_size``, its outline and ``lines``
    ((2, 2) segments inside it) as element edges.

    Args:
        region: a Polygon or MultiPolygon in 2D.
        lines: segments inside the region that must be element edges (contact lines).
        interior: (P, 2) candidate Steiner points, about ``element_size`` apart (the
            surface's element grid); those outside the region or within ``CLEARANCE``
            element sizes of the outline or a line are left out.
        element_size: target edge length: outline and lines are divided into pieces no
            longer than it.
        tolerance: points closer than this are one point.
        quality_rounds: rounds of circumcentres where an angle is under ``MIN_ANGLE``; 0
            adds no point the outline and lines do not need, so no point lands on the
            outline between its given points (the triangle of a curved surface cut in
            place keeps its edges as its neighbours see them).
        min_angle: the angle (degrees) under which a triangle gets a circumcentre; a
            surface whose own grid is thinner (a narrow quad) asks no better of its cuts.
        thin: where triangles are meant to be thin (strips along creases, bounded by
            ``lines``): those inside it get no circumcentre.

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
    steiner = _steiner_points(region, points, segments, np.asarray(interior, dtype=np.float64).reshape(-1, 2),
                              CLEARANCE * element_size)
    points, tris = _conforming_delaunay(np.concatenate([points, steiner]), segments, region, quality_rounds,
                                        min_angle, thin)
    corners = points[tris]
    signed = _signed_areas(corners)
    tris = np.where((signed < 0)[:, None], tris[:, [0, 2, 1]], tris)
    # every triangle is on one side of every segment, so its centroid tells where it lies
    inside = shapely.contains_xy(region, *corners.mean(axis=1).T)
    tris = tris[inside & (np.abs(signed) > 0)]
    used, index = np.unique(tris, return_inverse=True)
    return points[used], index.reshape(-1, 3).astype(np.int64)


def _steiner_points(region: BaseGeometry, points: np.ndarray, segments: np.ndarray, candidates: np.ndarray,
                    clearance: float) -> np.ndarray:
    """(Q, 2) the ``candidates`` inside ``region`` farther than ``clearance`` from every
    segment (S, 2) of ``points`` (N, 2), in their given order, each once."""
    if not len(candidates):
        return candidates
    candidates = candidates[np.sort(np.unique(candidates, axis=0, return_index=True)[1])]
    inside = shapely.contains_xy(region, candidates[:, 0], candidates[:, 1])
    lines = shapely.multilinestrings(points[segments])
    far = shapely.distance(shapely.points(candidates), lines) > clearance
    return candidates[inside & far]


def _conforming_delaunay(points: np.ndarray, segments: np.ndarray, region: BaseGeometry,
                         quality_limit: int, min_angle: float,
                         thin: BaseGeometry | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The Delaunay triangulation of (N, 2) ``points`` with every segment (S, 2) a union of
    its edges, refined where a triangle in ``region`` has an angle under ``min_angle``.

    A segment the triangulation misses is split at its midpoint. A bad triangle gets a
    point at its circumcentre (Ruppert 1995), unless that point falls within a segment's
    diametral circle: then the segment is split instead, so no point lands beside a
    segment. At most ``quality_limit`` rounds of that: a corner of the input sharper than
    ``min_angle`` cannot be mended and is left as it is. Triangles inside ``thin`` are
    left thin.

    Returns:
        points: (N', 2) the points, those added appended.
        triangles: (T, 3) int64, the whole convex hull's.
    """
    segments = np.sort(segments, axis=1)
    quality_rounds = 0
    for _ in range(MAX_ROUNDS + quality_limit):
        tris = Delaunay(points).simplices.astype(np.int64)
        edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
        n = len(points)
        have = np.isin(segments[:, 0] * n + segments[:, 1], edges[:, 0] * n + edges[:, 1])
        split = ~have
        centres = np.zeros((0, 2))
        if have.all():
            if quality_rounds == quality_limit:
                return points, tris
            corners = points[tris]
            centroids = corners.mean(axis=1).T
            inside = shapely.contains_xy(region, *centroids)
            if thin is not None:
                inside &= ~shapely.contains_xy(thin, *centroids)
            bad = inside & (min_angles(corners) < min_angle) & (np.abs(_signed_areas(corners)) > 0)
            if not bad.any():
                return points, tris
            quality_rounds += 1
            centres = _spread(*_circumcircles(corners[bad]))
            a, b = points[segments[:, 0]], points[segments[:, 1]]
            middle, radius = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=1)
            encroached = np.linalg.norm(centres[:, None] - middle[None], axis=-1) < radius[None]  # (C, S)
            split = encroached.any(axis=0)
            keep = ~encroached.any(axis=1) & shapely.contains_xy(region, centres[:, 0], centres[:, 1])
            centres = centres[keep]
        missed = segments[split]
        halves = 0.5 * (points[missed[:, 0]] + points[missed[:, 1]])
        new = np.arange(n, n + len(missed))
        points = np.concatenate([points, halves, centres])
        segments = np.concatenate([segments[~split], np.stack([missed[:, 0], new], 1), np.stack([new, missed[:, 1]], 1)])
        segments = np.sort(segments, axis=1)
    raise RuntimeError(f"conforming Delaunay: segments still missed after {MAX_ROUNDS} rounds of splitting")


def min_angles(corners: np.ndarray) -> np.ndarray:
    """(T,) the smallest angle, in degrees, of each of (T, 3, 2) triangles."""
    sides = np.linalg.norm(corners[:, [1, 2, 0]] - corners[:, [2, 0, 1]], axis=-1)  # side k faces corner k
    shortest = sides.min(axis=1)
    others = np.sort(sides, axis=1)[:, 1:]
    cos = (others[:, 0] ** 2 + others[:, 1] ** 2 - shortest ** 2) / np.maximum(2 * others[:, 0] * others[:, 1], 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _circumcircles(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) the circumcentres and (T,) circumradii of (T, 3, 2) non-degenerate triangles."""
    a = corners[:, 0]
    b, c = corners[:, 1] - a, corners[:, 2] - a
    d = 2 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    bb, cc = (b * b).sum(1), (c * c).sum(1)
    offset = np.stack([(c[:, 1] * bb - b[:, 1] * cc) / d, (b[:, 0] * cc - c[:, 0] * bb) / d], axis=1)
    return a + offset, np.linalg.norm(offset, axis=1)


def _spread(centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """The (C, 2) ``centres`` to insert in one round, each farther than half its radius
    (C,) from those kept before it: neighbouring bad triangles often share (nearly) one
    circumcircle, and two points inserted almost together would make a sliver."""
    kept: list[int] = []
    tree = cKDTree(centres)
    taken = np.zeros(len(centres), dtype=bool)
    for i in range(len(centres)):
        near = tree.query_ball_point(centres[i], 0.5 * radii[i])
        if not taken[near].any():
            kept.append(i)
            taken[i] = True
    return centres[kept]


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
    # only the points the segments use, each once
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
