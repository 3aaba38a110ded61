"""Form-factor rows kept between the shots of one shooter, so that no hemicube is rendered
twice for the same shooter on the same mesh."""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable

import torch

from hemirad.core.fastops import flatnonzero


class FormFactorRows:
    """The rows F_s. of the shooters that shot, sparse, least recently used dropped first.

    A row holds the elements with F_sj > 0 and their F_sj, bit for bit as rendered; it is
    valid for the mesh it was rendered on: ``clear`` when the mesh changes.

    Args:
        budget_bytes: the most the kept rows may hold (their indices and values); 0 keeps none.
    Attributes:
        hits, misses: lookups that found a row, and that did not.
    """

    def __init__(self, budget_bytes: int):
        self.budget_bytes = int(budget_bytes)
        self._rows: OrderedDict[Hashable, tuple[torch.Tensor, torch.Tensor]] = OrderedDict()
        self.nbytes = 0
        self.hits = self.misses = 0

    def __len__(self) -> int:
        return len(self._rows)

    def get(self, shooter: Hashable, num_elements: int) -> torch.Tensor | None:
        """(T,) the dense row of ``shooter`` (T = ``num_elements``), or None when it is not kept."""
        row = self._rows.get(shooter)
        if row is None:
            self.misses += 1
            return None
        self.hits += 1
        self._rows.move_to_end(shooter)
        index, values = row
        return torch.zeros(num_elements, dtype=values.dtype, device=values.device).index_copy_(0, index, values)

    def put(self, shooter: Hashable, form_factors: torch.Tensor) -> None:
        """Keep the (T,) row of ``shooter``, dropping the least recently used rows over the budget."""
        index = flatnonzero(form_factors != 0)
        values = form_factors.index_select(0, index)
        size = index.element_size() * len(index) + values.element_size() * len(values)
        if size > self.budget_bytes:
            return
        old = self._rows.pop(shooter, None)
        if old is not None:
            self.nbytes -= sum(t.element_size() * len(t) for t in old)
        while self._rows and self.nbytes + size > self.budget_bytes:
            _, dropped = self._rows.popitem(last=False)
            self.nbytes -= sum(t.element_size() * len(t) for t in dropped)
        self._rows[shooter] = (index, values)
        self.nbytes += size

    def clear(self) -> None:
        """Forget every row (the mesh changed)."""
        self._rows.clear()
        self.nbytes = 0
