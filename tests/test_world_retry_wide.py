"""The world generator's truth (synth/world.py World.run) that stays non-finite after two halvings of the step
takes the wide grid on its fourth run (#23): dev_0190 (a 2.9 kPa, 20 kg/m^3 clamped bar) swings down past the
grid's floor and goes non-finite at frame 3 at 447, 894 and 1788 substeps; in the wide grid it hangs, fine.
The rollout is faked here (the real one is ~1 min of CPU): it fails unless the grid reaches a whole extent below
the object, as the real one did on the CPU (the wide grid at 447 substeps: 8 frames, the bar 12.5 cm lower)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import physinteract_usd.sim as sim_mod
from physinteract_usd.errors import SimulationError
from physinteract_usd.synth.world import World, draw_world


def _fake(calls, world, mode):
    class FakeRollout:
        def __init__(self, model, control):
            self.model = model

        def __call__(self, E, nu):
            g = self.model.grid
            calls.append((float(g.lower[1]), int(self.model.substeps)))
            wide = g.lower[1] < world.x0[:, 1].min() - world.extent
            if mode == "never" or not wide:
                raise SimulationError("simulation state became non-finite (1 particles, e.g. particle 0)", frame=3)
            n = len(world.x0)
            return torch.zeros(world.T, n, 3), torch.eye(3).expand(world.T, n, 3, 3).clone()
    return FakeRollout


def test_a_persistent_non_finite_truth_takes_the_wide_grid(monkeypatch):
    w = World(draw_world(190, "dev", {"settle": False}))   # the main run alone (its draw settles it)
    calls = []
    monkeypatch.setattr(sim_mod, "Rollout", _fake(calls, w, "wide"))
    x, F = w.run()
    assert x.shape[0] == w.T and len(calls) == 4
    s0 = calls[0][1]
    assert s0 == 447                                            # the draw's own substep rule, unchanged
    assert [c[1] for c in calls] == [s0, 2 * s0, 4 * s0, 4 * s0]  # no further halving for the wide run
    assert calls[0][0] == calls[1][0] == calls[2][0] and calls[3][0] < calls[2][0] - w.extent * 0.9
    assert w.substeps == 4 * s0


def test_it_still_raises_when_the_wide_grid_fails_too(monkeypatch):
    w = World(draw_world(190, "dev", {"settle": False}))   # the main run alone (its draw settles it)
    calls = []
    monkeypatch.setattr(sim_mod, "Rollout", _fake(calls, w, "never"))
    with pytest.raises(SimulationError, match="non-finite"):
        w.run()
    assert len(calls) == 4
