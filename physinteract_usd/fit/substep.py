"""One substep for models compared against each other (moved from select.py, which re-exports it,
so that the optimiser's Gauss-Newton step can use it without an import cycle), and the one guard
every probe runs under (`kept_rung`): a forward pass the fit does not keep leaves the adaptive
substep's rung as it found it."""

from __future__ import annotations


class pinned_substep:
    """Within it, the simulator's adaptive substep is the one for a field whose largest E is
    `e_bound` (its rung; None: unchanged), whatever E is simulated. Models compared on held-back
    frames are simulated at one substep: the adaptive substep depends on the largest E and, through
    its hysteresis, on what was simulated before, and a different time step changes the loss (on
    hemp_rope, grid 32, by about 2% between two rungs: as much as the candidates differ).
    On exit the rung it found is restored as well as the adaptivity: a probe must not change the
    main fit's later substep (the hysteresis would otherwise keep a stiffer probe's rung; #26, as
    fit/parts_start.py's restore for the H200's hemp_rope MA 0.80 -> 0.49)."""

    def __init__(self, prob, e_bound: float | None):
        self.sim = getattr(prob, "sim", None)
        self.e_bound = e_bound

    def __enter__(self):
        sim = self.sim
        self.was = None
        if self.e_bound is None or sim is None or not getattr(sim, "adaptive", False):
            return self
        self.was = sim.adaptive
        self.bound0 = sim.e_bound
        want = sim.bound_for(float(self.e_bound))
        if want != sim.e_bound:
            sim._use_bound(want)
        sim.adaptive = False
        return self

    def __exit__(self, *exc):
        if self.was is not None:
            self.sim.adaptive = self.was
            if self.sim.e_bound != self.bound0:
                self.sim._use_bound(self.bound0)
        return False


class kept_rung:
    """Within it the adaptive substep follows the fields simulated, as always; on exit the rung it
    found is restored. Every probe (a forward pass whose simulation the fit does not keep: the parts
    start's simplex, select's part probes, the batched sweeps of `FitProblem.losses_batch`) runs under
    it, so the probes neither move the main fit's later substep (the hysteresis keeps a stiffer probe's
    rung: the H200's hemp_rope, MA 0.80 -> 0.49) nor depend on the order they ran in: each probe
    takes the rung `ensure_stable` gives its field from the rung the probes started at. Nested
    guards restore in order. A probe that raises restores too."""

    def __init__(self, prob):
        sim = getattr(prob, "sim", prob)
        self.sim = sim if getattr(sim, "adaptive", False) and hasattr(sim, "e_bound") else None

    def __enter__(self):
        self.bound0 = None if self.sim is None else self.sim.e_bound
        return self

    def __exit__(self, *exc):
        if self.bound0 is not None and self.sim.e_bound != self.bound0:
            self.sim._use_bound(self.bound0)
        return False
