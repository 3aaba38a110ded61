"""Patches shoot, elements receive (Cohen, Greenberg, Immel & Brock 1986, substructuring):
which patch shoots next, and which of its sub-patches its power leaves from
(docs/DESIGN.md §1.4).

A patch's power is the sum of its elements' unshot power, so the number of shots to converge
follows the number of patches, not of elements. A patch shoots from one hemicube at its
centroid unless a ``ShooterTest`` finds that point a poor stand-in for its extent (the
paper's eq. 7 turned on the shooter: ``adaptive.shooter_split``); then it shoots from its
quadrants, recursively, down to single elements as hierarchical radiosity refines the larger
of two interacting patches (Hanrahan, Salzman & Aupperle 1991). A patch's choice is made the
first time it shoots and kept: it depends on geometry only.
"""
from __future__ import annotations

from typing import Callable

import torch

from hemirad.core.fastops import flatnonzero, row_sums
from hemirad.geometry.patches import PatchTree
from hemirad.geometry.split import GrowingRows
from hemirad.transport.view import HemicubeView

# (what a node's hemicube saw, (K, 3) the corners of the node's elements) -> shoot from its
# children instead?
ShooterTest = Callable[[HemicubeView, torch.Tensor], bool]


def hidden_centroid_test(share: float = 0.01) -> ShooterTest:
    """A ``ShooterTest`` that needs no more than the render: split a node whose hemicube
    sends more than ``share`` of its power into back faces. Its centroid then lies where its
    elements are not: under an object that stands on it (a floor patch straddling a block's
    footprint), and would shoot into that object's inside."""
    def test(view: HemicubeView, corners: torch.Tensor) -> bool:
        seen_back = (view.element >= 0) & ~view.front
        return float(view.weight[seen_back].sum()) > share

    return test


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
    Attributes:
        leaf, patch: (T,) int64 each element's leaf position and patch (children inherit
            their parent's).
        cuts: per patch that shot, the nodes its power leaves from.
        shooter_splits: nodes that shoot from their children instead of themselves.
        sent: (N, 3) the power each node has shot so far, over all its shots.
        sent_by_leaf: (T0, 3) the same per initial element (by leaf position): what each
            shot's power was made of, which spreads a node's light to its near receivers.
            With ``sent``, what every receiver got from every node can be recomputed on a
            refined mesh (``adaptive.answer``).
    """

    def __init__(self, tree: PatchTree, device: torch.device, split_test: ShooterTest | None = None):
        self.tree = tree
        self.split_test = split_test
        self._leaf = GrowingRows(tree.leaf.to(device))
        self._patch = GrowingRows(tree.patch.to(device))
        self.cuts: dict[int, list[int]] = {}
        self.shooter_splits = 0
        self._members: dict[int, torch.Tensor] = {}  # per node, while the elements are unchanged
        self._bounds = list(zip(tree.lo.tolist(), tree.hi.tolist()))  # per node (lo, hi), as ints
        self.sent = torch.zeros(tree.num_nodes, 3, dtype=torch.float64, device=device)
        self.sent_by_leaf = torch.zeros(len(tree.leaf), 3, dtype=torch.float64, device=device)

    @property
    def leaf(self) -> torch.Tensor:
        return self._leaf.values

    @property
    def patch(self) -> torch.Tensor:
        return self._patch.values

    def inherit(self, parent: torch.Tensor) -> None:
        """Follow a split of the receivers: new element i lies in old element ``parent[i]`` (T',)."""
        self._leaf.inherit(parent)
        self._patch.inherit(parent)
        self._members.clear()

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
            lo, hi = self._bounds[node]
            leaf = self.leaf
            members = self._members[node] = flatnonzero((leaf >= lo) & (leaf < hi))
        return members

    def cut(self, patch: int, render: Callable[[int], HemicubeView], corners: Callable[[int], torch.Tensor]
            ) -> list[int]:
        """The nodes ``patch`` shoots from: its root, or where ``split_test`` says so, its
        children's cuts. ``render(node)`` gives a node's view, ``corners(node)`` (K, 3) its
        elements' corners."""
        if patch in self.cuts:
            return self.cuts[patch]
        nodes, pending = [], [int(self.tree.root[patch])]
        while pending:
            node = pending.pop()
            children = self.tree.children(node)
            if children and self.split_test is not None and self.split_test(render(node), corners(node)):
                pending += reversed(children)
                self.shooter_splits += 1
            else:
                nodes.append(node)
        self.cuts[patch] = nodes
        return nodes

    def state_dict(self) -> dict:
        """The per-element rows and the cuts made, as tensors."""
        patches = sorted(self.cuts)
        sizes = torch.tensor([len(self.cuts[p]) for p in patches], dtype=torch.int64)
        nodes = torch.tensor([n for p in patches for n in self.cuts[p]], dtype=torch.int64)
        return {"leaf": self.leaf.cpu().clone(), "patch": self.patch.cpu().clone(),
                "cut_patches": torch.tensor(patches, dtype=torch.int64), "cut_sizes": sizes, "cut_nodes": nodes,
                "shooter_splits": self.shooter_splits, "sent": self.sent.cpu().clone(),
                "sent_by_leaf": self.sent_by_leaf.cpu().clone()}

    def load_state_dict(self, state: dict, num_elements: int) -> None:
        """Continue from ``state_dict()``'s output for a mesh of ``num_elements``; ValueError if it does not fit."""
        leaf, patch = state["leaf"], state["patch"]
        for name, rows in (("leaf", leaf), ("patch", patch)):
            if not isinstance(rows, torch.Tensor) or rows.shape != (num_elements,) or rows.dtype != torch.int64:
                raise ValueError(f"patches.{name} must be a ({num_elements},) int64 tensor")
        sizes, nodes, patches = state["cut_sizes"], state["cut_nodes"], state["cut_patches"]
        if int(sizes.sum()) != len(nodes) or len(sizes) != len(patches):
            raise ValueError("the patches' cuts do not fit together")
        device = self.leaf.device
        self._leaf, self._patch = GrowingRows(leaf.to(device)), GrowingRows(patch.to(device))
        self._members.clear()
        self.cuts = {int(p): part.tolist() for p, part in zip(patches, torch.split(nodes, sizes.tolist()))}
        self.shooter_splits = int(state["shooter_splits"])
        for name in ("sent", "sent_by_leaf"):
            rows, want = state.get(name), getattr(self, name)
            if not isinstance(rows, torch.Tensor) or rows.shape != want.shape or rows.dtype != torch.float64:
                raise ValueError(f"patches.{name} must be a {tuple(want.shape)} float64 tensor")
        self.sent, self.sent_by_leaf = state["sent"].to(device), state["sent_by_leaf"].to(device)
