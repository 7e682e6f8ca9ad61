"""The grid box (sim/solver.py `GRID_BOX`, rollout.py `BOX_MARGIN`): the grid kernels (clear, grid update
and their adjoints) run over a box of nodes bounded to the object instead of the whole grid. The loss
and every gradient must be bitwise those of the whole grid (float64, graphs on and off, stored states
and replay), also when the object leaves its box: the pass is then redone on the whole grid."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd.sim import Rollout
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import solver as solver_mod
from test_fused_zero import _loss_and_grads, _scene


def _rollout(m, ctrl, box, graphs, mp, fused_zero=True):
    mp.setattr(solver_mod, "GRID_BOX", box)
    mp.setattr(solver_mod, "FUSED_ZERO", fused_zero)
    ro = Rollout(m, ctrl, graphs=graphs)
    assert ro.solver.grid_box is box
    return ro


def _same(ref, got, tag):
    for call_r, call_g in zip(ref, got):
        assert float(call_r[0].abs()) > 0
        for a, b in zip(call_r, call_g):
            assert torch.equal(a, b), (tag, float((a - b).abs().max()))
        assert all(float(t.abs().max()) > 0 for t in call_g[1:3])


@pytest.mark.parametrize("store", [True, False], ids=["stored-states", "replay"])
def test_box_gives_bitwise_the_whole_grid(store):
    """Every effect, a grasp released mid-rollout, a clamp, a collider; float64; graphs on and off;
    fused zeroing and memsets (the box clears by its kernel in both)."""
    m, ctrl, pts, eff, trajs = _scene()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "BOX_MARGIN", 1)
        if not store:
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", 0)
        ref = _loss_and_grads(_rollout(m, ctrl, False, False, mp), pts, eff, trajs)
        for graphs, fz in ((False, True), (True, True), (True, False)):
            ro = _rollout(m, ctrl, True, graphs, mp, fused_zero=fz)
            _same(ref, _loss_and_grads(ro, pts, eff, trajs), (graphs, fz))
            assert ro.box_redos == 0
            # the box is a real part of the grid: the object's reach plus one cell
            assert 0 < ro.solver.box_volume < 0.5 * ro.solver.n_nodes, (ro.solver.box_lo, ro.solver.box_hi)


def _moving(ro, v0s, shrink_before_backward=False):
    """Forward + backward with initial velocities v0s (m/s along x): the object drifts across cells."""
    P = ro.P
    g = torch.Generator().manual_seed(1)
    W = torch.randn(ro.T + 1, P, 3, generator=g, dtype=torch.float64)
    out = []
    for vx in v0s:
        E = torch.tensor(np.linspace(1.5e3, 2.5e3, P), requires_grad=True)
        nu = torch.full((P,), 0.3, dtype=torch.float64, requires_grad=True)
        v0 = torch.tensor([vx, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
        x, F = ro(E, nu, v0=v0)
        loss = (x * W).sum() + F.sum()
        if shrink_before_backward:       # a box the backward's particles leave (as after another forward)
            lo = ro.solver.box_lo
            ro.solver.set_box(lo, np.add(lo, 3))
        loss.backward()
        out.append([loss.detach().clone(), E.grad.clone(), nu.grad.clone(), v0.grad.clone(), x.detach().clone()])
    return out


@pytest.mark.parametrize("graphs", [False, True], ids=["eager", "graphs"])
def test_object_leaving_its_box_is_redone_on_the_whole_grid(graphs):
    """No contacts, a fast initial velocity: the first box (the rest shape, no margin) is left in the
    first forward, a faster second call leaves the box of the first's reach; each such pass is redone
    on the whole grid, and the results are bitwise those of the whole grid."""
    from physinteract_usd.sim import Control, GridSpec, SimModel
    from sim_helpers import block
    dx = 0.05
    pts = block((2, 2, 2), dx / 2, (0.15, 0.2, 0.25))
    m = SimModel.create(pts, (dx / 2) ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), dx, (14, 10, 10)), fps=10,
                        substeps=6, E_max=1e4, dtype="float64", gravity=(0.0, 0.0, 0.0))
    ctrl = Control([], n_frames=3)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "BOX_MARGIN", 0)
        ref = _moving(_rollout(m, ctrl, False, False, mp), (0.3, 0.6))
        assert float(ref[1][4][-1, :, 0].min() - ref[1][4][0, :, 0].max()) > 2 * dx   # it really moves away
        ro = _rollout(m, ctrl, True, graphs, mp)
        got = _moving(ro, (0.3, 0.6))
        for r, g_ in zip(ref, got):
            for a, b in zip(r, g_):
                assert torch.equal(a, b), float((a - b).abs().max())
        assert ro.box_redos == 2, ro.box_redos          # one forward redone per call
        assert ro.solver.box_volume < ro.solver.n_nodes
        # the backward checks too: a box its particles leave is caught and the pass redone
        for store in (True, False):
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", 1 << 30 if store else 0)
            ro = _rollout(m, ctrl, True, graphs, mp)
            got = _moving(ro, (0.3,), shrink_before_backward=True)
            for a, b in zip(ref[0], got[0]):
                assert torch.equal(a, b), (store, float((a - b).abs().max()))
            assert ro.box_redos == 2, (store, ro.box_redos)   # the first forward's, then the backward's


@pytest.mark.parametrize("graphs", [False, True], ids=["eager", "graphs"])
def test_frames_past_the_store_budget_replay_bitwise(graphs):
    """States of the frames that fit the budget are stored, the others replayed from their checkpoints
    (rollout.py `frames_to_store`): the loss and every gradient bitwise those of all stored and of all
    replayed (with the box on: the backward's stored and replayed frames run over it alike)."""
    m, ctrl, pts, eff, trajs = _scene(T=3)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "BOX_MARGIN", 1)
        fb = _rollout(m, ctrl, True, graphs, mp)._frame_bytes()
        res = {}
        for budget, n_stored in ((1 << 40, 3), (2 * fb, 1), (3 * fb - 1, 1), (fb, 0), (0, 0)):
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", budget)
            ro = _rollout(m, ctrl, True, graphs, mp)
            assert ro.frames_to_store() == n_stored, (budget, fb)
            res[budget] = _loss_and_grads(ro, pts, eff, trajs)
            assert (ro._states is None) == (n_stored == 0)
            assert n_stored == 0 or len(ro._states) == n_stored
            assert (ro._replay is not None) == (n_stored < 3)
        ref = res[1 << 40]
        for budget, got in res.items():
            _same(ref, got, budget)


def test_solver_simulate_redoes_a_run_that_left_the_box():
    """MPMSolver.simulate (no rollout) with a box its particles leave: redone on the whole grid, the
    same positions as without a box."""
    from physinteract_usd.sim import GridSpec, SimModel, SimState
    from sim_helpers import block
    dx = 0.05
    pts = block((2, 2, 2), dx / 2, (0.15, 0.2, 0.25))
    m = SimModel.create(pts, (dx / 2) ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), dx, (14, 10, 10)), fps=10,
                        substeps=4, E_max=1e4, dtype="float64", gravity=(0.0, 0.0, 0.0))
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        for box in (False, True):
            mp.setattr(solver_mod, "GRID_BOX", box)
            sol = solver_mod.MPMSolver(m)
            if box:
                sol.set_box((1, 2, 3), (6, 7, 8))        # around the rest shape only
                assert sol.box_volume == 5 * 5 * 5
            out[box] = sol.simulate(3, state=SimState.rest(m, v0=(0.6, 0.0, 0.0)))
            if box:
                assert sol.full_box()                   # it was left, and the run redone on the whole grid
    assert np.array_equal(out[False]["x"], out[True]["x"])
    assert out[True]["x"][-1][:, 0].min() > pts[:, 0].max() + dx       # it did move out of the box


@pytest.mark.parametrize("margin", [1000, 1], ids=["box-is-whole-grid", "box"])
def test_gpu_grid_stride_loop_on_the_cpu(margin):
    """The GPU's launch over the grid box (a grid-stride loop over the box's nodes, `kernels.box_span`
    contig = 0), run on the CPU, with a box that is the whole grid and with one bounded to the object:
    the same positions bit for bit as the CPU's whole-grid kernels and the same gradients to round-off
    (Warp's generated adjoints add the effect parameters' node terms in another order), also with a
    thread count smaller than the box (as a graph captured with a smaller box runs)."""
    m, ctrl, pts, eff, trajs = _scene()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "BOX_MARGIN", 1)
        ref = _loss_and_grads(_rollout(m, ctrl, False, False, mp), pts, eff, trajs)
        mp.setattr(rollout_mod, "BOX_MARGIN", margin)
        for nthr in (None, 7):
            ro = _rollout(m, ctrl, True, False, mp)
            assert ro.solver.full_box() == (margin > 100)
            ro.solver.contig = 0
            if nthr is not None:
                mp.setattr(solver_mod.MPMSolver, "n_grid_threads", property(lambda self: nthr))
            got = _loss_and_grads(ro, pts, eff, trajs)
            for call_r, call_g in zip(ref, got):
                assert torch.equal(call_r[0], call_g[0])
                for a, b in zip(call_r[1:], call_g[1:]):
                    assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), \
                        float((a - b).abs().max())


def test_box_off_runs_the_whole_grid_kernels_without_the_escape_count():
    """With the box off (the CPU's default) the grid update is the whole grid's kernel (no box decoded or
    tested per node) and p2g counts no escapes, even with a box array that the particles leave."""
    from physinteract_usd.sim import GridSpec, SimModel, SimState
    from sim_helpers import block
    dx = 0.05
    pts = block((2, 2, 2), dx / 2, (0.15, 0.2, 0.25))
    m = SimModel.create(pts, (dx / 2) ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), dx, (14, 10, 10)), fps=10,
                        substeps=4, E_max=1e4, dtype="float64", gravity=(0.0, 0.0, 0.0))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(solver_mod, "GRID_BOX", False)
        sol = solver_mod.MPMSolver(m)
        assert sol.grid_kernel is sol.K.grid_update and sol.n_grid_threads == -(-sol.n_nodes // sol.chunk)
        sol.set_box((1, 2, 3), (6, 7, 8))
        a, b = SimState.rest(m, v0=(0.6, 0.0, 0.0)), SimState.zeros(m.n_particles, m.dtype, m.device)
        for s in range(8):
            sol.step(a, b, 0, s % 4)
            a, b = b, a
        assert int(sol.box_flag.numpy()[0]) == 0
        assert a.x.numpy()[:, 0].min() > pts[:, 0].max() + dx       # it left the box array's nodes
        mp.setattr(solver_mod, "GRID_BOX", True)
        sol = solver_mod.MPMSolver(m)
        assert sol.grid_kernel is sol.K.grid_update_box
        sol.set_box((1, 2, 3), (6, 7, 8))
        sol.step(SimState.rest(m, v0=(0.6, 0.0, 0.0)), b, 0, 0)
        assert int(sol.box_flag.numpy()[0]) == 0
        a = SimState.rest(m, v0=(0.6, 0.0, 0.0))
        a.x.assign(a.x.numpy() + np.array([0.2, 0.0, 0.0]))
        sol.step(a, b, 0, 0)
        assert int(sol.box_flag.numpy()[0]) > 0                     # the box on: the escape is counted
