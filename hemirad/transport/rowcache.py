"""Form-factor rows kept between the shots of one shooter, so that no hemicube is rendered
twice for the same shooter on the same mesh."""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass

import torch

from hemirad.core.fastops import flatnonzero

# Bytes a kept entry costs: an int32 element index and its float64 form factor.
ENTRY_BYTES = 12
# Rows are packed into slabs of this size (or the budget, when smaller). Thousands of small
# long-lived rows allocated one by one among a shot's short-lived temporaries fragment
# glibc's heap: measured, the process grew 7x faster than the rows it kept.
SLAB_BYTES = 64 << 20


@dataclass
class _Slab:
    """Storage for many rows, filled front to back; freed with the last row that lives in it."""

    index: torch.Tensor  # (n,) int32
    values: torch.Tensor  # (n,) float64
    used: int = 0


@dataclass
class _Row:
    slab: _Slab
    start: int
    count: int


class FormFactorRows:
    """The rows F_s. of the shooters that shot, sparse, least recently used dropped first.

    A row holds the elements with F_sj > 0 and their F_sj, bit for bit as rendered; it is
    valid for the mesh it was rendered on: ``clear`` when the mesh changes.

    Args:
        budget_bytes: the most the kept rows may hold (``ENTRY_BYTES`` per element a row
            reaches); 0 keeps none. Slabs whose rows were partly dropped may hold up to
            one more slab's worth while they empty.
    """

    def __init__(self, budget_bytes: int):
        self.budget_bytes = int(budget_bytes)
        self._slab_entries = max(1, min(SLAB_BYTES, self.budget_bytes) // ENTRY_BYTES)
        self._rows: OrderedDict[Hashable, _Row] = OrderedDict()
        self._slab: _Slab | None = None
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._rows)

    def __contains__(self, shooter: Hashable) -> bool:
        """Whether ``shooter``'s row is kept (without counting as a use, as ``get`` does)."""
        return shooter in self._rows

    def get(self, shooter: Hashable, num_elements: int) -> torch.Tensor | None:
        """(T,) the dense row of ``shooter`` (T = ``num_elements``), or None when it is not kept."""
        row = self._rows.get(shooter)
        if row is None:
            return None
        index = row.slab.index[row.start:row.start + row.count].long()
        values = row.slab.values[row.start:row.start + row.count]
        out = torch.zeros(num_elements, dtype=values.dtype, device=values.device).index_copy_(0, index, values)
        if row.slab is not self._slab:  # used again: move it to the newest slab, so old slabs empty
            self._drop(shooter)
            self._store(shooter, index, values)
        else:
            self._rows.move_to_end(shooter)
        return out

    def put(self, shooter: Hashable, form_factors: torch.Tensor) -> None:
        """Keep the (T,) row of ``shooter``, dropping the least recently used rows over the budget."""
        index = flatnonzero(form_factors != 0)
        if ENTRY_BYTES * len(index) > self.budget_bytes:
            return
        if shooter in self._rows:
            self._drop(shooter)
        self._store(shooter, index, form_factors.index_select(0, index))

    def _store(self, shooter: Hashable, index: torch.Tensor, values: torch.Tensor) -> None:
        count = len(index)
        while self._rows and self.nbytes + ENTRY_BYTES * count > self.budget_bytes:
            self._drop(next(iter(self._rows)))
        slab = self._slab
        if slab is None or slab.used + count > len(slab.index):
            n = max(self._slab_entries, count)
            slab = self._slab = _Slab(torch.empty(n, dtype=torch.int32, device=values.device),
                                      torch.empty(n, dtype=values.dtype, device=values.device))
        slab.index[slab.used:slab.used + count] = index
        slab.values[slab.used:slab.used + count] = values
        self._rows[shooter] = _Row(slab, slab.used, count)
        slab.used += count
        self.nbytes += ENTRY_BYTES * count

    def _drop(self, shooter: Hashable) -> None:
        row = self._rows.pop(shooter)
        self.nbytes -= ENTRY_BYTES * row.count

    def clear(self) -> None:
        """Forget every row (the mesh changed)."""
        self._rows.clear()
        self._slab = None
        self.nbytes = 0
