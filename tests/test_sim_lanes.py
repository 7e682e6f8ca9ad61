"""Two lanes (sim/lanes.py): a rollout whose per-frame CPU graphs run each substep's particle kernels over two
halves of the particles on two threads (lane B's scatter into a grid of its own, summed by lane A before the grid
update) gives the one-lane forward and gradients up to float summation order, every effect on, with and without
substep tapes, and the same numbers run after run (a race between the lanes would show as a difference); the
gradients also pass test_sim_gradients' finite-difference checks in float64 on two lanes."""

from __future__ import annotations

import functools

import pytest
import torch

from physinteract_usd.sim import lanes as lanes_mod
from physinteract_usd.sim import Rollout
import test_sim_gradients as tsg
from test_sim_tape import EFFECTS, _run, _scene


def _with_lanes(n, fn, *a, **kw):
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(lanes_mod, "LANES", n)
        mp.setattr(lanes_mod, "MIN_PARTICLES", 0)
        return fn(*a, **kw)


def _close(a, b, rtol):
    for ga, gb in zip(a, b):
        for u, v in zip(ga, gb):
            scale = float(v.abs().max()) or 1.0
            assert float((u - v).abs().max()) <= rtol * scale, (u, v)


@pytest.mark.parametrize("tape,ground_contact", [(True, "nodes"), (False, "nodes"), (True, "penalty")])
def test_two_lanes_give_the_one_lane_gradients(tape, ground_contact):
    m, ctrl, pts, traj = _scene("float64", ground_contact=ground_contact)
    ro1, g1 = _with_lanes(1, _run, m, ctrl, pts, traj, tape)
    assert ro1.solver.lanes is None
    ro2, g2 = _with_lanes(2, _run, m, ctrl, pts, traj, tape)
    assert ro2.solver.lanes is not None                          # it ran on two lanes
    assert any(isinstance(g, lanes_mod.LanePair) for g in ro2._fwd_store_graphs.values())
    _close(g2, g1, 1e-9)
    # the same numbers again (no race between the lanes): bitwise
    for _ in range(2):
        _, g3 = _with_lanes(2, _run, m, ctrl, pts, traj, tape)
        for a, b in zip(g2, g3):
            for u, v in zip(a, b):
                assert torch.equal(u, v)


def test_two_lanes_forward_float32_within_summation_order():
    m, ctrl, pts, traj = _scene("float32", effects={})

    def fwd():
        ro = Rollout(m, ctrl)
        E = torch.linspace(2e3, 4e3, len(pts), dtype=torch.float32)
        with torch.no_grad():
            ro(E, trajectories={0: torch.tensor(traj, dtype=torch.float32)})    # the eager one-off forward
            return ro, ro(E, trajectories={0: torch.tensor(traj, dtype=torch.float32)})

    _, (x1, F1) = _with_lanes(1, fwd)
    ro2, (x2, F2) = _with_lanes(2, fwd)
    assert ro2.solver.lanes is not None
    assert torch.allclose(x2, x1, rtol=1e-5, atol=1e-5 * float(x1.abs().max()))
    assert torch.allclose(F2, F1, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("case", [functools.partial(tsg.test_grad_pull_on_ground_fixed_corotated, "nodes"),
                                  functools.partial(tsg.test_grad_pull_on_ground_fixed_corotated, "penalty"),
                                  tsg.test_grad_plasticity_viscoelasticity_sphere_release],
                         ids=["ground_nodes", "ground_penalty", "plasticity_visco"])
def test_two_lanes_gradients_match_finite_differences(case, monkeypatch):
    """test_sim_gradients' FD checks (float64, relative error < 1e-4), run on two lanes."""
    made = []

    class Counted(lanes_mod.Lanes):
        def __init__(self, sol):
            super().__init__(sol)
            made.append(self)

    monkeypatch.setattr(lanes_mod, "LANES", 2)
    monkeypatch.setattr(lanes_mod, "MIN_PARTICLES", 0)
    monkeypatch.setattr(lanes_mod, "Lanes", Counted)
    case()
    assert made                       # the rollout ran on two lanes


def test_the_default_takes_two_lanes_only_with_a_core_to_spare(monkeypatch):
    """`auto_lanes` (LANES None) with AUTO on: two lanes where >= 2 cores are the process's and one sits idle,
    decided once; with AUTO off (the default): one lane."""
    monkeypatch.setattr(lanes_mod, "AUTO", True)
    for cores, spare, want in ((2, 1.0, 2), (2, 0.2, 1), (1, 1.0, 1), (4, 0.7, 2)):
        monkeypatch.setattr(lanes_mod, "_AUTO", None)
        monkeypatch.setattr(lanes_mod, "free_cores", lambda c=cores: c)
        monkeypatch.setattr(lanes_mod, "spare_cores", lambda interval=0.1, s=spare: s)
        assert lanes_mod.auto_lanes() == want, (cores, spare)
    monkeypatch.setattr(lanes_mod, "spare_cores", lambda interval=0.1: 0.0)
    assert lanes_mod.auto_lanes() == 2                     # once decided, the process keeps it
    monkeypatch.setattr(lanes_mod, "AUTO", False)
    monkeypatch.setattr(lanes_mod, "_AUTO", None)
    assert lanes_mod.auto_lanes() == 1
    assert -1.0 <= lanes_mod.spare_cores(0.02) <= (__import__("os").cpu_count() or 1)
