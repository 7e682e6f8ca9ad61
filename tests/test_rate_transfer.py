"""The rate transfer (SimModel.transfer_tau, docs/sim.md; #24): free particles keep f = exp(-dt / tau) of the
velocity the grid could not carry, v_p <- v_apic + f (v_p - v_grid_old(x_p)), so the transfer's dissipation is a
rate per second instead of a share per substep.

- Off (tau 0, the default) it is APIC: nothing extra is launched (the other sim tests are today's results).
- Gradients with it on against central finite differences in float64 (E, nu, effects, trajectories, the initial
  velocity), as tests/test_sim_gradients.py.
- The substep tapes, the fused kernels, fused zeroing, the grid box and captured graphs give bitwise the plain
  (eager) path's results.
- Known answer (benchmarks/dt_convergence.py's cantilever): with APIC the ringing's decay per period doubles
  when the substeps double; with the rate transfer it nearly stops depending on them, and the first frequency
  stays the Euler-Bernoulli beam's."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import solver as solver_mod
from sim_helpers import block, directional_check, rel_err
from test_sim_gradients import TOL, _run_checks

DX = 0.05
SP = DX / 2
TAU = 0.02


def _pull_scene(tau, dtype="float64", T=3, substeps=20):
    pts = block((5, 3, 3), SP, (0.2, 0.1, 0.25))
    eff = {"damping": {"coefficient": 3.0}, "ground": {"height": 0.1, "friction": 0.3}}
    m = SimModel.create(pts, SP ** 3, 1000.0, 3e3, 0.3, grid=GridSpec((0, 0, 0), DX, (14, 10, 14)), fps=15,
                        substeps=substeps, E_max=2e4, dtype=dtype, effects=eff, blend_dt=1.0 / (15 * 50),
                        transfer_tau=tau)
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1e-9)[0]
    traj = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0.0, 0.03, T + 1)
    traj[:, 1] += np.linspace(0.0, 0.01, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=right, trajectory=traj, release_frame=2),
                    Contact("fixed", indices=left[:4])], n_frames=T)
    return m, ctrl, pts, eff, traj


def test_off_is_apic_and_on_changes_the_motion():
    m0, ctrl, pts, eff, traj = _pull_scene(0.0)
    mn, *_ = _pull_scene(None)
    m1, *_ = _pull_scene(TAU)
    assert m0.transfer_tau == 0.0 and mn.transfer_tau == 0.0 and m1.transfer_tau == TAU
    with torch.no_grad():
        x0, F0 = Rollout(m0, ctrl)()
        xn, Fn = Rollout(mn, ctrl)()
        x1, F1 = Rollout(m1, ctrl)()
    assert torch.equal(x0, xn) and torch.equal(F0, Fn)
    assert float((x1 - x0).abs().max()) > 1e-5        # the blend acts
    with pytest.raises(ValueError, match="transfer_tau"):
        _pull_scene(-0.01)


def test_rate_transfer_gradients_match_finite_differences():
    """E, nu, damping / ground parameters, the grasp's trajectory (released mid-rollout), and v0."""
    m, ctrl, pts, eff, traj = _pull_scene(TAU)
    ro = Rollout(m, ctrl)
    assert ro.solver.rate_f > 0.5
    P = len(pts)
    E0 = np.full(P, 3e3) * np.linspace(0.8, 1.2, P)
    _run_checks(ro, E0, np.full(P, 0.3), eff, {0: traj})
    # the initial state (velocity): the rate term reads v_p directly
    g = torch.Generator().manual_seed(3)
    W = torch.randn(ro.T + 1, P, 3, generator=g, dtype=torch.float64)
    v_init = 0.05 * torch.randn(P, 3, generator=g, dtype=torch.float64)

    def loss(v0):
        x, F = ro(torch.as_tensor(E0), v0=v0)
        return (x * W).sum() + 0.1 * F.sum()

    (an, fd), = directional_check(loss, [v_init], [0.05], eps=[1e-6], seed=1)
    assert rel_err(an, fd) < TOL and abs(fd) > 1e-9, (an, fd)


def _grads(m, ctrl, pts, traj, mp, graphs=True, **flags):
    for k, v in flags.items():
        mp.setattr(solver_mod if k in ("FUSED_KERNELS", "FUSED_ZERO", "GRID_BOX") else rollout_mod, k, v)
    ro = Rollout(m, ctrl, graphs=graphs)
    E = torch.linspace(2e3, 4e3, len(pts), dtype=torch.float64).requires_grad_(True)
    tr = torch.tensor(traj, dtype=torch.float64, requires_grad=True)
    x, F = ro(E, trajectories={0: tr})
    (x[-1, :, 0].sum() + 0.3 * x[2, :, 1].sum() + F[-1, :, 0, 1].sum()).backward()
    return x.detach(), E.grad.clone(), tr.grad.clone()


def test_tapes_fused_kernels_and_grid_box_are_bitwise_the_plain_path():
    m, ctrl, pts, eff, traj = _pull_scene(TAU, substeps=8)
    with pytest.MonkeyPatch.context() as mp:
        ref = _grads(m, ctrl, pts, traj, mp, graphs=False, TAPE_GRID=False, FUSED_KERNELS=False, FUSED_ZERO=False,
                     GRID_BOX=False)
    # captured graphs: their first backward executes while it captures, over the stored substep states, then
    # replays over them; the adjoint must leave each state as its forward wrote it (rate term included)
    with pytest.MonkeyPatch.context() as mp:
        graphs = _grads(m, ctrl, pts, traj, mp, TAPE_GRID=False, FUSED_KERNELS=False, FUSED_ZERO=False, GRID_BOX=False)
    for a, b in zip(ref, graphs):
        assert torch.equal(a, b)
    # one graph per frame shape (CUDA's default, sim/frame_graphs.py) with the GPU's kernel paths, on the CPU
    with pytest.MonkeyPatch.context() as mp:
        fg = _grads(m, ctrl, pts, traj, mp, TAPE_GRID=False, FRAME_GRAPHS=True, FUSED_KERNELS=True, FUSED_ZERO=True,
                    GRID_BOX=True)
    for a, b in zip(ref, fg):
        assert torch.equal(a, b)
    with pytest.MonkeyPatch.context() as mp:
        tape = _grads(m, ctrl, pts, traj, mp, TAPE_GRID=True, FUSED_KERNELS=False, FUSED_ZERO=False, GRID_BOX=False)
    with pytest.MonkeyPatch.context() as mp:
        fused = _grads(m, ctrl, pts, traj, mp, TAPE_GRID=False, FUSED_KERNELS=True, FUSED_ZERO=True, GRID_BOX=True)
    for a, b in zip(ref, tape):
        assert torch.equal(a, b)
    for a, b in zip(ref, fused):
        assert torch.equal(a, b)
    assert float(ref[1].abs().sum()) > 0 and float(ref[2].abs().sum()) > 0


BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        import dt_convergence
        yield dt_convergence
    finally:
        sys.path.remove(str(BENCH))


def _decay(bench, substeps, transfer, frames=12, samples=4):
    y, _ = bench.simulate(substeps, transfer, frames, per_frame=samples)
    return bench.analyse(y, bench.FPS * samples)


def test_the_kernels_are_the_host_side_prototype(bench):
    y_k, _ = bench.simulate(150, "kernel:0.01", 2, per_frame=4)
    y_h, _ = bench.simulate(150, "rate:0.01", 2, per_frame=4)
    y_a, _ = bench.simulate(150, "apic", 2, per_frame=4)
    assert np.allclose(y_k, y_h, rtol=0, atol=1e-10)
    assert np.abs(y_k - y_a).max() > 1e-5


def test_cantilever_decay_no_longer_grows_with_the_substeps(bench):
    """APIC: the log decrement a period doubles from 150 to 300 substeps a frame (tests/test_dt_convergence.py);
    with the rate transfer (tau 0.01 s) it stays < 0.4x APIC's at 150 and grows by < 0.2x of that a doubling; the first frequency and
    the mean sag stay the beam's (Euler-Bernoulli) within 5-6%."""
    sag, f1 = bench.beam()
    apic = _decay(bench, 150, "apic")
    a = _decay(bench, 150, "kernel:0.01")
    b = _decay(bench, 300, "kernel:0.01")
    for r in (a, b):
        assert r["lows"] >= 3
        assert 1.0 / r["period_s"] / f1 == pytest.approx(1.0, abs=0.05)
        assert r["mean_sag_m"] / sag == pytest.approx(1.0, abs=0.06)
    assert a["period_s"] == pytest.approx(apic["period_s"], rel=0.01)
    assert a["log_decrement"] < 0.4 * apic["log_decrement"]
    # what still grows is small: +0.009 a doubling against APIC's +0.083 (the affine part C, still projected
    # every substep); relative to its own small size it is x1.5-1.65 (20 / 12 frames) against APIC's x2.07
    assert b["log_decrement"] - a["log_decrement"] < 0.2 * apic["log_decrement"]
    assert b["log_decrement"] < 1.8 * a["log_decrement"]


def test_tiled_copies_keep_it():
    """sim/batch.py's tiled model (fit --starts, batched probes) carries transfer_tau: B copies = B rollouts."""
    from physinteract_usd.sim.batch import tile

    m, ctrl, pts, eff, traj = _pull_scene(TAU, substeps=8)
    tl = tile(m, ctrl, 2)
    assert tl.model.transfer_tau == TAU
    P = m.n_particles
    Es = [torch.full((P,), v, dtype=torch.float64) for v in (2e3, 4e3)]
    with torch.no_grad():
        ref = [Rollout(m, ctrl)(E)[0] for E in Es]
        xb = tl.split(Rollout(tl.model, tl.control)(tl.stack(torch.stack(Es)))[0])
    for b in range(2):
        assert torch.allclose(xb[b], ref[b], atol=1e-9, rtol=0)
