"""`pinned_substep` (fit/substep.py) leaves the adaptive substep's rung as it found it (#26): the Gauss-Newton
step, select's held-back frame losses and strain exposure, and diagnose's refits pin a stiffer rung for their
probes; through the hysteresis that rung would otherwise stay for the main fit's later forwards."""

from __future__ import annotations

import types

from physinteract_usd.fit.substep import pinned_substep
from physinteract_usd.sim.cfl import rung


class _Sim:
    """The rung bookkeeping of simulation.Simulation (bound_for, _use_bound, ensure_stable's hysteresis)."""

    def __init__(self, top=1.0e5, e=1.0e4):
        self.top, self.adaptive, self.used = top, True, []
        self.e_bound = self.bound_for(e)

    def bound_for(self, e_max):
        return rung(e_max, self.top)

    def _use_bound(self, b):
        self.used.append(b)
        self.e_bound = b

    def ensure_stable(self, e_max):
        want = self.bound_for(e_max)
        if want < self.e_bound and e_max * 1.1 > want:
            want = self.e_bound
        if want != self.e_bound:
            self._use_bound(want)


def test_a_stiffer_pin_is_undone_on_exit():
    sim = _Sim()
    b0 = sim.e_bound
    with pinned_substep(types.SimpleNamespace(sim=sim), 4.0e4):
        assert sim.e_bound > b0 and not sim.adaptive
    assert sim.adaptive and sim.e_bound == b0
    # the main fit's next forward at a field just under its rung stays on it (as without the probe)
    sim.ensure_stable(b0 * 0.95)
    assert sim.e_bound == b0


def test_the_rung_is_restored_when_the_probe_raises():
    sim = _Sim()
    b0 = sim.e_bound
    try:
        with pinned_substep(types.SimpleNamespace(sim=sim), 4.0e4):
            raise RuntimeError("probe failed")
    except RuntimeError:
        pass
    assert sim.adaptive and sim.e_bound == b0


def test_same_rung_and_no_pin_touch_nothing():
    sim = _Sim()
    with pinned_substep(types.SimpleNamespace(sim=sim), sim.e_bound):
        pass
    with pinned_substep(types.SimpleNamespace(sim=sim), None):
        pass
    assert sim.used == [] and sim.adaptive
