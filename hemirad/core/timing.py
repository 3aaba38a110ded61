"""Where a solve's time goes: one object that accumulates seconds per named phase."""
from __future__ import annotations

import time
from contextlib import contextmanager


class Profiler:
    """Accumulated wall-clock seconds per phase, e.g. ``raster``, ``gradient``, ``refine``.

    A solve owns one and hands it to the parts that do the work, so every phase is timed in
    one place and a checkpoint saves and restores all of them together.

    Args:
        phases: the phase names, in reporting order; each starts at 0. Others may be added
            by timing them.
    """

    def __init__(self, phases: tuple[str, ...] = ()):
        self.seconds: dict[str, float] = dict.fromkeys(phases, 0.0)

    @contextmanager
    def phase(self, name: str):
        """Time the ``with`` block and add it to ``name`` (also when the block raises)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - start)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def state_dict(self) -> dict[str, float]:
        """The seconds per phase (a copy)."""
        return dict(self.seconds)

    def load_state_dict(self, seconds: dict) -> None:
        """Continue from ``state_dict()``'s output (a resumed run's earlier time)."""
        self.seconds = {name: float(value) for name, value in seconds.items()}
