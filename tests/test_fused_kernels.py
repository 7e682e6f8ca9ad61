"""Fused transfer kernels (sim/solver.py `FUSED_KERNELS`: p2g_fused = stress + scatter, g2p_fused =
gather + particle update, forward only): the loss and every gradient bitwise those of the separate
kernels, and fewer launches per substep."""

from __future__ import annotations

import collections

import pytest
import torch
import warp as wp

from physinteract_usd.sim import Rollout
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import solver as solver_mod
from test_fused_zero import _loss_and_grads, _scene


def _rollout(m, ctrl, fused_kernels, graphs, mp):
    mp.setattr(solver_mod, "FUSED_KERNELS", fused_kernels)
    mp.setattr(solver_mod, "FUSED_ZERO", True)
    ro = Rollout(m, ctrl, graphs=graphs)
    assert ro.solver.fused_kernels is fused_kernels
    return ro


@pytest.mark.parametrize("store", [True, False], ids=["stored-states", "replay"])
def test_fused_kernels_give_bitwise_the_separate_kernels(store):
    """Every effect, a grasp released mid-rollout, a clamp, a collider; float64; eager and graphs."""
    m, ctrl, pts, eff, trajs = _scene()
    with pytest.MonkeyPatch.context() as mp:
        if not store:
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", 0)
        ref = _loss_and_grads(_rollout(m, ctrl, False, False, mp), pts, eff, trajs)
        for graphs in (False, True):
            got = _loss_and_grads(_rollout(m, ctrl, True, graphs, mp), pts, eff, trajs)
            for call_r, call_g in zip(ref, got):
                assert float(call_r[0].abs()) > 0
                for a, b in zip(call_r, call_g):
                    assert torch.equal(a, b), (graphs, float((a - b).abs().max()))
                # every gradient is there (the comparison cannot pass on all-zero gradients)
                assert all(float(t.abs().max()) > 0 for t in call_g[1:3])


def test_fused_kernels_launch_fewer_kernels_per_substep():
    m, ctrl, pts, eff, trajs = _scene()
    counts = {}
    with pytest.MonkeyPatch.context() as mp:
        for fused in (False, True):
            ro = _rollout(m, ctrl, fused, False, mp)
            c = collections.Counter()
            launch = wp.launch
            where = []
            step, step_adj = solver_mod.MPMSolver.step, solver_mod.MPMSolver.step_adjoint

            def w_step(*a, _f=step, **k):
                where.append("f")
                try:
                    return _f(*a, **k)
                finally:
                    where.pop()

            def w_adj(*a, _f=step_adj, **k):
                where.append("b")
                try:
                    return _f(*a, **k)
                finally:
                    where.pop()

            def w_launch(*a, **k):
                if where:
                    c[where[-1]] += 1
                return launch(*a, **k)

            with pytest.MonkeyPatch.context() as mp2:
                mp2.setattr(solver_mod.wp, "launch", w_launch)
                mp2.setattr(solver_mod.MPMSolver, "step", w_step)
                mp2.setattr(solver_mod.MPMSolver, "step_adjoint", w_adj)
                mp2.setattr(rollout_mod, "STORE_STATES_BYTES", 1 << 40)
                mp2.setattr(rollout_mod, "TAPE_GRID", False)     # the backward's recompute counted too
                _loss_and_grads(ro, pts, eff, trajs, scales=(1.0,))
            n = ro.T * ro.S
            counts[fused] = (c["f"] / n, c["b"] / n)
    assert counts[False] == (6.0, 12.0), counts
    assert counts[True] == (4.0, 11.0), counts
