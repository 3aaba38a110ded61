"""The light of every shooting node at once: its kept row and near field as two sparse
matrices, so that a sweep in which every patch shoots its unshot power (Jacobi) costs two
sparse products instead of a Python loop of shots (docs/DESIGN.md §1.4).

A node's shot is linear in the unshot power of its leaves (the elements of its patch tree),
summed by the near field's sources they lie in (the elements the solve began with, whose
power spreads its light to its near receivers, ``nearfield``): receiver j gets

    F_sj (sum_l far_scale_l P_l)               from G's row, where j is not near s,
    sum_s W_sj P_s                             where it is,

for leaf powers P_l and source powers P_s (3,). Over all nodes that is  far @ Q + near @ P
with ``far`` (T, N) the rows with their near receivers removed, Q (N, 3) each node's
far-scaled power, ``near`` (T, T0) the near weights, a node's k sources in the columns
lo..lo + k - 1 of its leaf positions [lo, hi), and P (T0, 3) those sources' power. Both
matrices are kept sorted by (receiver, column), whatever order the nodes were added in, so a
sum over them is the same bit for bit in a run resumed from a checkpoint.

What a group of nodes adds (their rows' small receivers and their near fields) is made in
parts that are functions of the mesh and the nodes' views alone (``GroupLight``), so a worker
thread makes them while the solver draws the next group's hemicubes, and the solver makes
them too where it would wait for the worker.
"""
from __future__ import annotations

import threading
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import torch

from hemirad.core.fastops import flatnonzero
from hemirad.geometry.mesh import Mesh
from hemirad.transport.nearfield import NearReceivers, NearShooter, near_fields
from hemirad.transport.smallreceivers import small_receiver_rows
from hemirad.transport.view import HemicubeView

# Bytes an entry of the matrices costs: an int32 column index and a float64 value (int32
# indices: a third less memory than int64 before a sweep outgrows ``solver.cache_mb``).
ENTRY_BYTES = 12
#: A sweep group's small-receiver rows are made this many views at a pass, a part of its ``GroupLight``.
ROW_BATCH = 8


@dataclass(frozen=True)
class _NodeLight:
    lo: int  # the node's leaf positions [lo, hi)
    far_index: torch.Tensor  # (m,) int32 receivers of G's row, near ones removed (int32: it waits for the merge)
    far_values: torch.Tensor  # (m,)
    near_rows: torch.Tensor  # (n,)
    near_weights: torch.Tensor  # (k, n)


class _SortedCSR:
    """A (R, C) sparse matrix kept in CSR form, its entries sorted by (row, column), that new
    entries are merged into in linear time: the same matrix, bit for bit, whatever batches
    they came in (a full sort of every entry at each sweep that added nodes took 6.7 s of a
    57 s answer run on office)."""

    def __init__(self, shape: tuple[int, int], device: torch.device):
        self.shape = shape
        self.crow = torch.zeros(shape[0] + 1, dtype=torch.int32, device=device)
        self.columns = torch.zeros(0, dtype=torch.int32, device=device)
        self.values = torch.zeros(0, dtype=torch.float64, device=device)

    def merge(self, key: torch.Tensor, values: torch.Tensor) -> None:
        """Add the entries (E,) ``values`` at (E,) int64 ``key`` = row * C + column, none of them
        already held. The temporaries are kept few (a refined room's last sweep merges 18
        million entries: each 8 bytes an entry more is 150 MB more at the solve's peak)."""
        R, C = self.shape
        key, order = torch.sort(key)
        values = values.index_select(0, order)
        del order
        held = torch.repeat_interleave(torch.arange(R, device=key.device), torch.diff(self.crow)) * C + self.columns
        total = len(held) + len(key)
        # where each new entry goes among the held ones (no ties: every (row, column) is new)
        new_at = torch.searchsorted(held, key).add_(torch.arange(len(key), device=key.device))
        del held
        old_at = flatnonzero(torch.ones(total, dtype=torch.bool, device=key.device).index_fill_(0, new_at, False))
        self.columns = torch.empty(total, dtype=torch.int32, device=key.device).index_copy_(
            0, old_at, self.columns).index_copy_(0, new_at, (key % C).to(torch.int32))
        self.values = torch.empty(total, dtype=torch.float64, device=key.device).index_copy_(
            0, old_at, self.values).index_copy_(0, new_at, values)
        del old_at, new_at, values
        self.crow = self.crow + torch.cat([self.crow.new_zeros(1), torch.cumsum(
            torch.bincount(key.div_(C, rounding_mode="floor"), minlength=R), 0).to(torch.int32)])

    def matrix(self) -> torch.Tensor:
        with warnings.catch_warnings():  # torch's note that its sparse CSR support is in beta
            warnings.simplefilter("ignore", UserWarning)
            return torch.sparse_csr_tensor(self.crow, self.columns, self.values, self.shape, check_invariants=False)


class SweepTransport:
    """The light of the nodes that shot, for shooting them all at once.

    Args:
        num_elements: T, the receivers (the current mesh).
        num_nodes: N, the patch tree's nodes.
        num_leaves: T0, the leaves of the patch trees (leaf positions).
    Attributes:
        node_of_leaf: (T0,) the node each leaf shoots with (-1: its patch has not shot yet).
        column_of_leaf: (T0,) the near matrix's column of each leaf's source.
        far_scale: (T0,) per leaf, the scale of its node's row (``NearReceivers.far_scale``).
        nbytes: what the matrices hold.
    """

    def __init__(self, num_elements: int, num_nodes: int, num_leaves: int, device: torch.device):
        self.shape = (num_elements, num_nodes, num_leaves)
        self.device = device
        self.node_of_leaf = torch.full((num_leaves,), -1, dtype=torch.int64, device=device)
        # a node's k sources take the near matrix's columns lo..lo + k - 1 of its leaves' [lo, hi)
        self.column_of_leaf = torch.arange(num_leaves, device=device)
        self.far_scale = torch.ones(num_leaves, dtype=torch.float64, device=device)
        self._nodes: set[int] = set()
        self.groups: set[int] = set()  # the caller's groups of patches whose nodes were all added
        self._pending: dict[int, _NodeLight] = {}  # added since the matrices were last merged
        self._far = _SortedCSR((num_elements, num_nodes), device)
        self._near = _SortedCSR((num_elements, num_leaves), device)
        self._matrices: tuple[torch.Tensor, torch.Tensor] | None = None
        self.nbytes = 0

    def __contains__(self, node: int) -> bool:
        return node in self._nodes

    def add(self, node: int, bounds: tuple[int, int], form_factors: torch.Tensor, near: NearReceivers | None,
            source: torch.Tensor) -> None:
        """Add ``node``, shooting for the leaves ``bounds`` [lo, hi), with its row ``form_factors``
        (T,), its near receivers (None: none) and ``source`` (hi - lo,) the near field's
        source each leaf lies in (``PatchShooters.sources``)."""
        lo, hi = bounds
        far = form_factors != 0
        rows = torch.empty(0, dtype=torch.int64, device=self.device)
        weights = form_factors.new_zeros(0, 0)
        self.column_of_leaf[lo:hi] = lo + source
        if near is not None and len(near.rows):
            far.index_fill_(0, near.rows, False)
            rows, weights = near.rows, near.weights
            self.far_scale[lo:hi] = near.far_scale.index_select(0, source)
        far_index = flatnonzero(far)
        self._pending[node] = _NodeLight(lo, far_index.to(torch.int32), form_factors.index_select(0, far_index), rows,
                                         weights)
        self._nodes.add(node)
        self.node_of_leaf[lo:hi] = node
        self.nbytes += ENTRY_BYTES * (len(far_index) + weights.numel())
        self._matrices = None

    def _merge(self) -> None:
        """Merge the nodes added since into the matrices."""
        nodes = sorted(self._pending)
        lights = [self._pending.pop(n) for n in nodes]
        far_columns = self._far.shape[1]
        far_key = torch.cat([light.far_index.long() * far_columns + node for node, light in zip(nodes, lights)])
        far_values = torch.cat([light.far_values for light in lights])
        near_columns = self._near.shape[1]
        lights = [light for light in lights if light.near_rows.numel()]
        near_key = torch.cat([light.near_rows.repeat(len(light.near_weights)) * near_columns
                              + (light.lo + torch.arange(len(light.near_weights), device=self.device)
                                 ).repeat_interleave(len(light.near_rows)) for light in lights]) if lights else None
        near_values = torch.cat([light.near_weights.reshape(-1) for light in lights]) if lights else None
        del lights  # the pending light, now in the keys and values
        self._far.merge(far_key, far_values)
        del far_key, far_values
        if near_key is not None:
            self._near.merge(near_key, near_values)

    def incident(self, leaf_power: torch.Tensor) -> torch.Tensor:
        """(T, 3) the power reaching every receiver's front when every leaf shoots its (T0, 3)
        ``leaf_power`` from its node; every leaf with power must have a node."""
        if self._matrices is None:
            self._merge()
            self._matrices = (self._far.matrix(), self._near.matrix())
        far, near = self._matrices
        node = self.node_of_leaf
        if bool((node < 0).any()):
            assert not bool(leaf_power[node < 0].any()), "a leaf with unshot power has no node"
            node = node.clamp(min=0)
        node_power = torch.zeros(self.shape[1], 3, dtype=leaf_power.dtype, device=self.device).index_add_(
            0, node, self.far_scale[:, None] * leaf_power)
        incident = far @ node_power
        if near.values().numel() == 0:
            return incident
        return incident + near @ torch.zeros_like(leaf_power).index_add_(0, self.column_of_leaf, leaf_power)


class GroupLight:
    """What a sweep group's nodes send, made apart from the solver: the rows F_sj (T,) of the
    ``small`` nodes (node -> its views, each (view, pixel limit, weight): one view of weight 1,
    its hemicube's, or a lamp's eyes, whose rows the node's sums by their weights), then the
    near fields of the nodes of ``shooters`` (node -> what ``nearfield`` needs of it; empty
    with ``reach`` 0), all together (``nearfield.near_fields``), their ``form_factors`` None
    where ``small`` makes the row. ``result`` gives the rows made and the near fields, by node.

    It is made in parts, which touch no state of the solver: the rows ``ROW_BATCH`` views a part
    (``small_receiver_rows``), then the near fields. The ``worker`` thread makes a group's parts
    in order; a thread that would wait for it makes a part no thread has begun (``make_part``),
    so at a sweep's end, with nothing left to draw, both threads work on its last groups (made
    whole by one thread or the other, the lamps' group of a sweep's first shots, 0.2-0.3 s on
    office, left a core idle). Each part is a function of the mesh and its views alone: the
    same numbers whichever thread makes which."""

    def __init__(self, worker: ThreadPoolExecutor, mesh: Mesh, small: dict[int, list[tuple[HemicubeView, float, float]]],
                 shooters: dict[int, NearShooter], reach: float, totals: str):
        views = [(node, view, limit, weight) for node, made in small.items() for view, limit, weight in made]
        self._batches = [views[start:start + ROW_BATCH] for start in range(0, len(views), ROW_BATCH)]
        self._rows: list[list[torch.Tensor] | None] = [None] * len(self._batches)
        self._mesh, self._small, self._shooters, self._reach, self._totals = mesh, small, shooters, reach, totals
        self._lock = threading.Condition()
        self._begun = 0  # parts begun: the row batches in order, then the near fields
        self._finished = 0  # row batches finished
        self._made: tuple[dict[int, torch.Tensor], dict[int, NearReceivers]] | None = None
        self._error: BaseException | None = None
        worker.submit(self._make_all)

    def done(self) -> bool:
        return self._made is not None or self._error is not None

    def _take(self) -> int | None:
        """The next part no thread has begun, None where there is none (the near fields wait
        for every row: the thread that finishes the last takes them)."""
        with self._lock:
            batches = len(self._batches)
            if self._error is not None or self._begun > batches or (
                    self._begun == batches and self._finished < batches):
                return None
            self._begun += 1
            return self._begun - 1

    def make_part(self) -> bool:
        """Make on this thread a part of the group no thread has begun; whether there was one."""
        part = self._take()
        if part is None:
            return False
        try:
            if part < len(self._batches):
                batch = self._batches[part]
                rows = small_receiver_rows([view for _, view, _, _ in batch], self._mesh.corners, self._mesh.areas,
                                           [limit for _, _, limit, _ in batch])
                with self._lock:
                    self._rows[part] = rows
                    self._finished += 1
            else:
                made = self._near_fields()
                with self._lock:  # the views are let go now, not when the worker's queue lets go of the group
                    self._batches, self._small, self._shooters, self._made = [], {}, {}, made
                    self._lock.notify_all()
        except BaseException as error:  # handed to the thread that takes the group in (``result``)
            with self._lock:
                self._error = error
                self._lock.notify_all()
        return True

    def _make_all(self) -> None:
        while self.make_part():
            pass

    def _near_fields(self) -> tuple[dict[int, torch.Tensor], dict[int, NearReceivers]]:
        """The rows by node, from their batches, and the near fields made with them."""
        rows: dict[int, torch.Tensor] = {}
        views = [(node, weight) for batch in self._batches for node, _, _, weight in batch]
        for (node, weight), row in zip(views, (row for made in self._rows for row in made)):
            if len(self._small[node]) == 1:
                rows[node] = row
            else:  # the eyes' rows summed in their order, as ``ProgressiveSolver.node_row`` sums them
                rows.setdefault(node, torch.zeros_like(row)).add_(weight * row)
        self._rows = []
        if not self._shooters:
            return rows, {}
        made = [replace(s, form_factors=rows[node]) if s.form_factors is None else s
                for node, s in self._shooters.items()]
        return rows, dict(zip(self._shooters, near_fields(self._mesh, made, self._reach, self._totals)))

    def result(self) -> tuple[dict[int, torch.Tensor], dict[int, NearReceivers]]:
        """The rows made and the near fields, by node, waiting for the thread making the last part."""
        with self._lock:
            while not self.done():
                self._lock.wait()
            if self._error is not None:
                raise self._error
            return self._made


def make_a_part(groups: Sequence[GroupLight]) -> bool:
    """Make on this thread a part that no thread has begun of the oldest of ``groups`` (oldest
    first, sent to one worker, which takes them in that order) that has one; whether there was one.

    A thread that must wait for the oldest does this instead while it can. At the end of a
    sweep, when nothing is left to draw, a worker alone on the groups sent last left a core
    idle: floating's refined solve (3,416 elements, 2 cores) drew its reflectors in 0.70 s and
    waited 0.85 s more for their light. Measured (the study's runs from x2 to 3,416 elements,
    two interleaved runs each), making whole groups, the newest first: floating 3.82 / 3.98 s
    -> 3.63 / 3.60 s, the Cornell box 3.47 / 3.53 -> 3.32 / 3.33 s, office 5.81 / 5.77 -> 5.69 /
    5.65 s, the same numbers; then parts of the oldest instead (the study's goal runs from x2,
    three interleaved runs): floating 3.50 -> 3.26 s, the Cornell box 3.37 -> 3.20 s, office
    5.06 -> 4.85 s, the same numbers."""
    return any(group.make_part() for group in groups)
