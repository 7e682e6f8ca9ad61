"""The block-local scatters (sim/solver.py `P2G_MODE = "tiled"`: kernels.p2g_tiled, g2p_gather_adj_tiled;
issue #26): a block of consecutive particles accumulates its stencils in a shared tile of nodes, then adds
each touched node into the grid once. The same values summed in another order, so not bitwise: the loss
and every gradient must agree with the atomic path to ~1e-12 relative in float64, and the gradient with
central finite differences.

What the CPU covers: the kernels' code as CUDA runs it, with Warp's CPU tiles (shared tile = a block-local
buffer, `acc[q] += v` an add): one thread per block looping over the block's particles (the CPU default),
and with `wp.config.enable_cpu_blocks` several cooperative threads per block (barriers after every shared
add, the bounding box from tile reductions), as on CUDA. Boxes clipped to a few slots (nodes outside the
tile take their global atomic directly) and a part-filled last block are exercised. Not covered: CUDA's
shared-memory atomics and their speed (benchmarks/bench_sim.py --p2g both, on a GPU)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from physinteract_usd.sim import Rollout
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import solver as solver_mod
from sim_helpers import directional_check, rel_err
from test_fused_zero import _loss_and_grads, _scene

RTOL = 1e-12


def _rollout(m, ctrl, mode, mp, fused_kernels=True, graphs=False, block=8, cap=None):
    mp.setattr(solver_mod, "P2G_MODE", mode)
    mp.setattr(solver_mod, "P2G_BLOCK", block)
    mp.setattr(solver_mod, "P2G_CAP", cap)
    mp.setattr(solver_mod, "FUSED_KERNELS", fused_kernels)
    mp.setattr(solver_mod, "FUSED_ZERO", True)
    ro = Rollout(m, ctrl, graphs=graphs)
    assert ro.solver.p2g_mode == (mode or "atomic")
    return ro


def _close(ref, got, tag):
    worst = 0.0
    for call_r, call_g in zip(ref, got):
        for a, b in zip(call_r, call_g):
            scale = float(a.abs().max())
            assert scale > 0, tag                               # every gradient has signal
            err = float((a - b).abs().max()) / scale
            worst = max(worst, err)
            assert err < RTOL, (tag, err)
    return worst


@pytest.mark.parametrize("store", [True, False], ids=["stored-states", "replay"])
def test_tiled_scatter_agrees_with_atomics(store):
    """Every effect, a grasp released mid-rollout, a clamp, a collider; float64; 27 particles in blocks of
    8 (the last holds 3); fused and separate kernels, graphs on and off, the full tile and boxes clipped to
    4 and 9 slots (most stencil nodes then take the direct global atomic)."""
    m, ctrl, pts, eff, trajs = _scene()
    with pytest.MonkeyPatch.context() as mp:
        if not store:
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", 0)
        ref = _loss_and_grads(_rollout(m, ctrl, None, mp), pts, eff, trajs)
        for fk, graphs, cap in ((True, False, None), (True, True, None), (False, False, None), (True, False, 4),
                                (True, True, 9)):
            got = _loss_and_grads(_rollout(m, ctrl, "tiled", mp, fk, graphs, cap=cap), pts, eff, trajs)
            _close(ref, got, (fk, graphs, cap))
        # not bitwise: the sums really are taken in another order (else the test says little about order)
        assert any(not torch.equal(a, b) for a, b in zip(ref[0], got[0]))


def test_tiled_scatter_with_cooperative_cpu_blocks():
    """Four cooperative threads per block on the CPU (wp.config.enable_cpu_blocks): the bounding box from
    tile reductions over the threads, a barrier after every shared add, two particles per thread."""
    m, ctrl, pts, eff, trajs = _scene(T=1)
    old = wp.config.enable_cpu_blocks
    with pytest.MonkeyPatch.context() as mp:
        ref = _loss_and_grads(_rollout(m, ctrl, None, mp), pts, eff, trajs, scales=(1.0,))
        try:
            wp.config.enable_cpu_blocks = True
            ro = _rollout(m, ctrl, "tiled", mp, block=8)
            # 8 particles per block on 4 threads: launch_tiled takes block_dim = P2G_BLOCK, so narrow it
            launch_tiled = wp.launch_tiled

            def four(*a, **kw):
                kw["block_dim"] = 4
                return launch_tiled(*a, **kw)

            mp.setattr(solver_mod.wp, "launch_tiled", four)
            got = _loss_and_grads(ro, pts, eff, trajs, scales=(1.0,))
        finally:
            wp.config.enable_cpu_blocks = old
    _close(ref, got, "cpu blocks")


def test_tiled_scatter_gradient_matches_finite_differences():
    """Directional derivatives (E, nu, the grasp's trajectory) of the tiled path against central
    differences: a block pulled by a grasp against a clamp, damped (no contact or yield kinks), boxes
    clipped to 9 slots."""
    from physinteract_usd.sim import Contact, Control, GridSpec, SimModel
    from sim_helpers import block
    dx = 0.05
    pts = block((4, 3, 3), dx / 2, (0.2, 0.12, 0.25))
    P, T = len(pts), 2
    m = SimModel.create(pts, (dx / 2) ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), dx, (10, 10, 10)), fps=20,
                        substeps=6, E_max=1e4, dtype="float64", effects={"damping": {"coefficient": 1.0}})
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1e-9)[0]
    grab = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    grab += np.linspace(0.0, 1.0, T + 1)[:, None] * np.array([0.01, 0.004, -0.003])   # every pinned component
    ctrl = Control([Contact("pointAdherent", indices=right, trajectory=grab),
                    Contact("fixed", indices=left[:3])], n_frames=T)
    g = torch.Generator().manual_seed(3)
    W = torch.randn(T + 1, P, 3, generator=g, dtype=torch.float64)
    with pytest.MonkeyPatch.context() as mp:
        ro = _rollout(m, ctrl, "tiled", mp, cap=9)

        def loss(E, nu, tr):
            x, F = ro(E, nu, trajectories={0: tr})
            return (x * W).sum() + 0.1 * F.sum()

        args = [torch.tensor(np.linspace(1.5e3, 2.5e3, P)), torch.full((P,), 0.3, dtype=torch.float64),
                torch.tensor(grab)]
        res = directional_check(loss, args, [200.0, 0.02, 0.01], eps=[1e-5, 1e-5, 1e-6])
    for an, fd in res:
        assert abs(fd) > 1e-9 and rel_err(an, fd) < 1e-5, res


def test_bad_mode_is_refused(monkeypatch):
    m, ctrl, *_ = _scene(T=1)
    monkeypatch.setattr(solver_mod, "P2G_MODE", "shared")
    with pytest.raises(ValueError, match="P2G_MODE"):
        Rollout(m, ctrl)
