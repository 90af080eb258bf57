"""Wall time of the named phases of a run, for benchmarks and ``--json`` summaries.

    phases = Phases()
    with phases("filter loop"):
        ...
    phases.seconds            # {"filter loop": 1.23}

``NO_PHASES`` measures nothing and costs nothing: the default of the functions that take ``phases``.
"""

from __future__ import annotations

import time
from contextlib import contextmanager, nullcontext

__all__ = ["Phases", "NO_PHASES"]


class Phases:
    """Seconds spent in each named phase (summed when a phase is entered more than once), in order of entry."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - start)

    def add(self, name: str, seconds: float) -> None:
        """Count ``seconds`` to the phase ``name``."""
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


class _NoPhases:
    @property
    def seconds(self) -> dict[str, float]:
        return {}

    def __call__(self, name: str):
        return nullcontext()

    def add(self, name: str, seconds: float) -> None:
        pass


NO_PHASES = _NoPhases()
