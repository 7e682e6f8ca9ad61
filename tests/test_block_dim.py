"""The solver's threads per block (sim/solver.py `BLOCK_DIM`, opt-in for CUDA, #26): every launch of a
substep, forward and adjoint, carries it; the CPU keeps Warp's 256 (no module variant to compile); the
frame-shape graphs' warm-up is keyed by it (a new variant loads its modules outside a capture)."""

from __future__ import annotations

import sys

import pytest
import warp as wp

from physinteract_usd.sim import Rollout
from physinteract_usd.sim import solver as solver_mod
from test_fused_zero import _loss_and_grads, _scene


def test_cpu_solver_keeps_warps_block_dim(monkeypatch):
    m, ctrl, *_ = _scene()
    monkeypatch.setattr(solver_mod, "BLOCK_DIM", 64)
    assert Rollout(m, ctrl, graphs=False).solver.block_dim == 256
    monkeypatch.setattr(solver_mod, "BLOCK_DIM", None)
    assert Rollout(m, ctrl, graphs=False).solver.block_dim == 256


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "separate"])
def test_every_solver_launch_carries_the_block_dim(monkeypatch, fused):
    """A forward and backward (every effect, pins, a collider) with the solver's block_dim set to 64: every
    wp.launch issued from sim/solver.py carries it (launched at 256 here, so nothing compiles), and the results
    are bitwise those of the default."""
    m, ctrl, pts, eff, trajs = _scene()
    monkeypatch.setattr(solver_mod, "FUSED_KERNELS", fused)
    monkeypatch.setattr(solver_mod, "FUSED_ZERO", True)
    ref = _loss_and_grads(Rollout(m, ctrl, graphs=False), pts, eff, trajs)
    ro = Rollout(m, ctrl, graphs=False)
    ro.solver.block_dim = 64
    seen = []
    launch = wp.launch

    def rec(*a, **k):
        f = sys._getframe(1)
        if f.f_code.co_filename.endswith("solver.py"):
            seen.append(k.get("block_dim"))
            k["block_dim"] = 256
        return launch(*a, **k)

    monkeypatch.setattr(wp, "launch", rec)
    got = _loss_and_grads(ro, pts, eff, trajs)
    assert len(seen) > 50
    assert set(seen) == {64}, sorted(set(map(str, seen)))
    for call_r, call_g in zip(ref, got):
        for a, b in zip(call_r, call_g):
            assert (a == b).all()


def test_frame_graph_warm_key_holds_the_block_dim():
    m, ctrl, *_ = _scene()
    ro = Rollout(m, ctrl, graphs=True)
    k256 = ro._warm_key("forward")
    ro.solver.block_dim = 64
    assert ro._warm_key("forward") != k256


def test_every_simulator_launch_carries_one_block_dim(monkeypatch):
    """The set-up's CUDA warm-up compiles the simulator's modules at one block size (`launch_block_dim`); a launch
    at another size compiles a whole module again (a fresh H200's first fit after the warm-up still compiled the core
    module and the frame graphs' at 256, 14.5 s, 2026-11-29). A forward and backward through the frame-shape
    graphs' path, the rest state included: every launch from the simulator's files carries the same size."""
    from physinteract_usd.sim import rollout as rollout_mod

    m, ctrl, pts, eff, trajs = _scene()
    monkeypatch.setattr(rollout_mod, "FRAME_GRAPHS", True)
    monkeypatch.setattr(solver_mod, "launch_block_dim", lambda device: 64)
    ro = Rollout(m, ctrl, graphs=False)
    assert ro.frame_graphs and ro.solver.block_dim == 64
    seen = {}
    launch = wp.launch

    def rec(*a, **k):
        f = sys._getframe(1).f_code.co_filename
        if f.endswith(("solver.py", "rollout.py", "state.py")):
            seen.setdefault(f.rsplit("/", 1)[-1], []).append(k.get("block_dim"))
            k["block_dim"] = 256
        return launch(*a, **k)

    monkeypatch.setattr(wp, "launch", rec)
    _loss_and_grads(ro, pts, eff, trajs)
    assert {"solver.py", "rollout.py", "state.py"} <= set(seen), sorted(seen)
    for name, dims in seen.items():
        assert set(dims) == {64}, (name, sorted(set(map(str, dims))))
