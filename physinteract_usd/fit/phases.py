"""Where a fit's time goes (#26): seconds per phase, kept in the fit's model ("phases_s") and printed by
`fit --json`, so a slow fit says which part was slow (the start search, the starts before the finest level,
the iterations, the final pass, the confidence estimate) without a profiler. Phases add up where one is
entered twice; the clock is the host's (`time.perf_counter`): every phase ends on a loss read back to the
host, so the GPU's queued work is in the phase that waited for it."""

from __future__ import annotations

import time
from contextlib import contextmanager


class Phases:
    """Seconds per named phase: `with phases("iterations"): ...`; `dict(phases.seconds)` for the record."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t)

    def add(self, name: str, dt: float) -> None:
        self.seconds[name] = round(self.seconds.get(name, 0.0) + float(dt), 3)


__all__ = ["Phases"]
