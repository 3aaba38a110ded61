"""Undirected edges as int64 keys, and the index of the midpoints that splitting made on them.

An edge (a, b) of vertex indices, in either order, has the key ``min * 2^32 + max``: one
int64 per edge, the same in every mesh (a split keeps the old vertex indices), and sorting
keys sorts edges by their lower then their higher end. Sorted keys are searched with
``torch.searchsorted``, which is what makes edge lookups vectorised: the midpoint lookup of
pattern 2 splitting and 2:1 grading, the T-vertex search of the display and the edge lines
of the mesh views all go through here.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import torch

from hemirad.core.fastops import flatnonzero

if TYPE_CHECKING:
    from hemirad.geometry.mesh import Mesh

# Keys are exact while vertex indices stay below 2^31 (the product stays inside int64).
KEY_BASE = 1 << 32

# The key under which a mesh's cache holds its ``midpoint_index``.
MIDPOINT_INDEX = "midpoint_index"

# ``find(a, b) -> (N,) int64``: see ``midpoint_lookup``.
MidpointFinder = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def edge_keys(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,) int64 one key per undirected edge ``min * 2^32 + max`` of the (N,) int64 ends
    ``a`` and ``b`` (in either order)."""
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    return lo * KEY_BASE + hi


def key_ends(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The (N,) lower and (N,) higher end of the edges of the (N,) ``keys``."""
    return keys // KEY_BASE, keys % KEY_BASE


def triangle_edges(triangles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The (3T,) start and (3T,) end vertices of the directed edges of (T, 3) ``triangles``:
    edge ``3 t + e`` of triangle t runs from corner e to corner e + 1, so (v0 v1), (v1 v2),
    (v2 v0), in the triangle's winding."""
    return triangles.reshape(-1), triangles[:, [1, 2, 0]].reshape(-1)


def unique_edge_keys(triangles: torch.Tensor) -> torch.Tensor:
    """(E,) int64 the sorted keys of the distinct undirected edges of (T, 3) ``triangles``."""
    return torch.unique(edge_keys(*triangle_edges(triangles)))


def unique_edges(triangles: torch.Tensor) -> torch.Tensor:
    """(E, 2) int64 the distinct undirected edges of (T, 3) ``triangles``, lower end first,
    sorted by lower then higher end."""
    return torch.stack(key_ends(unique_edge_keys(triangles)), dim=1)


def _locate(keys: torch.Tensor, query: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For (N,) ``query`` in (M,) sorted ``keys`` (M > 0): (N,) the position each would hold
    (clamped into the keys) and (N,) bool whether the key there is the query."""
    pos = torch.searchsorted(keys, query).clamp_max(len(keys) - 1)
    return pos, keys.index_select(0, pos) == query


def contains(keys: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """(N,) bool: which of the (N,) ``query`` keys are among the (M,) sorted ``keys``."""
    if len(keys) == 0:
        return torch.zeros(query.shape, dtype=torch.bool, device=query.device)
    return _locate(keys, query)[1]


def search(keys: torch.Tensor, values: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """(N,) the int64 ``values`` (M,) stored with the (M,) sorted ``keys`` at the (N,)
    ``query`` keys, -1 where a query is absent."""
    if len(keys) == 0:
        return torch.full_like(query, -1)
    pos, hit = _locate(keys, query)
    return torch.where(hit, values.index_select(0, pos), -1)


def midpoint_keys(edge_parents: torch.Tensor, first: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The (M,) keys of the edges that the vertices of (V, 2) ``edge_parents`` are midpoints
    of, and (M,) those vertices (numbered from ``first``, the index of the first row), in
    vertex order; a vertex with parents -1 is no midpoint and has none."""
    midpoints = flatnonzero(edge_parents[:, 0] >= 0)
    keys = edge_keys(edge_parents[midpoints, 0], edge_parents[midpoints, 1])
    return keys, midpoints + first


def midpoint_index(mesh: Mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """The sorted keys of the edges splitting made midpoints on, and those midpoints: (M,)
    int64 each.

    Kept in the mesh's cache (the mesh is immutable, so the index never goes stale);
    ``SplitRounds.result`` hands its output the index merged with the new midpoints
    (``merged_index``), so a chain of splits never sorts it again.
    """
    def build() -> tuple[torch.Tensor, torch.Tensor]:
        keys, midpoints = midpoint_keys(mesh.edge_parents)
        keys, order = torch.sort(keys)
        return keys, midpoints[order]

    return mesh.cache.get(MIDPOINT_INDEX, build)


def merged_index(index: tuple[torch.Tensor, torch.Tensor], keys: torch.Tensor,
                 midpoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``midpoint_index`` with the (k,) new ``midpoints`` on the edges of the (k,) ``keys``
    added (no key is in it yet: an edge is split once). A merge of two sorted lists, cheaper
    than sorting the whole index again."""
    old_keys, old_mid = index
    M, device = len(old_keys), keys.device
    keys, order = torch.sort(keys)
    slot = torch.searchsorted(old_keys, keys)  # (k,) the old keys before each new one
    new_at = slot + torch.arange(len(keys), device=device)  # its place in the merged list
    # each old key moves up by the number of new keys before it
    moved_by = torch.zeros(M + 1, dtype=torch.int64, device=device).index_add_(0, slot, torch.ones_like(slot))
    old_at = torch.arange(M, device=device) + moved_by.cumsum(0)[:M]
    merged = []
    for old, new in ((old_keys, keys), (old_mid, midpoints.index_select(0, order))):
        out = torch.empty(M + len(keys), dtype=torch.int64, device=device)
        merged.append(out.index_copy_(0, old_at, old).index_copy_(0, new_at, new))
    return merged[0], merged[1]


def lookup(keys: torch.Tensor, midpoints: torch.Tensor) -> MidpointFinder:
    """``midpoint_lookup`` over an index of (M,) sorted edge keys and their (M,) midpoints."""

    def find(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return search(keys, midpoints, edge_keys(a, b))

    return find


def midpoint_lookup(mesh: Mesh) -> MidpointFinder:
    """A vectorised map from undirected edges to the midpoint vertex splitting made on them.

    Returns:
        A function ``find(a, b) -> (N,) int64`` taking two (N,) int64 tensors of vertex
        indices (in either order) and giving, for each pair, the vertex whose
        ``edge_parents`` is that pair, or -1 where the edge has never been split.
    """
    return lookup(*midpoint_index(mesh))
