"""The scan's preload (`sim.preload`, #23): the stress that holds a scanned (already sagged) object at rest on its
supports, so the model does not sag again from the scan at whatever E the fit tries."""
import numpy as np
import pytest
import torch

from sim_helpers import block, directional_check
from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
from physinteract_usd.sim.preload import equilibrium_stress, preload_F

DX, SP, RHO, NU = 0.02, 0.01, 1000.0, 0.3


def _model(x, E, grid, effects=None, material="fixedCorotated"):
    return SimModel.create(x, SP ** 3, RHO, E, NU, grid=grid, fps=20, E_max=2e6, dtype="float64",
                           effects=effects, material=material)


def _run(model, control, F0=None):
    with torch.no_grad():
        x, F = Rollout(model, control, graphs=False)(F0=F0)
    return x.numpy(), F


@pytest.fixture(scope="module")
def cantilever():
    """A 2e5 Pa cantilever (0.14 m) clamped at one end, damped to rest under gravity: its settled shape is the scan
    (a 2 cm sag)."""
    pts = block((14, 3, 3), SP, (0.1, 0.3, 0.1))
    grid = GridSpec((0, 0, 0), DX, (20, 24, 12))
    clamp = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1.5 * SP)[0]
    x, _ = _run(_model(pts, 2e5, grid, {"damping": {"coefficient": 25.0}}),
                Control([Contact("fixed", indices=clamp)], n_frames=40))
    return x[-1], clamp, grid


def test_a_prestressed_scan_stays_at_rest_at_any_E(cantilever):
    # the scan simulated stress-free sags again (cm); prestressed with the balancing stress it holds still, undamped,
    # for 0.5 s at the truth's E and at other E alike (the stress does not depend on E, its stretch does)
    scan, clamp, grid = cantilever
    ctl = Control([Contact("fixed", indices=clamp)], n_frames=10)
    pre = equilibrium_stress(_model(scan, 2e5, grid), ctl)
    assert pre.residual < 1e-4 and pre.held_nodes > 0
    for E in (1e5, 2e5, 8e5):
        x, _ = _run(_model(scan, E, grid), ctl, F0=preload_F(pre, torch.tensor(E, dtype=torch.float64), NU))
        assert np.abs(x - scan).max() < 1e-4, E
        free, _ = _run(_model(scan, E, grid), ctl)
        assert np.abs(free - scan).max() > 5e-3, E


def test_preload_finds_the_truths_E_where_stress_free_does_not(cantilever):
    # the truth: the settled cantilever (its own settled F) lifted at the tip and let go; the model from the scan
    # alone: stress-free its loss is least at a wrong E (the object's extra sag mimics a softer or stiffer one),
    # prestressed at the truth's E (benchmarks/preload_probe.py sweeps it)
    scan, clamp, grid = cantilever
    pts = block((14, 3, 3), SP, (0.1, 0.3, 0.1))
    _, Fs = _run(_model(pts, 2e5, grid, {"damping": {"coefficient": 25.0}}),
                 Control([Contact("fixed", indices=clamp)], n_frames=40))
    tip = np.nonzero(scan[:, 0] > scan[:, 0].max() - 1.5 * SP)[0]
    traj = np.repeat(scan[tip].mean(0)[None], 9, 0)
    traj[:, 1] += 0.03 * np.clip(np.arange(9) / 3.0, 0, 1)
    ctl = Control([Contact("pointAdherent", indices=tip, trajectory=traj, release_frame=4),
                   Contact("fixed", indices=clamp)], n_frames=8)
    truth, _ = _run(_model(scan, 2e5, grid), ctl, F0=Fs[-1])
    pre = equilibrium_stress(_model(scan, 2e5, grid), ctl)
    loss = {}
    for f in (0.7, 1.0, 1.4):
        E = 2e5 * f
        pl, _ = _run(_model(scan, E, grid), ctl, F0=preload_F(pre, torch.tensor(E, dtype=torch.float64), NU))
        sf, _ = _run(_model(scan, E, grid), ctl)
        loss[f] = (np.mean((pl - truth) ** 2), np.mean((sf - truth) ** 2))
    assert min(loss, key=lambda f: loss[f][0]) == 1.0
    assert loss[1.0][0] < 1e-3 * loss[1.0][1]
    assert min(loss, key=lambda f: loss[f][1]) != 1.0


def test_a_block_settled_on_the_ground_gets_the_simulators_own_stress():
    # known answer: a block damped to rest on the ground (it sinks into the contact band until the ground's nodes hold
    # it) carries, at rest, the simulator's own equilibrium stress; the balancing stress solved from its settled
    # shape alone is that stress (within 30%: the settle is nonlinear, the solve linear; both ring alike in the
    # layers over the band, the grid's, not the continuum's rho g depth), and prestressed the block stays put
    pts = block((8, 6, 8), SP, (0.06, 0.041, 0.06))
    grid = GridSpec((0, 0, 0), DX, (14, 10, 14))
    ground = {"ground": {"height": 0.04, "friction": 0.5}}
    x, F = _run(_model(pts, 1e5, grid, {**ground, "damping": {"coefficient": 25.0}}), Control([], n_frames=30))
    scan, F = x[-1], F[-1].numpy()
    mu, lam = 1e5 / (2 * (1 + NU)), 1e5 * NU / ((1 + NU) * (1 - 2 * NU))
    U, _, Vt = np.linalg.svd(F)
    J = np.linalg.det(F)
    tau = 2 * mu * np.einsum("pij,pkj->pik", F - U @ Vt, F) + (lam * (J - 1) * J)[:, None, None] * np.eye(3)
    m = _model(scan, 1e5, grid, ground)
    ctl = Control([], n_frames=6)
    pre = equilibrium_stress(m, ctl)
    assert pre.residual < 1e-3
    assert np.linalg.norm(pre.tau - tau) < 0.3 * np.linalg.norm(tau)
    held, _ = _run(m, ctl, F0=preload_F(pre, torch.tensor(1e5, dtype=torch.float64), NU))
    free, _ = _run(m, ctl)
    assert np.abs(held - scan).max() < 1e-6 < 1e-4 < np.abs(free - scan).max()


def test_the_preload_gradient_matches_finite_differences(cantilever):
    # F0(E, nu) is an implicit function of the constitutive law: its gradient, alone and through a rollout, against
    # central differences in float64
    scan, clamp, grid = cantilever
    ctl = Control([Contact("fixed", indices=clamp)], n_frames=3)
    pre = equilibrium_stress(_model(scan, 2e5, grid), ctl)
    P = len(scan)
    w = torch.randn(P, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    for material in ("fixedCorotated", "neoHookean"):
        def f0(E, nu):
            return (preload_F(pre, E, nu, material) * w).sum()
        for an, fd in directional_check(f0, [torch.full((P,), 2e5, dtype=torch.float64),
                                             torch.full((P,), NU, dtype=torch.float64)], [2e4, 0.02], eps=1e-4):
            assert an == pytest.approx(fd, rel=1e-5, abs=1e-12), material
    ro = Rollout(_model(scan, 2e5, grid), ctl, graphs=False)
    target = torch.as_tensor(scan) + 0.001

    def loss(E, nu):
        x, _ = ro(E, nu, F0=preload_F(pre, E, nu))
        return ((x - target) ** 2).sum()
    for an, fd in directional_check(loss, [torch.full((P,), 2e5, dtype=torch.float64),
                                           torch.full((P,), NU, dtype=torch.float64)], [2e4, 0.02], eps=1e-3):
        assert an == pytest.approx(fd, rel=1e-4, abs=1e-12)


def test_nothing_holding_the_object_is_an_error():
    pts = block((3, 3, 3), SP, (0.1, 0.1, 0.1))
    m = _model(pts, 1e5, GridSpec((0, 0, 0), DX, (14, 14, 14)))
    with pytest.raises(ValueError, match="nothing holds the object"):
        equilibrium_stress(m, Control([], n_frames=2))
