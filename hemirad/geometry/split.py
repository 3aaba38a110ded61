"""Element subdivision: the two split patterns of Hasebe & Makino, and mesh-shape quality.

Pattern 1 (centroid, 1 -> 3) adds one vertex inside the triangle, so neighbours are never
affected and the mesh stays conforming, but every generation makes the children thinner:
repeated splitting drives the largest interior angle towards 180 degrees.

Pattern 2 (edge midpoints, 1 -> 4) makes four children similar to the parent, so shape
quality never degrades, at the price of T-vertices on unsplit neighbours (see
``display.conforming_vertex_values`` and ``display.conforming_triangles``). Midpoints are
shared: two triangles split in the same call get one vertex on their common edge, and a
triangle split later reuses the vertex its neighbour made earlier, found through
``Mesh.edge_parents`` (``edges.midpoint_lookup``).

Everything here is pure and vectorised over elements: it returns a new Mesh and never
modifies its input.
"""
from __future__ import annotations

import math

import torch

from hemirad.core.fastops import flatnonzero, rows_touching
from hemirad.geometry.edges import (MIDPOINT_INDEX, MidpointFinder, edge_keys, key_ends, lookup, merged_index,
                                    midpoint_index, midpoint_keys, midpoint_lookup, search, triangle_edges)
from hemirad.geometry.mesh import Mesh, barycentric
from hemirad.geometry.patterns import CHILDREN, PATTERNS

def _split_pattern1(vertices: torch.Tensor, triangles: torch.Tensor, chosen: torch.Tensor,
                    find: MidpointFinder | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centroid split of the triangles ``chosen`` (n,) -> new vertices (n, 3), their
    edge_parents (n, 2) and the children (3n, 3), grouped by parent."""
    tri = triangles[chosen]  # (n, 3)
    n = len(tri)
    new_vertices = vertices[tri].mean(dim=1)
    c = len(vertices) + torch.arange(n, dtype=torch.int64, device=tri.device)
    v0, v1, v2 = tri.unbind(dim=1)
    # Each child keeps one parent edge and replaces the opposite corner by the centroid,
    # so it is wound like the parent.
    children = torch.stack([
        torch.stack([v0, v1, c], dim=1),
        torch.stack([v1, v2, c], dim=1),
        torch.stack([v2, v0, c], dim=1),
    ], dim=1).reshape(-1, 3)
    # The centroid lies on no edge: it can never be a T-vertex.
    new_parents = torch.full((n, 2), -1, dtype=torch.int64, device=tri.device)
    return new_vertices, new_parents, children


def _split_pattern2(vertices: torch.Tensor, triangles: torch.Tensor, chosen: torch.Tensor,
                    find: MidpointFinder) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Midpoint split of the triangles ``chosen`` (n,) -> new vertices (k, 3), their
    edge_parents (k, 2) and the children (4n, 3), grouped by parent; ``find`` is the
    mesh's ``midpoint_lookup``."""
    num_vertices = len(vertices)
    tri = triangles[chosen]  # (n, 3)
    n = len(tri)
    # One entry per distinct edge among the chosen triangles: an edge shared by two chosen
    # triangles gets a single midpoint. torch.unique sorts, so new vertices come out in a
    # deterministic order (by their sorted end vertices).
    unique_keys, inverse = torch.unique(edge_keys(*triangle_edges(tri)), sorted=True, return_inverse=True)
    unique_lo, unique_hi = key_ends(unique_keys)

    # Reuse a midpoint an earlier split made on the same edge (the neighbour was split
    # before); only the rest get new vertices.
    existing = find(unique_lo, unique_hi)
    missing = existing < 0
    num_new = int(missing.sum())
    new_index = num_vertices + torch.arange(num_new, dtype=torch.int64, device=tri.device)
    mid_of_unique = existing.clone()
    mid_of_unique[missing] = new_index
    a, b = unique_lo[missing], unique_hi[missing]
    new_vertices = 0.5 * (vertices[a] + vertices[b])
    new_parents = torch.stack([a, b], dim=1)

    m = mid_of_unique[inverse].reshape(n, 3)  # (n, 3): m01, m12, m20
    m01, m12, m20 = m.unbind(dim=1)
    v0, v1, v2 = tri.unbind(dim=1)
    # Three corner children and the central one (rotated by 180 degrees); all four are
    # similar to the parent and wound like it.
    children = torch.stack([
        torch.stack([v0, m01, m20], dim=1),
        torch.stack([m01, v1, m12], dim=1),
        torch.stack([m20, m12, v2], dim=1),
        torch.stack([m01, m12, m20], dim=1),
    ], dim=1).reshape(-1, 3)
    return new_vertices, new_parents, children


def split_triangles(mesh: Mesh, selected: torch.Tensor, pattern: str) -> tuple[Mesh, torch.Tensor]:
    """Split the selected triangles with one of the paper's two patterns.

    Args:
        mesh: the mesh; not modified.
        selected: (T,) bool, the triangles to split.
        pattern: ``"pattern1"`` (centroid, 1 -> 3 children (v0 v1 c), (v1 v2 c), (v2 v0 c))
            or ``"pattern2"`` (edge midpoints, 1 -> 4 children (v0 m01 m20),
            (m01 v1 m12), (m20 m12 v2), (m01 m12 m20)).

    Returns:
        mesh: the new mesh. Its vertices are the old ones (same indices) followed by the
            new ones. Every old triangle keeps its index: an unsplit one is unchanged, a
            split one's index now holds its first child; the other children follow the old
            triangles, grouped by parent in the order of the parents. Children inherit
            surface and material, get ``level + 1`` and keep the parent's winding. Geometry
            the old mesh had computed is handed over, computed afresh for children only.
        parent: (T',) int64, for each new triangle the index of the old triangle it lies in:
            ``parent[:T]`` is ``0, 1, ..., T - 1``. ``values[parent]`` (or, the same and
            cheaper, ``inherit(values, parent)``) carries per-element quantities such as
            radiosity over: value per unit area is unchanged, so power is conserved.
    """
    selected = torch.as_tensor(selected, dtype=torch.bool, device=mesh.triangles.device).reshape(-1)
    if len(selected) != mesh.num_elements:
        raise ValueError(f"need one flag per element ({mesh.num_elements}), got {len(selected)}")
    chosen = flatnonzero(selected)
    rounds = SplitRounds(mesh, pattern, room=len(chosen))
    rounds.split(chosen)
    return rounds.result()


def child_containing(triangles: torch.Tensor, points: torch.Tensor, pattern: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The child, as ``split_triangles`` makes it with ``pattern``, of each of the (n, 3, 3)
    ``triangles`` that contains its point (n, 3) (inside the triangle: a descendant's centroid
    finds the child it descends from): (n, 3, 3) its corners (in the split's order and
    winding) and (n,) its number among its siblings."""
    a, b, c = triangles.unbind(1)
    u, v, w = barycentric(triangles, points).unbind(1)
    if pattern == "pattern1":  # (v0 v1 c), (v1 v2 c), (v2 v0 c): the one without the smallest coordinate's corner
        g = triangles.mean(1)
        children = torch.stack([torch.stack([a, b, g], 1), torch.stack([b, c, g], 1), torch.stack([c, a, g], 1)], 1)
        which = torch.argmin(torch.stack([w, u, v], 1), dim=1)
    elif pattern == "pattern2":  # (v0 m01 m20), (m01 v1 m12), (m20 m12 v2), (m01 m12 m20)
        m01, m12, m20 = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
        children = torch.stack([torch.stack([a, m01, m20], 1), torch.stack([m01, b, m12], 1),
                                torch.stack([m20, m12, c], 1), torch.stack([m01, m12, m20], 1)], 1)
        which = torch.where(u > 0.5, 0, torch.where(v > 0.5, 1, torch.where(w > 0.5, 2, 3)))
    else:
        raise ValueError(f"pattern must be one of {', '.join(PATTERNS)}, not {pattern!r}")
    return children[torch.arange(len(triangles), device=triangles.device), which], which


class GrowingRows:
    """A tensor with room to grow along its first dimension; ``values`` is the filled part.

    Per-element values kept in one follow a mesh through its splits (``inherit``) by
    appending the new rows in place, without copying the old ones; ``inherit`` and
    ``append`` leave the filled rows alone, so a ``values`` taken before still holds what it
    held (``SplitRounds`` also rewrites rows of its own buffers).
    """

    def __init__(self, values: torch.Tensor, room: int = 0):
        self.buffer = torch.empty((len(values) + room, *values.shape[1:]), dtype=values.dtype, device=values.device)
        self.buffer[:len(values)] = values
        self.size = len(values)

    @property
    def values(self) -> torch.Tensor:
        return self.buffer[:self.size]

    def append(self, rows: torch.Tensor) -> None:
        need = self.size + len(rows)
        if need > len(self.buffer):
            bigger = torch.empty((need + need // 2, *self.buffer.shape[1:]), dtype=self.buffer.dtype,
                                 device=self.buffer.device)
            bigger[:self.size] = self.values
            self.buffer = bigger
        self.buffer[self.size:need] = rows
        self.size = need

    def inherit(self, parent: torch.Tensor) -> torch.Tensor:
        """``inherit(values, parent)``, appended in place; returns the new ``values``."""
        self.append(self.values.index_select(0, parent[self.size:]))
        return self.values


class SplitRounds:
    """A mesh split in rounds (a refiner's selection, then the triangles 2:1 grading adds),
    each round splitting triangles of the previous one's result.

    The mesh's arrays are copied once into buffers with room to grow, and every round writes
    its children in place: the result is the one a chain of ``split_triangles`` calls gives,
    bit for bit, without copying the whole mesh per round. Likewise the midpoints the rounds
    make are looked up in a small index of their own and merged into the mesh's sorted one
    once, by ``result``.

    Args:
        mesh: the mesh before the first round; not modified.
        pattern: as for ``split_triangles``.
        room: how many triangles the rounds are expected to split (the buffers grow past it).
    """

    def __init__(self, mesh: Mesh, pattern: str, room: int = 0):
        if pattern not in PATTERNS:
            raise ValueError(f"unknown split pattern {pattern!r}; expected one of {', '.join(PATTERNS)}")
        self.before, self.pattern = mesh, pattern
        self.per_parent = CHILDREN[pattern]
        device = mesh.triangles.device
        new_triangles = room * (self.per_parent - 1)
        new_vertices = room * (1 if pattern == "pattern1" else 3)
        self._triangles = GrowingRows(mesh.triangles, new_triangles)
        self._level = GrowingRows(mesh.level, new_triangles)
        self._parent = GrowingRows(torch.arange(mesh.num_elements, device=device), new_triangles)
        self._vertices = GrowingRows(mesh.vertices, new_vertices)
        self._edge_parents = GrowingRows(mesh.edge_parents, new_vertices)
        # the midpoint index, once needed (pattern 2 looks midpoints up; pattern 1 makes none)
        self._index = mesh.cache.get(MIDPOINT_INDEX)
        self._new_midpoints = []  # (keys, midpoints) made by each round, not yet in _index
        self._find = None  # the current mesh's midpoint lookup, once made (a round renews it)

    @property
    def num_elements(self) -> int:
        return self._triangles.size

    @property
    def num_vertices(self) -> int:
        return self._vertices.size

    @property
    def triangles(self) -> torch.Tensor:
        """(T, 3) the current triangles (a view: the next round changes it)."""
        return self._triangles.values

    def midpoint_lookup(self) -> MidpointFinder:
        """``midpoint_lookup`` of the current mesh (made once per round: a round's grading
        check and the next round's split share it)."""
        if self._find is None:
            self._find = self._make_lookup()
        return self._find

    def _make_lookup(self) -> MidpointFinder:
        if self._index is None:
            self._index = midpoint_index(self.before)
        if not self._new_midpoints:
            return lookup(*self._index)
        keys, order = torch.sort(torch.cat([keys for keys, _ in self._new_midpoints]))
        new = keys, torch.cat([mid for _, mid in self._new_midpoints]).index_select(0, order)

        def find(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # an edge is in one index or neither
            query = edge_keys(a, b)
            old = search(*self._index, query)
            return torch.where(old >= 0, old, search(*new, query))

        return find

    def split(self, chosen: torch.Tensor) -> None:
        """Split the current triangles ``chosen`` (n,), sorted indices."""
        V = self._vertices.size
        split = _split_pattern1 if self.pattern == "pattern1" else _split_pattern2
        find = self.midpoint_lookup() if self.pattern == "pattern2" else None
        new_vertices, new_parents, children = split(self._vertices.values, self._triangles.values, chosen, find)
        children = children.reshape(len(chosen), self.per_parent, 3)
        others = self.per_parent - 1
        self._triangles.append(children[:, 1:].reshape(-1, 3))
        self._triangles.buffer[chosen] = children[:, 0]
        self._level.buffer[chosen] += 1
        self._level.append(self._level.values.index_select(0, chosen).repeat_interleave(others))
        self._parent.append(self._parent.values.index_select(0, chosen).repeat_interleave(others))
        self._vertices.append(new_vertices.to(self._vertices.buffer.dtype))
        self._edge_parents.append(new_parents)
        if self._index is not None:  # else the index is built from the result's edge_parents
            keys, midpoints = midpoint_keys(new_parents, first=V)
            if len(keys):
                self._new_midpoints.append((keys, midpoints))
                self._find = None

    def unbalanced(self, near: torch.Tensor | None = None) -> torch.Tensor:
        """``unbalanced`` of the current mesh; ``near`` (V,) over its vertices."""
        return _unbalanced(self.triangles, self.midpoint_lookup(), near)

    def result(self) -> tuple[Mesh, torch.Tensor]:
        """The split mesh and (T',) the triangle of the mesh before that each one lies in
        (``split_triangles``' two results, for all the rounds together). The mesh holds
        views of the buffers (no round may follow) and the geometry and plane ids the mesh
        before had computed, computed afresh for the changed triangles only: the split
        ones and the appended ones."""
        old, parent = self.before, self._parent.values
        mesh = Mesh(vertices=self._vertices.values, triangles=self._triangles.values,
                    surface=inherit(old.surface, parent), material=inherit(old.material, parent),
                    surface_names=list(old.surface_names), level=self._level.values,
                    edge_parents=self._edge_parents.values)
        if self._new_midpoints:
            keys, midpoints = (torch.cat(parts) for parts in zip(*self._new_midpoints))
            self._index, self._new_midpoints = merged_index(self._index, keys, midpoints), []
        if self._index is not None:
            mesh.cache.put(MIDPOINT_INDEX, self._index)
        T = old.num_elements
        replaced = torch.unique(parent[T:])  # a triangle was split if and only if children were appended to it
        mesh.inherit_geometry(old, torch.cat([replaced, torch.arange(T, len(parent), device=parent.device)]))
        if old.cache.contains("plane_ids"):  # children lie in their parent's plane
            mesh.cache.put("plane_ids", inherit(old.plane_ids, parent))
        return mesh, parent


def inherit(values: torch.Tensor, parent: torch.Tensor) -> torch.Tensor:
    """``values[parent]`` for a ``parent`` map of ``split_triangles`` (or a chain of them),
    whose first ``len(values)`` entries are the identity: a copy and a gather of the new
    rows only.

    Args:
        values: (T, ...) per old element; parent: (T',) with ``parent[:T] == arange(T)``.
    Returns:
        (T', ...) a new tensor.
    """
    return torch.cat([values, values.index_select(0, parent[len(values):])])


def unbalanced(mesh: Mesh, near: torch.Tensor | None = None) -> torch.Tensor:
    """(n,) sorted: the triangles whose neighbours are more than one level finer across an edge.

    The 2:1 rule of graded meshes: an edge of a leaf may carry one midpoint, but that
    midpoint's half-edges may not be split again. A leaf that breaks it sits beside a much
    finer region (typically a shadow edge that crosses it too, just under the threshold);
    splitting it grades the mesh and keeps T-vertices from nesting.

    Args:
        near: (V,) bool, optional: only triangles with a vertex marked here are examined
            (after a split, the vertices of the split triangles: a new violation has one).
    """
    return _unbalanced(mesh.triangles, midpoint_lookup(mesh), near)


def _unbalanced(all_triangles: torch.Tensor, find, near: torch.Tensor | None) -> torch.Tensor:
    if near is None:
        candidates, triangles = torch.arange(len(all_triangles), device=all_triangles.device), all_triangles
    else:
        candidates = rows_touching(all_triangles, near)
        triangles = all_triangles.index_select(0, candidates)
    a, b = triangle_edges(triangles)
    m = find(a, b)
    has = m >= 0
    m_safe = torch.where(has, m, a)
    halves = find(torch.cat([a, m_safe]), torch.cat([m_safe, b])) >= 0  # (a, m) then (m, b)
    nested = (has & (halves[:len(a)] | halves[len(a):])).reshape(-1, 3)
    return candidates.index_select(0, flatnonzero(nested[:, 0] | nested[:, 1] | nested[:, 2]))


def largest_angles(mesh: Mesh) -> torch.Tensor:
    """(T,) float64 the largest interior angle of each triangle, in degrees.

    Angles come from atan2(|cross|, dot), which stays accurate near 0 and 180 degrees
    where acos of a normalised dot product loses half its digits.
    """
    c = mesh.corners  # (T, 3, 3)
    # At corner i the two sides run to corners i + 1 and i + 2.
    to_next = c[:, [1, 2, 0]] - c
    to_prev = c[:, [2, 0, 1]] - c
    sin_part = torch.linalg.cross(to_next, to_prev, dim=-1).norm(dim=-1)
    cos_part = (to_next * to_prev).sum(dim=-1)
    angles = torch.atan2(sin_part, cos_part)  # (T, 3), radians, summing to pi
    return angles.amax(dim=1) * (180.0 / math.pi)


def angle_quality(mesh: Mesh) -> dict[str, float]:
    """Mean and population variance (degrees, degrees^2) of each element's largest angle.

    This is the paper's mesh-quality measure: 60 degrees and variance 0 for a mesh of
    equilateral triangles; slivers push the mean towards 180 and inflate the variance.
    """
    angles = largest_angles(mesh)
    if len(angles) == 0:
        return {"mean": float("nan"), "variance": float("nan")}
    return {"mean": float(angles.mean()), "variance": float(angles.var(correction=0))}
