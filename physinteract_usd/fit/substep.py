"""One substep for models compared against each other (moved from select.py, which re-exports it,
so that the optimiser's Gauss-Newton step can use it without an import cycle)."""

from __future__ import annotations


class pinned_substep:
    """Within it, the simulator's adaptive substep is the one for a field whose largest E is
    `e_bound` (its rung; None: unchanged), whatever E is simulated. Models compared on held-back
    frames are simulated at one substep: the adaptive substep depends on the largest E and, through
    its hysteresis, on what was simulated before, and a different time step changes the loss (on
    hemp_rope, grid 32, by about 2% between two rungs: as much as the candidates differ)."""

    def __init__(self, prob, e_bound: float | None):
        self.sim = getattr(prob, "sim", None)
        self.e_bound = e_bound

    def __enter__(self):
        sim = self.sim
        self.was = None
        if self.e_bound is None or sim is None or not getattr(sim, "adaptive", False):
            return self
        self.was = sim.adaptive
        want = sim.bound_for(float(self.e_bound))
        if want != sim.e_bound:
            sim._use_bound(want)
        sim.adaptive = False
        return self

    def __exit__(self, *exc):
        if self.was is not None:
            self.sim.adaptive = self.was
        return False
