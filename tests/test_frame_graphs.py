"""One captured graph per frame shape (sim/rollout.py `FRAME_GRAPHS`, sim/frame_graphs.py; issue #26): the
frame index is a device-side counter the graph advances, the frame-indexed rows go through windows. The
loss and every gradient must be bitwise those of the per-frame graphs and of eager launches (float64;
stored states, replay, some frames stored; the GPU's fused kernels and grid box run on the CPU; a pass
redone on the whole grid), and a capture must issue far fewer launches from Python."""

from __future__ import annotations

import collections

import numpy as np
import pytest
import torch
import warp as wp

from physinteract_usd.sim import Rollout
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import solver as solver_mod
from test_fused_zero import _loss_and_grads, _scene


def _ro(m, ctrl, mp, graphs, frame_graphs, gpu_paths=False):
    mp.setattr(rollout_mod, "FRAME_GRAPHS", frame_graphs)
    mp.setattr(solver_mod, "FUSED_ZERO", gpu_paths)
    mp.setattr(solver_mod, "FUSED_KERNELS", gpu_paths)
    mp.setattr(solver_mod, "GRID_BOX", gpu_paths)
    ro = Rollout(m, ctrl, graphs=graphs)
    assert ro.frame_graphs is frame_graphs
    return ro


def _no_grad_forwards(ro, pts, n=3):
    """Forwards without gradients (the start search's): the first eager, the later ones the forward graphs."""
    P = len(pts)
    out = []
    for i in range(n):
        E = torch.tensor(np.linspace(1.5e3, 2.5e3, P) * (1.0 - 0.1 * i))
        x, F = ro(E, torch.full((P,), 0.3, dtype=torch.float64))
        out.append([x.clone(), F.clone()])
    return out


def _same(ref, got, tag):
    assert len(ref) == len(got)
    for r, g in zip(ref, got):
        assert float(r[0].abs().max()) > 0
        for a, b in zip(r, g):
            assert torch.equal(a, b), (tag, float((a - b).abs().max()))


@pytest.mark.parametrize("store", ["all", "some", "none"])
@pytest.mark.parametrize("gpu_paths", [False, True], ids=["cpu-paths", "gpu-paths"])
def test_frame_shape_graphs_are_bitwise_the_per_frame_path(store, gpu_paths):
    """Every effect, a grasp released mid-rollout, a clamp, a moving collider, 3 frames: eager launches,
    per-frame graphs and frame-shape graphs give bitwise the same loss and gradients (two calls, graphs
    replayed with new inputs) and the same forwards without gradients."""
    m, ctrl, pts, eff, trajs = _scene(T=3)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "BOX_MARGIN", 1)
        fb = _ro(m, ctrl, mp, False, False)._frame_bytes()
        budget = {"all": 1 << 40, "some": int(2.5 * fb), "none": 0}[store]
        mp.setattr(rollout_mod, "STORE_STATES_BYTES", budget)
        ref = _ro(m, ctrl, mp, False, False, gpu_paths)
        r_grads, r_fwd = _loss_and_grads(ref, pts, eff, trajs), _no_grad_forwards(ref, pts)
        for graphs, fg in ((True, False), (True, True)):
            ro = _ro(m, ctrl, mp, graphs, fg, gpu_paths)
            _same(r_grads, _loss_and_grads(ro, pts, eff, trajs), (graphs, fg, "grads"))
            _same(r_fwd, _no_grad_forwards(ro, pts), (graphs, fg, "forwards"))
            n = {"all": 3, "some": 1, "none": 0}[store]
            assert (0 if ro._states is None else len(ro._states)) == n
            assert ro.graphs
            if fg:       # one graph per shape, not per frame
                assert set(ro._fwd_graphs) == {"forward"}
                assert len(ro._fwd_store_graphs) == (1 if n in (0, 3) else 2) or not ro._fwd_store_graphs
                assert all(len(g) <= 2 for g in (ro._adj_graphs, ro._bwd_graphs, ro._replay_graphs))


def test_frame_shape_graphs_redo_a_pass_that_left_the_box():
    """The grid box on, an object that leaves it: the forward and the backward are redone on the whole
    grid through the same frame-shape graphs (the counter reset per pass), bitwise the eager path."""
    from physinteract_usd.sim import Control, GridSpec, SimModel
    from sim_helpers import block
    from test_grid_box import _moving
    dx = 0.05
    pts = block((2, 2, 2), dx / 2, (0.15, 0.2, 0.25))
    m = SimModel.create(pts, (dx / 2) ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), dx, (14, 10, 10)), fps=10,
                        substeps=6, E_max=1e4, dtype="float64", gravity=(0.0, 0.0, 0.0))
    ctrl = Control([], n_frames=3)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "BOX_MARGIN", 0)
        ref = _moving(_ro(m, ctrl, mp, False, False), (0.3, 0.6))
        ro = _ro(m, ctrl, mp, True, True, gpu_paths=True)
        got = _moving(ro, (0.3, 0.6))
        for r, g in zip(ref, got):
            for a, b in zip(r, g):
                assert torch.equal(a, b), float((a - b).abs().max())
        assert ro.box_redos == 2
        for store in (True, False):
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", 1 << 30 if store else 0)
            ro = _ro(m, ctrl, mp, True, True, gpu_paths=True)
            got = _moving(ro, (0.3,), shrink_before_backward=True)
            for a, b in zip(ref[0], got[0]):
                assert torch.equal(a, b), (store, float((a - b).abs().max()))
            assert ro.box_redos == 2, (store, ro.box_redos)


def _count_launches(fn):
    n = collections.Counter()
    orig = wp.launch

    def counted(*a, **kw):
        n["launch"] += 1
        return orig(*a, **kw)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(wp, "launch", counted)
        fn()
    return n["launch"]


def test_frame_shape_graphs_issue_fewer_launches():
    """A first forward + backward captures its graph sets: per frame, T + 1 frames' launches per set (a
    warm-up frame and T captures); per shape, two frames' (warm-up and one capture) plus a few copies.
    A replayed call issues no launch per frame in either."""
    T = 6
    m, ctrl, pts, eff, trajs = _scene(T=T)
    counts = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "STORE_STATES_BYTES", 1 << 40)
        for fg in (False, True):
            ro = _ro(m, ctrl, mp, True, fg, gpu_paths=True)
            first = _count_launches(lambda: _loss_and_grads(ro, pts, eff, trajs, scales=(1.0,)))
            again = _count_launches(lambda: _loss_and_grads(ro, pts, eff, trajs, scales=(0.9,)))
            counts[fg] = (first, again)
    per_frame, per_shape = counts[False][0], counts[True][0]
    S = m.substeps
    assert per_frame > (T + 1) * 2 * S * 4            # two sets (stored forward, adjoint), >= 4 launches a substep
    assert per_shape < per_frame * 2.5 / (T + 1), counts   # ~2 frames' of T + 1
    assert counts[True][1] <= counts[False][1] + 4, counts     # replays: only the per-call work, a prelude


def test_frame_shape_graphs_float32():
    """The production dtype: the windows' kernels built for float32, bitwise the per-frame path."""
    from physinteract_usd.sim import Contact, Control, GridSpec, SimModel
    from sim_helpers import block
    SP, DX, T = 0.025, 0.05, 3
    pts = block((3, 3, 3), SP, (0.25, 0.12, 0.25))
    m = SimModel.create(pts, SP ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), DX, (10, 10, 10)), fps=20,
                        substeps=6, E_max=1e4, dtype="float32")
    side = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    grab = np.repeat(pts[side].mean(0)[None], T + 1, 0)
    grab[:, 0] += np.linspace(0.0, 0.01, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=side, trajectory=grab, release_frame=2)], n_frames=T)
    P = len(pts)
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        for fg in (False, True):
            ro = _ro(m, ctrl, mp, True, fg, gpu_paths=True)
            res = []
            for s in (1.0, 0.9):
                E = torch.full((P,), 2e3 * s, dtype=torch.float32, requires_grad=True)
                tr = torch.tensor(grab, dtype=torch.float32, requires_grad=True)
                x, F = ro(E, torch.full((P,), 0.3), trajectories={0: tr})
                (x.sum() + F.square().sum()).backward()
                res.append([x.detach().clone(), E.grad.clone(), tr.grad.clone()])
            out[fg] = res
            assert ro.graphs
    _same(out[False], out[True], "float32")
    assert float(out[True][0][2].abs().max()) > 0


def test_forward_only_rollout_holds_no_substep_window():
    """A rollout that is never differentiated (synth's truth, `simulate`) must not hold the window's S + 1
    substep states: at a fine step they are (S + 1) x P states (107 GB for the suite's balloon truth at
    grid 128 on the H200, where synth failed to allocate them). A backward then allocates them and its
    gradients are bitwise the per-frame path's."""
    m, ctrl, pts, eff, trajs = _scene(T=3)
    with pytest.MonkeyPatch.context() as mp:
        ref = _ro(m, ctrl, mp, False, False)
        r_fwd, r_grads = _no_grad_forwards(ref, pts), _loss_and_grads(ref, pts, eff, trajs)
        ro = _ro(m, ctrl, mp, True, True)
        _same(r_fwd, _no_grad_forwards(ro, pts), "forwards")
        assert ro._fw is not None and ro._fw.states is None and ro._fw.st is None
        _same(r_grads, _loss_and_grads(ro, pts, eff, trajs), "grads")
        assert ro._fw.states is not None and len(ro._fw.st) == ro.S + 1
