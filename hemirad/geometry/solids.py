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

Inside is decided by the generalised winding number (the solid angle the closed surface
subtends, over 4 pi): 1 inside, 0 outside, whatever the solid's shape. A point on the
surface (within the tolerance) counts as outside: a floor's elements under a box's bottom
face are not inside the box.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

#: (points x triangles) pairs evaluated at once: bounds the temporary arrays to some 50 MB.
CHUNK = 1 << 18


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
        near = ((points >= self.low - tolerance) & (points <= self.high + tolerance)).all(axis=1)
        rows = np.flatnonzero(near)
        rows = rows[winding_numbers(points[rows], self.corners) > 0.5]
        # on the surface the solid angle of the triangle under the point is +-2 pi by
        # rounding: such a point is on the boundary, not inside
        inside[rows] = ~on_surface(points[rows], self.corners, tolerance)
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
                                                  np.cross(corners[:, 1], corners[:, 2])) / 6.0, minlength=count)
    area = np.bincount(label, weights=0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1), minlength=count)
    solids = []
    for component in range(count):
        rows = np.flatnonzero(label == component)
        # no thicker than the tolerance (a quad and its reverse, back to back): no inside
        if open_component[component] or volume[component] <= tolerance * area[component]:
            continue
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


def winding_numbers(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(P,) the winding number of the closed triangles (K, 3, 3) about each of ``points``
    (P, 3): the sum of their signed solid angles (Van Oosterom & Strackee 1983) over 4 pi."""
    out = np.empty(len(points))
    step = max(1, CHUNK // max(1, len(corners)))
    for start in range(0, len(points), step):
        p = points[start:start + step, None, None, :]
        r = corners[None] - p  # (p, K, 3, 3)
        a, b, c = r[:, :, 0], r[:, :, 1], r[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pki,pki->pk", a, np.cross(b, c))
        dot = lambda x, y: np.einsum("pki,pki->pk", x, y)  # noqa: E731
        denominator = la * lb * lc + dot(a, b) * lc + dot(a, c) * lb + dot(b, c) * la
        out[start:start + step] = 2.0 * np.arctan2(det, denominator).sum(axis=1) / (4.0 * np.pi)
    return out


def on_surface(points: np.ndarray, corners: np.ndarray, tolerance: float) -> np.ndarray:
    """(P,) bool: which of ``points`` (P, 3) lie within ``tolerance`` of one of the
    triangles (K, 3, 3): off its plane by no more, and inside its outline widened by as much."""
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    normal = np.cross(e1, e2)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    ends = corners[:, [1, 2, 0]] - corners  # (K, 3, 3) each edge
    inward = np.cross(normal[:, None], ends)  # points into the triangle for a right-handed one
    inward /= np.maximum(np.linalg.norm(inward, axis=-1, keepdims=True), 1e-300)
    out = np.zeros(len(points), dtype=bool)
    step = max(1, CHUNK // max(1, len(corners)))
    for start in range(0, len(points), step):
        d = points[start:start + step, None, :] - corners[None, :, 0]  # (p, K, 3)
        height = np.einsum("pki,ki->pk", d, normal)
        rel = points[start:start + step, None, None, :] - corners[None]  # (p, K, 3, 3)
        within = (np.einsum("pkji,kji->pkj", rel, inward) >= -tolerance).all(axis=-1)
        out[start:start + step] = ((np.abs(height) <= tolerance) & within).any(axis=1)
    return out
