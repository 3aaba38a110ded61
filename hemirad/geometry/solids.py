"""Closed solids among a scene's surfaces, and whether points lie inside them.

A solid is a set of surfaces whose triangles close up: every edge is met by as many
triangles running one way along it as the other, and the enclosed volume is positive
(the triangles face out). A box, a watertight mesh file, a cuboid described as six quads,
a lamp's open barrel together with the mesh of its two caps: each is one. A room faces in
(its volume is negative: what it encloses is everything outside it) and an open mesh (a
teapot without a bottom) does not close, so neither is a solid.

Surfaces are joined into solids through edges that exactly two triangles share, one each
way (after merging corners closer than the tolerance): a box whose edge lies along a
room's edge meets it in a four-triangle edge, and stays a solid of its own.

Inside is decided by a ray: from the point along a fixed direction, the faces it leaves
through less those it enters through is 1 inside a closed outward surface and 0 outside,
whatever its shape (the winding number). The faces a ray may meet are found through a
grid over the plane across the ray, so a point costs the few triangles over its cell,
not the whole solid. Three directions, none along an axis, vote: a ray grazing an edge
(which could count it twice or not at all) is outvoted. A point on the surface (within
the tolerance) counts as outside: a floor's elements under a box's bottom face are not
inside the box.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from hemirad.core.fastops import cross3

#: The rays' directions: unit vectors along no axis and no face of an axis-aligned box.
DIRECTIONS = np.array([[0.5381, 0.7164, 0.4437], [-0.6125, 0.3261, 0.7203], [0.2897, -0.8391, 0.4602]])
DIRECTIONS = DIRECTIONS / np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)

#: The grid across a ray has at most this many cells along a side.
MAX_CELLS = 256

#: Cells are made larger until the (cell, triangle) pairs are at most this many per triangle
#: (or a million): a solid's few large faces must not each cover the whole grid's cells.
CELLS_PER_TRIANGLE = 8


@dataclass(frozen=True)
class Solid:
    """A closed, outward-facing set of triangles.

    Attributes:
        corners: (K, 3, 3) float64 its triangles.
        members: the indices of the shells (as given to ``closed_solids``) it is made of.
        low, high: (3,) its bounding box.
    """

    corners: np.ndarray
    members: frozenset[int]
    low: np.ndarray
    high: np.ndarray

    def contains(self, points: np.ndarray, tolerance: float) -> np.ndarray:
        """(P,) bool: which of ``points`` (P, 3) lie inside, farther than ``tolerance`` from
        its surface."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inside = np.zeros(len(points), dtype=bool)
        rows = np.flatnonzero(((points >= self.low - tolerance) & (points <= self.high + tolerance)).all(axis=1))
        if not len(rows):
            return inside
        p = points[rows]
        votes = np.zeros(len(rows), dtype=np.int64)
        on = np.zeros(len(rows), dtype=bool)
        for k, direction in enumerate(DIRECTIONS):
            point, triangle = _under_ray(p, self.corners, direction, tolerance)
            votes += _crossings(p, self.corners, direction, point, triangle) > 0
            if k == 0:  # the triangles a point lies on are over its cell in every grid
                on[point[_on_triangles(p[point], self.corners[triangle], tolerance)]] = True
        inside[rows] = (votes >= 2) & ~on
        return inside


def closed_solids(shells: list[tuple[np.ndarray, np.ndarray]], tolerance: float) -> list[Solid]:
    """The solids the shells make, each shell (vertices (V, 3), triangles (T, 3)) being the
    outline triangles of one surface (a quad's two, a mesh patch's own)."""
    if not shells:
        return []
    vertices = np.concatenate([v for v, _ in shells]).astype(np.float64)
    offsets = np.cumsum([0] + [len(v) for v, _ in shells])
    triangles = np.concatenate([t + o for (_, t), o in zip(shells, offsets)]).astype(np.int64).reshape(-1, 3)
    owner = np.repeat(np.arange(len(shells)), [len(t) for _, t in shells])
    triangles = _merge_corners(vertices, tolerance)[triangles]
    proper = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) & \
        (triangles[:, 2] != triangles[:, 0])
    triangles, owner = triangles[proper], owner[proper]
    if not len(triangles):
        return []

    # directed edges, and for each undirected edge how many run each way
    tail = triangles.reshape(-1)
    head = triangles[:, [1, 2, 0]].reshape(-1)
    face = np.repeat(np.arange(len(triangles)), 3)
    key = np.minimum(tail, head) * len(vertices) + np.maximum(tail, head)
    step = np.where(tail < head, 1, -1)
    unique, edge = np.unique(key, return_inverse=True)
    ahead = np.bincount(edge, weights=step > 0, minlength=len(unique))
    behind = np.bincount(edge, weights=step < 0, minlength=len(unique))

    # triangles joined through edges two triangles share, one each way
    order = np.argsort(edge, kind="stable")
    starts = np.r_[0, np.flatnonzero(np.diff(edge[order])) + 1]  # each edge's first directed edge
    joining = np.flatnonzero((ahead == 1) & (behind == 1))
    pairs = np.stack([face[order[starts[joining]]], face[order[starts[joining] + 1]]], axis=1)
    n = len(triangles)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, label = connected_components(graph, directed=False)

    # closed: within a component, every edge run as often one way as the other
    combined = label[face] * len(unique) + edge
    per_edge, where = np.unique(combined, return_inverse=True)
    unbalanced = np.bincount(where, weights=step) != 0
    open_component = np.zeros(count, dtype=bool)
    open_component[per_edge[unbalanced] // len(unique)] = True
    corners = vertices[triangles]
    volume = np.bincount(label, weights=np.einsum("ij,ij->i", corners[:, 0],
                                                  cross3(corners[:, 1], corners[:, 2])) / 6.0, minlength=count)
    area = np.bincount(label, weights=0.5 * np.linalg.norm(
        cross3(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1), minlength=count)
    # no thicker than the tolerance (a quad and its reverse, back to back): no inside
    closed = np.flatnonzero(~open_component & (volume > tolerance * area))
    by_component = np.argsort(label, kind="stable")
    bounds = np.searchsorted(label[by_component], np.arange(count + 1))
    solids = []
    for component in closed:
        rows = by_component[bounds[component]:bounds[component + 1]]
        c = corners[rows]
        solids.append(Solid(c, frozenset(np.unique(owner[rows]).tolist()),
                            c.reshape(-1, 3).min(axis=0), c.reshape(-1, 3).max(axis=0)))
    return solids


def _merge_corners(vertices: np.ndarray, tolerance: float) -> np.ndarray:
    """(V,) for each vertex the smallest index of the vertices within ``tolerance`` of it
    (transitively): a quad's corner given in a scene file and the same corner in a mesh
    file read as 32-bit floats are one."""
    target = np.arange(len(vertices))
    pairs = np.asarray(sorted(cKDTree(vertices).query_pairs(tolerance)), dtype=np.int64).reshape(-1, 2)
    if len(pairs):
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(vertices),) * 2)
        _, label = connected_components(graph, directed=False)
        smallest = np.full(label.max() + 1, len(vertices))
        np.minimum.at(smallest, label, target)
        target = smallest[label]
    return target


def _under_ray(points: np.ndarray, corners: np.ndarray, direction: np.ndarray,
               tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(M,) point and (M,) triangle indices: for each of ``points`` (P, 3), the triangles
    of (K, 3, 3) ``corners`` over its cell of a grid across ``direction`` (3,), their
    bounding boxes widened by ``tolerance``: every triangle its ray can meet, and every
    triangle it lies on."""
    u, v = _across(direction)
    flat = np.stack([corners @ u, corners @ v], axis=-1)  # (K, 3, 2)
    at = np.stack([points @ u, points @ v], axis=-1)  # (P, 2)
    low, high = flat.min(axis=1) - tolerance, flat.max(axis=1) + tolerance
    origin = low.min(axis=0)
    span = float((high.max(axis=0) - origin).max())
    # cells about a triangle wide: each triangle over a few cells, a few triangles per cell
    cell = max(float(np.median((high - low).max(axis=1))), span / MAX_CELLS, 1e-300)
    while True:
        first = np.floor((low - origin) / cell).astype(np.int64)
        last = np.floor((high - origin) / cell).astype(np.int64)
        width = last - first + 1  # (K, 2) cells along each side
        count = width[:, 0] * width[:, 1]
        if count.sum() <= max(CELLS_PER_TRIANGLE * len(corners), 1 << 20):
            break
        cell *= 2.0
    columns = int(last[:, 1].max()) + 1
    triangle = np.repeat(np.arange(len(corners)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    cells = (first[triangle, 0] + k // width[triangle, 1]) * columns + first[triangle, 1] + k % width[triangle, 1]
    order = np.argsort(cells, kind="stable")
    cells, triangle = cells[order], triangle[order]

    where = np.floor((at - origin) / cell).astype(np.int64)
    within = (where >= 0).all(axis=1) & (where[:, 1] < columns)
    own = np.where(within, where[:, 0] * columns + where[:, 1], -1)
    start = np.searchsorted(cells, own, side="left")
    stop = np.where(within, np.searchsorted(cells, own, side="right"), start)
    many = stop - start
    point = np.repeat(np.arange(len(points)), many)
    offset = np.arange(many.sum()) - np.repeat(np.cumsum(many) - many, many)
    return point, triangle[np.repeat(start, many) + offset]


def _crossings(points: np.ndarray, corners: np.ndarray, direction: np.ndarray, point: np.ndarray,
               triangle: np.ndarray) -> np.ndarray:
    """(P,) for each of ``points`` (P, 3), the faces of (K, 3, 3) ``corners`` its ray along
    ``direction`` leaves through less those it enters through, of the candidate pairs
    ``point``, ``triangle`` (M,): 1 inside a closed outward surface, 0 outside."""
    u, v = _across(direction)
    c = corners[triangle]  # (M, 3, 3)
    p = points[point]  # (M, 3)
    flat = np.stack([c @ u, c @ v], axis=-1) - np.stack([p @ u, p @ v], axis=-1)[:, None]  # the point at 0
    a, b, d = flat[:, 0], flat[:, 1], flat[:, 2]
    cross = lambda x, y: x[:, 0] * y[:, 1] - x[:, 1] * y[:, 0]  # noqa: E731
    w = np.stack([cross(b, d), cross(d, a), cross(a, b)], axis=1)  # (M, 3): the point's side of each edge
    hit = (w > 0).all(axis=1) | (w < 0).all(axis=1)  # strictly inside the triangle, as seen along the ray
    normal = cross3(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    facing = normal @ direction
    ahead = np.einsum("mi,mi->m", c[:, 0] - p, normal) * np.sign(facing) > 0
    sign = np.sign(facing).astype(np.int64) * (hit & ahead)
    return np.bincount(point, weights=sign, minlength=len(points)).round().astype(np.int64)


def _on_triangles(points: np.ndarray, corners: np.ndarray, tolerance: float) -> np.ndarray:
    """(M,) bool: whether each of ``points`` (M, 3) lies within ``tolerance`` of its triangle
    ``corners`` (M, 3, 3): off its plane by no more, and inside its outline widened by as much."""
    normal = cross3(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    height = np.einsum("mi,mi->m", points - corners[:, 0], normal)
    edges = corners[:, [1, 2, 0]] - corners  # (M, 3, 3)
    inward = cross3(normal[:, None], edges)  # into the triangle, for its own winding
    inward /= np.maximum(np.linalg.norm(inward, axis=-1, keepdims=True), 1e-300)
    within = (np.einsum("mji,mji->mj", points[:, None] - corners, inward) >= -tolerance).all(axis=1)
    return (np.abs(height) <= tolerance) & within


def _across(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) across ``direction`` (3,) and across each other."""
    u = cross3(direction, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    return u, cross3(direction, u)
