"""Patches shoot, elements receive (Cohen, Greenberg, Immel & Brock 1986, substructuring):
which patch shoots next, and which of its sub-patches its power leaves from
(docs/DESIGN.md §1.4).

A patch's power is the sum of its elements' unshot power, so the number of shots to converge
follows the number of patches, not of elements. A patch shoots from one hemicube at its
centroid unless a ``ShooterTest`` finds that point a poor stand-in for its extent (the
paper's eq. 7 turned on the shooter: ``adaptive.shooter_split``); then it shoots from its
quadrants, recursively, down to single elements as hierarchical radiosity refines the larger
of two interacting patches (Hanrahan, Salzman & Aupperle 1991), but not under a cover, where
splitting uncovers nothing. A patch's choice is made the first time it shoots and kept: it
depends on geometry only.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from hemirad.core.fastops import flatnonzero, row_sums
from hemirad.geometry.patches import PatchTree
from hemirad.geometry.mesh import Mesh
from hemirad.geometry.patterns import CHILDREN
from hemirad.geometry.split import GrowingRows, child_containing
from hemirad.transport.view import HemicubeView

# (what a node's hemicube saw, (K, 3) the corners of the node's elements) -> shoot from its
# children instead?
ShooterTest = Callable[[HemicubeView, torch.Tensor], bool]

# Keys of a source's children: source * (MAX_CHILDREN + 1) + 1 + child
MAX_CHILDREN = max(CHILDREN.values())


#: A node whose hemicube sends more than this share of its power into back faces is hidden
#: (``hidden_centroid_test``); one that sends all but this share may be covered (``under_cover``).
HIDDEN_SHARE = 0.01
# Barycentric slack of ``under_cover``'s test: a point on a cover's outline lies under it.
_INSIDE = 1e-6


def _seen_back(view: HemicubeView) -> torch.Tensor:
    """(P,) bool the pixels of ``view`` that see a back face."""
    return (view.element >= 0) & ~view.front


def back_face_share(view: HemicubeView) -> float:
    """The share of a hemicube's power that its pixels send into back faces."""
    return float(view.back_share)


def under_cover(view: HemicubeView, points: torch.Tensor, corners: torch.Tensor) -> bool:
    """Whether ``view`` sends all but ``HIDDEN_SHARE`` of its power into back faces and every
    one of ``points`` (N, 3), on the plane of its eye, lies under one of those back faces:
    inside it, seen along the view's axis. ``corners`` (T, 3, 3): the elements the view is of.
    Such points are covered (a lamp hung just below a ceiling): what leaves them goes into
    the cover's back wherever it leaves from."""
    if back_face_share(view) < 1.0 - HIDDEN_SHARE:
        return False
    seen_back = _seen_back(view)
    cover = torch.unique(view.element[seen_back])
    axes = view.frame[:2]  # (2, 3): the plane's t and b
    a, b, c = ((corners.index_select(0, cover)[:, k] - view.eye) @ axes.T for k in range(3))  # (C, 2) each
    p = ((points - view.eye) @ axes.T)[:, None, :] - a  # (N, C, 2)
    ab, ac = b - a, c - a
    area = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]  # (C,) twice the signed area, as seen along the axis
    # not edge-on (a wall met behind the cover projects to a sliver whose rounding would hold
    # points: ``geometry.mesh.barycentric`` has no such guard, and used here it did)
    seen = area.abs() > 1e-12 * (ab.square().sum(1) + ac.square().sum(1))
    area = torch.where(seen, area, 1.0)
    u = (p[..., 0] * ac[:, 1] - p[..., 1] * ac[:, 0]) / area
    v = (ab[:, 0] * p[..., 1] - ab[:, 1] * p[..., 0]) / area
    inside = seen & (u >= -_INSIDE) & (v >= -_INSIDE) & (u + v <= 1.0 + _INSIDE)  # (N, C)
    return bool(inside.any(1).all())


def hidden_centroid_test(share: float = HIDDEN_SHARE) -> ShooterTest:
    """A ``ShooterTest`` that needs no more than the render: split a node whose hemicube
    sends more than ``share`` of its power into back faces. Its centroid then lies where its
    elements are not: under an object that stands on it (a floor patch straddling a block's
    footprint), and would shoot into that object's inside."""
    def test(view: HemicubeView, corners: torch.Tensor) -> bool:
        return back_face_share(view) > share

    return test


def eye_points(corners: torch.Tensor, level: int) -> torch.Tensor:
    """(K * 4**level, 3) the centroids of the triangles that ``level`` midpoint splits make of
    each of the (K, 3, 3) ``corners``: points that share a triangle's area equally, the first
    of each triangle's its own centroid (the middle child's middle child is the middle)."""
    for _ in range(level):
        a, b, c = corners.unbind(1)
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        corners = torch.stack([torch.stack(t, 1) for t in ((ab, bc, ca), (a, ab, ca), (ab, b, bc), (ca, bc, c))],
                              1).reshape(-1, 3, 3)
    return corners.mean(1)


def either(*tests: ShooterTest) -> ShooterTest:
    """A ``ShooterTest`` that splits where any of ``tests`` does (each asked in turn)."""
    def test(view: HemicubeView, corners: torch.Tensor) -> bool:
        return any(t(view, corners) for t in tests)

    return test


class PatchShooters:
    """The patches of a solve, followed through the receivers' splits.

    Args:
        tree: the patches of the initial mesh (``geometry.patches.build_patches``).
        device: where the per-element rows live.
        split_test: decides whether a node shoots from its children; None: every patch
            shoots from its centroid.
        source: (T,) int64 the triangle of ``source_corners`` each element of the tree's
            mesh lies in; default: itself.
        source_corners: (S, 3, 3) the triangles a node's light leaves from near it (its
            near field's sources, ``nearfield``): the elements of the mesh the solve began
            with, which on a mesh refined since hold the elements; None: those of the mesh
            the solver is on when it takes these patches (``source`` then its default).
        source_split: the pattern that refined the mesh: the elements of a split source
            then lie in (and take their light from) the child of it that holds them, one
            level down (``use_mesh``). Measured on floating refined twice by the answer
            (10,496 elements), relative MSE and seconds to converge: the refined elements as
            sources 0.00024 in 27 s (the near weights past the sweeps' memory), the initial
            ones 0.00031 in 16 s, their children 0.00025 in 20 s (office, 12,703: 0.00015 /
            0.00016 / 0.00015).
        eye_level: a node whose elements all emit shoots from the centroids of 4**eye_level
            equal parts of each (``eye_points``; its row the mean of theirs) instead of its
            centroid: a lamp's penumbrae are then those of a lamp meshed 2**eye_level times
            finer, without its elements.
        regroup: (T,) int64, optional: the patch each element of the tree's mesh joins when
            the mesh is refined and solved afresh (``assembly.refined_patches``), where that
            differs from ``tree``'s (the answer's first solve shoots from larger patches).
    Attributes:
        leaf, patch, source: (T,) int64 each element's leaf position, patch and source
            (children inherit their parent's).
        cuts: per patch that shot, the nodes its power leaves from.
        shooter_splits: nodes that shoot from their children instead of themselves.
        sent: (N, 3) the power each node has shot so far, over all its shots.
        sent_by_leaf: (T0, 3) the same per initial element (by leaf position): what each
            shot's power was made of, which spreads a node's light to its near receivers.
            With ``sent``, what every receiver got from every node can be recomputed on a
            refined mesh (``adaptive.answer``).
    """

    def __init__(self, tree: PatchTree, device: torch.device, split_test: ShooterTest | None = None,
                 source: torch.Tensor | None = None, source_corners: torch.Tensor | None = None,
                 source_split: str | None = None, eye_level: int = 0, regroup: torch.Tensor | None = None):
        self.tree = tree
        self.eye_level = eye_level
        self.regroup = regroup
        self.split_test = split_test
        self._leaf = GrowingRows(tree.leaf.to(device))
        self._patch = GrowingRows(tree.patch.to(device))
        source = torch.arange(len(tree.leaf), device=device) if source is None else source.to(device)
        self._source = GrowingRows(source)
        self.source_corners = None if source_corners is None else source_corners.to(device)
        self.source_split = source_split
        self._sources: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # per node, its sources
        self._leaf_corners = self._source_of_leaf = self._leaves_of_source = self._source_table = None  # (``use_mesh``)
        self.cuts: dict[int, list[int]] = {}
        self.shooter_splits = 0
        self._members: dict[int, torch.Tensor] = {}  # per node, while the elements are unchanged
        self._leaf_runs = None  # (the elements in leaf order, their leaf positions as numpy) for ``members``
        self._bounds = list(zip(tree.lo.tolist(), tree.hi.tolist()))  # per node (lo, hi), as ints
        self.sent = torch.zeros(tree.num_nodes, 3, dtype=torch.float64, device=device)
        self.sent_by_leaf = torch.zeros(len(tree.leaf), 3, dtype=torch.float64, device=device)

    @property
    def leaf(self) -> torch.Tensor:
        return self._leaf.values

    @property
    def patch(self) -> torch.Tensor:
        return self._patch.values

    @property
    def source(self) -> torch.Tensor:
        return self._source.values

    def inherit(self, parent: torch.Tensor) -> None:
        """Follow a split of the receivers: new element i lies in old element ``parent[i]`` (T',)."""
        for rows in (self._leaf, self._patch, self._source):
            rows.inherit(parent)
        self._members.clear()
        self._leaf_runs = None

    def use_mesh(self, mesh: Mesh) -> None:
        """Take the mesh the tree was built on (its elements are the leaves); its elements
        become the sources where none were given."""
        if self.source_corners is None:
            self.source_corners = mesh.corners
        order = torch.argsort(self.tree.leaf.to(mesh.triangles.device))  # the element at each leaf position
        self._leaf_corners = mesh.corners.index_select(0, order)
        source = self.source.index_select(0, order)
        corners = self.source_corners.index_select(0, source)
        key = source * (MAX_CHILDREN + 1)
        if self.source_split is not None:  # a split source's leaves: the child of it each lies in
            split = flatnonzero(mesh.level.index_select(0, order) > 0)
            child, number = child_containing(corners.index_select(0, split), mesh.centroids.index_select(
                0, order.index_select(0, split)), self.source_split)
            corners.index_copy_(0, split, child)
            key.index_add_(0, split, 1 + number)
        _, number = torch.unique(key, return_inverse=True)
        # numbered in the order of their first leaves: with each element its own source (an
        # unrefined mesh), a node's sources are its leaves in order
        positions = torch.arange(len(key), device=key.device)
        first = torch.full((int(number.max()) + 1,), len(key), dtype=torch.int64, device=key.device).scatter_reduce_(
            0, number, positions, "amin")
        self._source_of_leaf = torch.argsort(torch.argsort(first)).index_select(0, number)  # (T0,)
        self._leaves_of_source = torch.bincount(self._source_of_leaf)
        # the leaves of one source give it the same corners: any of them will do
        self._source_table = corners.new_empty(len(self._leaves_of_source), 3, 3).index_copy_(
            0, self._source_of_leaf, corners)
        self._sources.clear()

    def sources(self, node: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``node``'s near-field sources: (k, 3, 3) their corners, and (hi - lo,) for each of
        its leaf positions the one it lies in (0..k-1). A source all of whose elements the
        node holds is one; where the node holds only some (an emitting element split and
        shooting alone, a sub-patch cutting through one), each of its leaves is its own: a
        node's light never leaves from outside it."""
        found = self._sources.get(node)
        if found is None:
            lo, hi = self.bounds(node)
            source = self._source_of_leaf[lo:hi]
            count = len(self._leaves_of_source)
            whole = torch.bincount(source, minlength=count).index_select(0, source) == \
                self._leaves_of_source.index_select(0, source)
            key = torch.where(whole, source, count + lo + torch.arange(hi - lo, device=source.device))
            index, local = torch.unique(key, return_inverse=True)
            own = index >= count
            corners = torch.where(own[:, None, None], self._leaf_corners.index_select(0, (index - count).clamp(min=0)),
                                  self._source_table.index_select(0, index.clamp(max=count - 1)))
            found = self._sources[node] = (corners, local)
        return found

    def by_source(self, node: int, by_leaf: torch.Tensor) -> torch.Tensor:
        """(k, C) the (hi - lo, C) rows of ``node``'s leaf positions summed by its sources."""
        corners, local = self.sources(node)
        return by_leaf.new_zeros(len(corners), by_leaf.shape[1]).index_add_(0, local, by_leaf)

    def record(self, node: int, members: torch.Tensor, member_power: torch.Tensor) -> None:
        """Count a shot of ``node`` whose (K,) ``members`` shot (K, 3) ``member_power``."""
        self.sent[node] += member_power.sum(0)
        self.sent_by_leaf.index_add_(0, self.leaf.index_select(0, members), member_power)

    def record_sweep(self, node_of_leaf: torch.Tensor, leaf_power: torch.Tensor) -> None:
        """Count a sweep in which every initial element shot (T0, 3) ``leaf_power`` (by leaf
        position) from its node ``node_of_leaf`` (T0,; -1 where it shot nothing)."""
        self.sent.index_add_(0, node_of_leaf.clamp(min=0), leaf_power)
        self.sent_by_leaf += leaf_power

    def magnitudes(self, power: torch.Tensor) -> torch.Tensor:
        """(P,) per patch, the magnitude of its elements' unshot ``power`` (T, 3) (overshooting
        leaves some negative)."""
        magnitude = torch.zeros(self.tree.num_patches, dtype=power.dtype, device=power.device)
        return magnitude.index_add_(0, self.patch, row_sums(power.abs()))

    def strongest(self, power: torch.Tensor) -> int | None:
        """The patch whose elements hold the most unshot power (``magnitudes``), from the
        per-element ``power`` (T, 3); None when all is shot."""
        magnitude = self.magnitudes(power)
        best = int(torch.argmax(magnitude))
        return best if float(magnitude[best]) > 0.0 else None

    def bounds(self, node: int) -> tuple[int, int]:
        """``node``'s range [lo, hi) of leaf positions (its initial elements)."""
        return self._bounds[node]

    def members(self, node: int) -> torch.Tensor:
        """(K,) the elements of ``node``."""
        members = self._members.get(node)
        if members is None:
            if self._leaf_runs is None:  # once per mesh: a node's elements are then one run of it
                order = torch.argsort(self.leaf, stable=True)
                self._leaf_runs = order, self.leaf.index_select(0, order).cpu().numpy()
            order, sorted_leaf = self._leaf_runs
            start, end = np.searchsorted(sorted_leaf, self._bounds[node]).tolist()
            members = self._members[node] = torch.sort(order[start:end]).values  # in element order
        return members

    def member_counts(self, flags: torch.Tensor | None = None) -> np.ndarray:
        """(N,) int64 per node, how many elements it holds, or how many of them ``flags`` (T,)
        bool marks: prefix sums over the leaf positions, a node's elements being those of its
        positions [lo, hi)."""
        leaf = self.leaf.cpu().numpy()
        weights = None if flags is None else flags.cpu().numpy()
        before = np.concatenate([[0], np.cumsum(np.bincount(leaf, weights, len(self.tree.leaf)).astype(np.int64))])
        return before[self.tree.hi.cpu().numpy()] - before[self.tree.lo.cpu().numpy()]

    def cut(self, patch: int, render: Callable[[int], HemicubeView], corners: torch.Tensor) -> list[int]:
        """The nodes ``patch`` shoots from: its root, or where ``split_test`` says so, its
        children's cuts; but not a node whose elements all lie ``under_cover``: splitting it
        would go down to single elements that all shoot into the cover's back.
        ``render(node)`` gives a node's view; ``corners`` (T, 3, 3) are the elements'.

        Measured (floating, refined by the answer from the shipped sizes x2 to 3,426
        elements, rounds at most doubling): two ceiling patches behind the lamp, 5 mm above
        it, split into 124 nodes without the cover test (190 of the 445 hemicubes the last
        solve drew), into 8 with it (261 hemicubes), for the same relative MSE (0.00008)."""
        if patch in self.cuts:
            return self.cuts[patch]
        nodes, pending = [], [int(self.tree.root[patch])]
        while pending:
            node = pending.pop()
            children = self.tree.children(node)
            if children and self.split_test is not None:
                points = corners.index_select(0, self.members(node)).reshape(-1, 3)
                seen = render(node)
                if self.split_test(seen, points) and not under_cover(seen, points, corners):
                    pending += reversed(children)
                    self.shooter_splits += 1
                    continue
            nodes.append(node)
        self.cuts[patch] = nodes
        return nodes

    def state_dict(self) -> dict:
        """The per-element rows and the cuts made, as tensors."""
        patches = sorted(self.cuts)
        sizes = torch.tensor([len(self.cuts[p]) for p in patches], dtype=torch.int64)
        nodes = torch.tensor([n for p in patches for n in self.cuts[p]], dtype=torch.int64)
        return {"leaf": self.leaf.cpu().clone(), "patch": self.patch.cpu().clone(), "source": self.source.cpu().clone(),
                "cut_patches": torch.tensor(patches, dtype=torch.int64), "cut_sizes": sizes, "cut_nodes": nodes,
                "shooter_splits": self.shooter_splits, "sent": self.sent.cpu().clone(),
                "sent_by_leaf": self.sent_by_leaf.cpu().clone()}

    def load_state_dict(self, state: dict, num_elements: int) -> None:
        """Continue from ``state_dict()``'s output for a mesh of ``num_elements``; ValueError if it does not fit."""
        leaf, patch, source = state["leaf"], state["patch"], state["source"]
        for name, rows in (("leaf", leaf), ("patch", patch), ("source", source)):
            if not isinstance(rows, torch.Tensor) or rows.shape != (num_elements,) or rows.dtype != torch.int64:
                raise ValueError(f"patches.{name} must be a ({num_elements},) int64 tensor")
        sizes, nodes, patches = state["cut_sizes"], state["cut_nodes"], state["cut_patches"]
        if int(sizes.sum()) != len(nodes) or len(sizes) != len(patches):
            raise ValueError("the patches' cuts do not fit together")
        device = self.leaf.device
        self._leaf, self._patch, self._source = (GrowingRows(rows.to(device)) for rows in (leaf, patch, source))
        self._members.clear()
        self._leaf_runs = None
        self._sources.clear()
        self.cuts = {int(p): part.tolist() for p, part in zip(patches, torch.split(nodes, sizes.tolist()))}
        self.shooter_splits = int(state["shooter_splits"])
        for name in ("sent", "sent_by_leaf"):
            rows, want = state.get(name), getattr(self, name)
            if not isinstance(rows, torch.Tensor) or rows.shape != want.shape or rows.dtype != torch.float64:
                raise ValueError(f"patches.{name} must be a {tuple(want.shape)} float64 tensor")
        self.sent, self.sent_by_leaf = state["sent"].to(device), state["sent_by_leaf"].to(device)
