"""Fused zeroing (sim/solver.py `fused_zero`): one kernel clears a substep's grid arrays (and, in the
backward, its grid and particle adjoints) instead of separate memsets. The results must be
bitwise those of the memset path, and the fused kernels must clear everything the memsets did."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import solver as solver_mod
from sim_helpers import block

DX = 0.05
SP = DX / 2


def _scene(T=2):
    """Every zeroed buffer in use: a grasp (pinned grid arrays) released mid-rollout, a clamp, a
    sphere collider, the ground, plasticity, the Maxwell branch and damping."""
    pts = block((3, 3, 3), SP, (0.25, 0.12, 0.25))
    eff = {"plasticity": {"yieldStress": 60.0}, "viscoelasticity": {"modulus": 500.0, "relaxationTime": 0.05},
           "damping": {"coefficient": 1.0}, "ground": {"height": 0.1, "friction": 0.3}}
    m = SimModel.create(pts, SP ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), DX, (10, 10, 10)), fps=20,
                        substeps=6, E_max=1e4, dtype="float64", effects=eff)
    bottom = np.nonzero(pts[:, 1] < pts[:, 1].min() + 1e-9)[0]
    side = np.nonzero((pts[:, 0] > pts[:, 0].max() - 1e-9) & (pts[:, 1] > pts[:, 1].min() + 1e-9))[0]
    sph = np.repeat(np.array([pts[:, 0].mean(), pts[:, 1].max() + 0.04, pts[:, 2].mean()])[None], T + 1, 0)
    sph[:, 1] -= np.linspace(0.0, 0.02, T + 1)
    grab = np.repeat(pts[side].mean(0)[None], T + 1, 0)
    grab[:, 0] += np.linspace(0.0, 0.01, T + 1)
    ctrl = Control([Contact("fixed", indices=bottom[:2]),
                    Contact("pointNonAdherent", trajectory=sph, radius=0.03, friction=0.2),
                    Contact("pointAdherent", indices=side, trajectory=grab, release_frame=1)], n_frames=T)
    return m, ctrl, pts, eff, {1: sph, 2: grab}


def _loss_and_grads(ro, pts, eff, trajs, scales=(1.0, 0.8)):
    """Two forward+backward calls (changing inputs, so graphs are replayed with new data)."""
    P = len(pts)
    g = torch.Generator().manual_seed(0)
    W = torch.randn(ro.T + 1, P, 3, generator=g, dtype=torch.float64)
    WF = torch.randn(ro.T + 1, P, 3, 3, generator=g, dtype=torch.float64)
    out = []
    for s in scales:
        E = torch.tensor(np.linspace(1.5e3, 2.5e3, P) * s, requires_grad=True)
        nu = torch.full((P,), 0.3, dtype=torch.float64, requires_grad=True)
        ev = {e: {p: torch.tensor(float(v), dtype=torch.float64, requires_grad=True) for p, v in ps.items()}
              for e, ps in eff.items()}
        tr = {k: torch.tensor(v * (1 + 0.01 * s), requires_grad=True) for k, v in trajs.items()}
        v0 = torch.tensor([0.01, 0.0, -0.02], dtype=torch.float64, requires_grad=True)
        x, F = ro(E, nu, effects=ev, trajectories=tr, v0=v0)
        loss = (x * W).sum() + 0.1 * (F * WF).sum()
        loss.backward()
        leaves = [E, nu, v0] + [t for ps in ev.values() for t in ps.values()] + list(tr.values())
        out.append([loss.detach().clone()] + [t.grad.clone() for t in leaves])
    return out


def _rollout(m, ctrl, fused, graphs):
    with pytest.MonkeyPatch.context() as mp:      # FUSED_ZERO is read when the solver is built
        mp.setattr(solver_mod, "FUSED_ZERO", fused)
        ro = Rollout(m, ctrl, graphs=graphs)
        assert ro.solver.fused_zero is fused
        return ro


@pytest.mark.parametrize("store", [True, False], ids=["stored-states", "replay"])
def test_fused_zeroing_gives_bitwise_the_memset_path(store):
    """Losses and every gradient (E, nu, v0, each effect parameter, each trajectory), float64, with
    graphs (Warp's CPU graphs here) and eager launches, stored states and the replay."""
    m, ctrl, pts, eff, trajs = _scene()
    with pytest.MonkeyPatch.context() as mp:
        if not store:
            mp.setattr(rollout_mod, "STORE_STATES_BYTES", 0)
        ref = _loss_and_grads(_rollout(m, ctrl, False, False), pts, eff, trajs)
        for graphs in (False, True):
            ro = _rollout(m, ctrl, True, graphs)
            got = _loss_and_grads(ro, pts, eff, trajs)
            assert (ro._states is not None) == store and ro.graphs == graphs   # no silent fallback to eager
            for a, b in zip(ref, got):
                for u, v in zip(a, b):
                    assert torch.equal(u, v), (graphs, u, v)
    # the calls differ (else equality above says little), and every gradient has signal
    assert not torch.equal(ref[0][1], ref[1][1])
    assert all(float(t.abs().max()) > 0 for t in ref[0][1:])


def test_fused_kernels_clear_every_buffer_the_memsets_cleared():
    """Poison the grid, its adjoints, the particle-side adjoints and both carried state adjoints with
    NaN before the backward: the fused path must clear all of them (a buffer it missed would give
    NaN gradients or differ from the memset path)."""
    m, ctrl, pts, eff, trajs = _scene()
    ref = _loss_and_grads(_rollout(m, ctrl, False, False), pts, eff, trajs, scales=(1.0,))
    ro = _rollout(m, ctrl, True, False)
    _loss_and_grads(ro, pts, eff, trajs, scales=(1.0,))      # allocates the adjoint buffers
    sol = ro.solver
    bufs = [sol.gm, sol.gmv, sol.gpm, sol.gpmv, sol.gsm, *sol._adj_grid.values(), *sol._adj_part.values()]
    bufs += [getattr(a, f) for a in ro._adj for f in ("x", "v", "C", "F", "Fv")]
    assert len(bufs) == 5 + 6 + 3 + 10
    orig_backward = ro.run_backward

    def poisoned_backward(*a, **kw):
        for b in bufs:
            b.fill_(float("nan"))
        ro._adj[0].zero_()                 # run_backward zeroes the first carried adjoint itself
        return orig_backward(*a, **kw)

    ro.run_backward = poisoned_backward
    got = _loss_and_grads(ro, pts, eff, trajs, scales=(1.0,))
    for u, v in zip(ref[0], got[0]):
        assert torch.isfinite(v).all() and torch.equal(u, v)


def test_fused_backward_substep_has_no_memsets_and_three_clearing_launches():
    """What the profile counts: memsets per backward substep (eager, replay path) 24 -> 0, replaced
    by 3 clearing launches (the replayed forward's grid, the backward's grid + grid adjoints, its
    particle adjoints); forward substeps 5 memsets -> 1 launch."""
    m, ctrl, pts, eff, trajs = _scene(T=1)
    counts = {}
    for fused in (False, True):
        ro = _rollout(m, ctrl, fused, False)
        ro.states_fit = lambda: False                               # the replay path
        _loss_and_grads(ro, pts, eff, trajs, scales=(1.0,))       # warm: allocate, compile
        n = {"memset": 0, "clear": 0}
        orig_zero = wp.array.zero_
        orig_launch = wp.launch

        def zero_(self, *a, **kw):
            n["memset"] += 1
            return orig_zero(self, *a, **kw)

        def launch(kernel, *a, **kw):
            if kernel.func.__name__.startswith("zero_"):
                n["clear"] += 1
            return orig_launch(kernel, *a, **kw)

        per = {}
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(wp.array, "zero_", zero_)
            mp.setattr(solver_mod.wp, "launch", launch)
            for phase, fn in (("forward", ro.run_forward), ("backward", ro.run_backward)):
                n.update(memset=0, clear=0)
                fn()
                per[phase] = dict(n)
        counts[fused] = per
    S = m.substeps
    # the memset path: 5 per forward substep (the scatter targets); per backward substep 5 (replay) + 5 + 6 + 3 + 5
    # (the replay skips the last substep's step, so S - 1 replayed substeps); plus per-pass fixed costs
    old, new = counts[False], counts[True]
    assert old["forward"]["memset"] - new["forward"]["memset"] == 5 * S
    assert new["forward"]["clear"] == S and old["forward"]["clear"] == 0
    assert old["backward"]["memset"] - new["backward"]["memset"] == 19 * S + 5 * (S - 1)
    assert new["backward"]["clear"] == 2 * S + (S - 1)


def test_default_is_fused_on_cuda_and_memsets_on_the_cpu(monkeypatch):
    """FUSED_ZERO = None (the default): fused where memset graph nodes are launch-bound (CUDA); the
    CPU keeps memsets (measured faster there, docs/benchmarks/gpu.md)."""
    m, ctrl, _, _, _ = _scene(T=1)
    monkeypatch.setattr(solver_mod, "FUSED_ZERO", None)
    assert Rollout(m, ctrl).solver.fused_zero is False          # the scene is on the CPU
    monkeypatch.setattr(solver_mod, "FUSED_ZERO", True)
    assert Rollout(m, ctrl).solver.fused_zero is True
