"""Physics checks of the MPM simulator with known answers (float64, CPU, small scenes)."""

from __future__ import annotations

import numpy as np
import pytest

from physinteract_usd.errors import SimulationError
from physinteract_usd.sim import Contact, Control, GridSpec, MPMSolver, SimModel, SimState
from sim_helpers import block

RHO = 1000.0
G = 9.81


def test_free_fall():
    """Centroid drop equals g t^2 / 2 up to the symplectic-Euler term g t dt / 2 (exactly)."""
    dx = 0.05
    pts = block((4, 4, 4), dx / 2, (0.3, 0.55, 0.3))
    m = SimModel.create(pts, (dx / 2) ** 3, RHO, 1e4, 0.3, grid=GridSpec((0, 0, 0), dx, (16, 16, 16)), fps=30,
                        E_max=1e4, dtype="float64")
    T = 3
    out = MPMSolver(m).simulate(T)
    t = T / m.fps
    drop = out["x"][0][:, 1].mean() - out["x"][-1][:, 1].mean()
    assert drop == pytest.approx(G * t * t / 2 + G * t * m.dt / 2, rel=1e-9)
    assert abs(drop - G * t * t / 2) <= G * t * m.dt / 2 * (1 + 1e-6)
    # rigid: no deformation, no spread in velocity
    np.testing.assert_allclose(out["F"][-1], np.broadcast_to(np.eye(3), out["F"][-1].shape), atol=1e-9)
    np.testing.assert_allclose(out["v"][-1][:, 1], -G * t, rtol=1e-9)


def test_hanging_bar_extension_and_lateral_contraction():
    """A bar clamped at the top, hanging under its weight (damped to rest): tip extension
    rho g L^2 / (2 E) and mid-length lateral strain -nu rho g (L/2) / E within 10%."""
    dx = 0.02
    sp = dx / 2
    ny = 40
    pts = block((8, ny, 8), sp, (0.1, 0.1, 0.1))
    nu = 0.3
    ytop = pts[:, 1].max()
    clamp = np.nonzero(pts[:, 1] > ytop - 1.5 * sp)[0]          # top two particle layers
    y_clamp = ytop - 1.5 * sp                                     # clamp line: bottom face of the clamped layers
    L = ny * sp - 2 * sp                                          # free length
    E = RHO * G * L / 0.02                                        # 2% strain at the clamp, 1% at mid-length
    m = SimModel.create(pts, sp ** 3, RHO, E, nu, grid=GridSpec.around(pts, dx, padding=0.02), fps=10, E_max=E,
                        effects={"damping": {"coefficient": 80.0}}, dtype="float64")
    out = MPMSolver(m, Control([Contact("fixed", indices=clamp)], n_frames=2)).simulate(2)
    x = out["x"][-1]
    assert np.array_equal(x[clamp], pts[clamp])
    bot = pts[:, 1] < pts[:, 1].min() + 1e-9
    yb = y_clamp - pts[bot, 1].mean()
    u_exp = RHO * G / E * (L * yb - yb ** 2 / 2)
    u = -(x[bot, 1] - pts[bot, 1]).mean()
    assert u == pytest.approx(u_exp, rel=0.10)
    ym = y_clamp - L / 2
    sl = np.abs(pts[:, 1] - ym) < sp * 1.01
    w0 = np.abs(pts[sl][:, [0, 2]] - pts[sl][:, [0, 2]].mean(0)).mean()
    w1 = np.abs(x[sl][:, [0, 2]] - x[sl][:, [0, 2]].mean(0)).mean()
    lateral = w1 / w0 - 1
    assert lateral == pytest.approx(-nu * RHO * G * (L / 2) / E, rel=0.10)
    # and it is at rest
    assert np.abs(out["v"][-1]).max() < 1e-3 * np.sqrt(E / RHO) * 0.02


def _stretched_block(n, sp, F0, **model_kw):
    pts = block(n, sp, (0.1, 0.1, 0.1))
    xc = pts.mean(0)
    m = SimModel.create(pts, sp ** 3, RHO, grid=GridSpec.around(pts, 2 * sp, padding=0.04), gravity=(0, 0, 0),
                        dtype="float64", **model_kw)
    st = SimState.rest(m)
    st.x.assign(xc + (pts - xc) @ F0.T)
    st.F.assign(np.tile(F0, (len(pts), 1, 1)))
    return m, st, pts


def _energy(m, st, mu, lam):
    x, v, F, C = st.x.numpy(), st.v.numpy(), st.F.numpy(), st.C.numpy()
    s = np.linalg.svd(F, compute_uv=False)
    J = np.linalg.det(F)
    psi = mu * ((s - 1) ** 2).sum(1) + lam / 2 * (J - 1) ** 2
    dx = m.grid.dx
    return (0.5 * (m.mass[:, None] * v ** 2).sum() + (m.volume * psi).sum()
            + 0.5 * (m.mass * dx * dx / 4 * (C ** 2).sum((1, 2))).sum())   # APIC affine kinetic energy


def test_oscillation_energy_bounded_and_damping_rate():
    """A pre-stretched free block oscillates: undamped, its energy never grows; damped (c), the
    ratio damped / undamped follows exp(-c t) (the numerical dissipation cancels) within 8%."""
    E, nu, c = 1e4, 0.3, 5.0
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    F0 = np.diag([1.03, 0.99, 1.0])
    T, fps = 20, 50.0
    energies = {}
    for cc in (0.0, c):
        m, st, _ = _stretched_block((6, 6, 6), 0.0125, F0, E=E, nu=nu, fps=fps, E_max=E,
                                    effects={"damping": {"coefficient": cc}})
        sol = MPMSolver(m)
        en = [_energy(m, st, mu, lam)]
        for _ in range(T):
            sol.simulate(1, st)
            en.append(_energy(m, st, mu, lam))
        energies[cc] = np.array(en)
    e0 = energies[0.0]
    assert e0.max() <= e0[0] * (1 + 1e-6)          # bounded: never above the initial energy
    assert e0[-1] > 0.05 * e0[0]                   # and still oscillating
    t = np.arange(T + 1) / fps
    ratio = energies[c] / e0
    np.testing.assert_allclose(ratio, np.exp(-c * t), rtol=0.08)
    assert ratio[-1] < 0.2                         # really decayed


@pytest.mark.parametrize("strain, yield_strain", [(0.06, 0.02), (0.04, 0.08)])
def test_plasticity_permanent_set(strain, yield_strain):
    """A block released from a uniaxial-stress stretch, damped to rest: above yield it keeps a
    permanent set of (2/3)(1 + nu)(strain - yield strain) in log strain (the Hencky return
    mapping's answer); below yield it returns to its rest length."""
    E, nu = 1e4, 0.3
    F0 = np.diag([1 + strain, 1 - nu * strain, 1 - nu * strain])
    m, st, pts = _stretched_block((12, 6, 6), 0.0125, F0, E=E, nu=nu, fps=20, E_max=E,
                                  effects={"damping": {"coefficient": 60.0},
                                           "plasticity": {"yieldStress": E * yield_strain}})
    out = MPMSolver(m).simulate(8, st)
    L0 = np.ptp(pts[:, 0])
    set_ = np.log(np.ptp(out["x"][-1][:, 0]) / L0)
    assert np.abs(out["v"][-1]).max() < 1e-4
    expected = max(0.0, 2 / 3 * (1 + nu) * (strain - yield_strain))
    if expected > 0:
        assert set_ == pytest.approx(expected, rel=0.05)
    else:
        assert abs(set_) < 1e-3


@pytest.mark.parametrize("ground_contact", ["nodes", "penalty"])
def test_sliding_block_stops_where_coulomb_says(ground_contact):
    """A block launched along the ground at v0 stops after v0^2 / (2 mu g) (within 5%), the ground at the grid nodes
    or at the particles."""
    dx = 0.025
    sp = dx / 2
    h, v0, mu = 0.1, 1.0, 0.3
    pts = block((8, 6, 8), sp, (0.1, h, 0.1))
    d_exp = v0 ** 2 / (2 * mu * G)
    grid = GridSpec.around(pts, dx, lower=(0.1, h - 0.03, 0.1), upper=(0.2 + 1.5 * d_exp, h + 0.1, 0.2))
    T = int(np.ceil(v0 / (mu * G) * 1.3 * 20)) + 2
    m = SimModel.create(pts, sp ** 3, RHO, 1e5, 0.3, grid=grid, fps=20, E_max=1e5, max_speed=v0,
                        effects={"ground": {"height": h, "friction": mu}}, dtype="float64", ground_contact=ground_contact)
    out = MPMSolver(m).simulate(T + 4, SimState.rest(m, v0=(v0, 0, 0)))
    xc = out["x"][:, :, 0].mean(1)
    # stopped: its mean velocity over the last 0.2 s (the particles' ground is elastic: the stopped block, undamped,
    # rocks on it at +-2% v0 about rest)
    assert abs(out["v"][T:][:, :, 0].mean()) < 0.01 * v0
    assert xc[T] - xc[0] == pytest.approx(d_exp, rel=0.05)
    # frictionless: keeps sliding at v0
    m0 = m.replace(effects={"ground": {"height": h, "friction": 0.0}})
    out0 = MPMSolver(m0).simulate(3, SimState.rest(m0, v0=(v0, 0, 0)))
    assert out0["v"][-1][:, 0].mean() == pytest.approx(v0, rel=0.01)


def test_null_values_vanish_exactly():
    """Each effect at its null value gives bitwise the rollout without it."""
    dx = 0.05
    pts = block((4, 4, 4), dx / 2, (0.3, 0.12, 0.3))
    T = 2
    traj = np.repeat(pts[:8].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0, 0.02, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=np.arange(8), trajectory=traj)], n_frames=T)
    base = dict(grid=GridSpec((0, 0, 0), dx, (12, 12, 12)), fps=20, substeps=10, E_max=1e4, dtype="float64")

    def run(effects):
        m = SimModel.create(pts, (dx / 2) ** 3, RHO, 3e3, 0.3, effects=effects, **base)
        return MPMSolver(m, ctrl).simulate(T)

    ref = run({})
    for eff in ({"damping": {"coefficient": 0.0}}, {"plasticity": {"yieldStress": float("inf")}},
                {"viscoelasticity": {"modulus": 0.0, "relaxationTime": 0.05}}):
        out = run(eff)
        for k in ("x", "v", "F"):
            assert np.array_equal(out[k], ref[k]), (eff, k)
    # and away from null each one changes the motion
    for eff in ({"damping": {"coefficient": 5.0}}, {"plasticity": {"yieldStress": 5.0}},
                {"viscoelasticity": {"modulus": 3e3, "relaxationTime": 0.05}},
                {"ground": {"height": 0.13, "friction": 0.5}}):
        assert np.abs(run(eff)["x"] - ref["x"]).max() > 1e-4, eff


def test_viscoelastic_relaxation():
    """Maxwell branch: a block held stretched relaxes its branch stress as exp(-t/tau) (the
    branch's deviatoric Hencky strain decays at that rate while the total deformation is held)."""
    dx = 0.05
    pts = block((4, 4, 4), dx / 2, (0.3, 0.3, 0.3))
    tau = 0.05
    m = SimModel.create(pts, (dx / 2) ** 3, RHO, 3e3, 0.3, grid=GridSpec((0, 0, 0), dx, (16, 16, 16)), fps=20,
                        substeps=10, E_max=1e4, gravity=(0, 0, 0), dtype="float64",
                        effects={"viscoelasticity": {"modulus": 2e3, "relaxationTime": tau}})
    st = SimState.rest(m)
    F0 = np.diag([1.05, 0.98, 0.98])
    xc = pts.mean(0)
    st.x.assign(xc + (pts - xc) @ F0.T)
    st.F.assign(np.tile(F0, (len(pts), 1, 1)))
    st.Fv.assign(np.tile(F0, (len(pts), 1, 1)))
    # hold every particle: the total deformation stays F0, the branch relaxes
    ctrl = Control([Contact("fixed", indices=np.arange(len(pts)))], n_frames=3)
    out_dev = []
    sol = MPMSolver(m, ctrl)
    for k in range(3):
        out_dev.append(_dev_hencky_norm(st.Fv.numpy()))
        for s in range(m.substeps):
            nxt = SimState.zeros(len(pts), m.dtype, m.device)
            sol.step(st, nxt, k, s)
            st = nxt
    out_dev.append(_dev_hencky_norm(st.Fv.numpy()))
    t = np.arange(4) / m.fps
    np.testing.assert_allclose(np.array(out_dev) / out_dev[0], np.exp(-t / tau), rtol=1e-6)


def _dev_hencky_norm(F):
    s = np.linalg.svd(F, compute_uv=False)
    e = np.log(s)
    d = e - e.mean(1, keepdims=True)
    return float(np.linalg.norm(d, axis=1).mean())


def test_fixed_adherent_and_release():
    """Fixed particles never move; grasped particles follow the trajectory exactly while grasped,
    then fall freely after release."""
    dx = 0.05
    pts = block((6, 3, 3), dx / 2, (0.2, 0.3, 0.3))
    T = 4
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1e-9)[0]
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    c0 = pts[right].mean(0)
    traj = np.repeat(c0[None], T + 1, 0)
    traj[:, 0] += np.array([0.0, 0.01, 0.025, 0.03, 0.03])
    traj[:, 1] += np.array([0.0, 0.02, 0.03, 0.03, 0.03])
    ctrl = Control([Contact("fixed", indices=left),
                    Contact("pointAdherent", indices=right, trajectory=traj, release_frame=2)], n_frames=T)
    m = SimModel.create(pts, (dx / 2) ** 3, RHO, 3e3, 0.3, grid=GridSpec((0, 0, 0), dx, (16, 16, 16)), fps=20,
                        substeps=12, E_max=1e4, dtype="float64")
    out = MPMSolver(m, ctrl).simulate(T)
    for k in range(T + 1):
        assert np.array_equal(out["x"][k][left], pts[left])
    for k in range(3):  # grasped over frames 0 and 1: positions at frames 0..2 follow the trajectory
        np.testing.assert_allclose(out["x"][k][right].mean(0), traj[k], atol=1e-12)
    # released at frame 2: no longer on the (now static) trajectory: it sags under gravity
    assert out["x"][4][right].mean(0)[1] < traj[4][1] - 1e-3


def test_collider_pushes_but_does_not_pull():
    """A sphere moving into a block pushes it; a sphere moving away from a block it touches leaves it."""
    dx = 0.05
    pts = block((4, 4, 4), dx / 2, (0.3, 0.3, 0.3))
    T = 3
    x_min = pts[:, 0].min() - dx / 4
    r = 0.05
    m = SimModel.create(pts, (dx / 2) ** 3, RHO, 3e3, 0.3, grid=GridSpec((0, 0, 0), dx, (20, 16, 16)), fps=20,
                        substeps=12, E_max=1e4, gravity=(0, 0, 0), dtype="float64", contact_band=0.0)
    c = pts.mean(0)
    for direction in (+1, -1):
        traj = np.repeat(np.array([x_min - r, c[1], c[2]])[None], T + 1, 0)
        traj[:, 0] += direction * np.linspace(0, 0.06, T + 1)
        ctrl = Control([Contact("pointNonAdherent", trajectory=traj, radius=r)], n_frames=T)
        out = MPMSolver(m, ctrl).simulate(T)
        shift = out["x"][-1][:, 0].mean() - pts[:, 0].mean()
        if direction > 0:
            assert shift > 0.02          # pushed along
        else:
            assert abs(shift) < 1e-9     # not pulled


def test_moving_plane_lifts_and_drags_with_friction():
    """A plane rising under a block lifts it against gravity; moving sideways it drags the block
    along with friction, and slides under it without."""
    dx = 0.05
    pts = block((4, 2, 4), dx / 2, (0.3, 0.2, 0.3))
    T = 4
    base_y = pts[:, 1].min() - dx / 4
    res = {}
    for mu in (0.0, 1.0):
        traj = np.repeat(np.array([0.35, base_y, 0.35])[None], T + 1, 0)
        traj[:, 1] += np.linspace(0, 0.05, T + 1)
        traj[:, 0] += np.linspace(0, 0.08, T + 1)
        ctrl = Control([Contact("surfaceNonAdherent", trajectory=traj, normal=(0, 1, 0), friction=mu)],
                       n_frames=T)
        m = SimModel.create(pts, (dx / 2) ** 3, RHO, 5e3, 0.3, grid=GridSpec((0, 0, 0), dx, (20, 16, 16)), fps=20,
                            substeps=12, E_max=1e4, dtype="float64")
        res[mu] = MPMSolver(m, ctrl).simulate(T)["x"][-1]
    for mu in res:
        assert res[mu][:, 1].min() > base_y + 0.05 - 0.02       # lifted with the plane (no sinking through)
    dx0 = res[0.0][:, 0].mean() - pts[:, 0].mean()
    dx1 = res[1.0][:, 0].mean() - pts[:, 0].mean()
    assert abs(dx0) < 1e-6 and dx1 > 0.04


def test_leaving_the_domain_raises_with_frame_and_advice():
    dx = 0.05
    pts = block((4, 4, 4), dx / 2, (0.2, 0.2, 0.2))
    m = SimModel.create(pts, (dx / 2) ** 3, RHO, 3e3, 0.3, grid=GridSpec((0, 0, 0), dx, (10, 10, 10)), fps=10,
                        E_max=1e4, dtype="float64")
    with pytest.raises(SimulationError) as ei:
        MPMSolver(m).simulate(6)
    e = ei.value
    assert "left the grid domain" in e.problem and e.frame in (2, 3) and "enlarge the grid" in e.advice
    assert "frame" in str(e)


def test_too_large_substep_raises_non_finite():
    """Below the CFL bound the rollout is stable; at a quarter of the CFL substeps it blows up and
    says so (a SimulationError naming the frame and the fix), not NaNs."""
    dx = 0.025
    sp = dx / 2
    pts = block((6, 6, 6), sp, (0.1, 0.2, 0.1))
    E = 1e6
    grid = GridSpec.around(pts, dx, lower=(0.1, 0.1, 0.1), upper=(0.25, 0.4, 0.25))
    m = SimModel.create(pts, sp ** 3, RHO, E, 0.45, grid=grid, fps=30, E_max=E, nu_max=0.45, dtype="float64",
                        effects={"ground": {"height": 0.12, "friction": 0.5}})
    out = MPMSolver(m).simulate(4, SimState.rest(m, v0=(0, -2.0, 0)))
    assert np.isfinite(out["x"]).all()
    bad = m.replace(substeps=m.substeps // 4)
    with pytest.raises(SimulationError) as ei:
        MPMSolver(bad).simulate(4, SimState.rest(bad, v0=(0, -2.0, 0)))
    assert ei.value.frame is not None and "substeps" in ei.value.advice
    # where the named particle stood at its frame's start (#24: the GPU's "unstable" said nothing of it)
    assert "at the frame's start: speed" in ei.value.problem and "nearest other particle" in ei.value.problem


def test_float32_matches_float64():
    """The production dtype (float32) tracks float64 on a contact-rich rollout."""
    dx = 0.05
    pts = block((4, 4, 4), dx / 2, (0.3, 0.12, 0.3))
    T = 3
    traj = np.repeat(pts[-8:].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0, 0.03, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=np.arange(len(pts) - 8, len(pts)), trajectory=traj),
                    Contact("fixed", indices=np.arange(4))], n_frames=T)
    xs = {}
    for dt in ("float32", "float64"):
        m = SimModel.create(pts, (dx / 2) ** 3, RHO, 3e3, 0.3, grid=GridSpec((0, 0, 0), dx, (12, 12, 12)), fps=20,
                            substeps=20, E_max=1e4, dtype=dt,
                            effects={"ground": {"height": 0.1, "friction": 0.3}, "damping": {"coefficient": 1.0}})
        xs[dt] = MPMSolver(m, ctrl).simulate(T)["x"]
    disp = np.abs(xs["float64"] - pts).max()
    assert np.abs(xs["float32"] - xs["float64"]).max() < 1e-3 * disp


@pytest.mark.slow
def test_cantilever_tip_deflection_high_resolution():
    """Slow (~3 min on 2 CPU cores): a cantilever (L/h = 10, 6 cells through the thickness, 18k
    particles) clamped at one end sags under gravity (damped to rest) by the Timoshenko beam's tip
    deflection, 3 rho g L^4 / (2 E h^2) (1 + 2 (1 + nu) h^2 / (3 kappa L^2)), within 5%.
    (At 4 cells through the thickness the MPM beam is ~10% too soft: it converges with dx.)"""
    L, h = 0.5, 0.05
    dx = h / 6
    sp = dx / 2
    nl, nh, nclamp = int(round(L / sp)), int(round(h / sp)), 4
    pts = block((nl + nclamp, nh, nh), sp, (0.1 - nclamp * sp, 0.3, 0.1))
    nu = 0.3
    E = 3 * RHO * G * L ** 4 / (2 * 0.02 * L * h ** 2)       # ~2% of L deflection
    clamp = np.nonzero(pts[:, 0] < 0.1)[0]
    grid = GridSpec.around(pts, dx, lower=(pts[:, 0].min() - 0.01, 0.25, 0.09), upper=(0.11 + L, 0.31 + h, 0.11 + h))
    T = 3
    m = SimModel.create(pts, sp ** 3, RHO, E, nu, grid=grid, fps=10, E_max=E, dtype="float32",
                        effects={"damping": {"coefficient": 60.0}})
    out = MPMSolver(m, Control([Contact("fixed", indices=clamp)], n_frames=T)).simulate(T)
    tip = pts[:, 0] > pts[:, 0].max() - 1e-9
    Lb = pts[tip, 0].mean() - 0.1
    kappa = 5 / 6
    expected = 3 * RHO * G * Lb ** 4 / (2 * E * h ** 2) * (1 + 2 * (1 + nu) * h ** 2 / (3 * kappa * Lb ** 2))
    d = -(out["x"][-1][tip, 1] - pts[tip, 1]).mean()
    assert d == pytest.approx(expected, rel=0.05)


def test_a_settled_shape_restarted_with_its_deformation_gradient_stays_put():
    """The prestressed start (`Rollout(..., F0=...)`, #23): a soft cantilever clamped at one end, damped to rest under
    gravity, sags by 10.8 cm at its tip. Its settled shape taken as the rest positions, with the settled deformation
    gradient as frame 0's F (the stress that holds it up), it stays where it is (undamped, over half a second); taken
    stress-free, as `init` takes a scan today, it sags again by about as much."""
    import torch

    from physinteract_usd.sim import Rollout

    dx = 0.02
    sp = dx / 2
    pts = block((14, 3, 3), sp, (0.1, 0.3, 0.1))                    # 14 cm along x, clamped at x's low end
    grid = GridSpec((0, 0, 0), dx, (20, 24, 12))
    clamp = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1.5 * sp)[0]
    E = 2e4

    def run(x0, frames, damping, F0=None):
        eff = {"damping": {"coefficient": damping}} if damping else {}
        m = SimModel.create(x0, sp ** 3, RHO, E, 0.3, grid=grid, fps=20, E_max=E, dtype="float64", effects=eff)
        ro = Rollout(m, Control([Contact("fixed", indices=clamp)], n_frames=frames), graphs=False)
        with torch.no_grad():
            x, F = ro(F0=F0)
        return x.numpy(), F.numpy()

    x, F = run(pts, 40, 25.0)                                        # 2 s, damped: settled
    sag = float(np.abs(x[-1][:, 1] - pts[:, 1]).max())
    assert sag > 0.01 and float(np.abs(x[-1] - x[-5]).max()) < 0.02 * sag
    held, _ = run(x[-1], 10, 0.0, F0=torch.as_tensor(F[-1]))
    free, _ = run(x[-1], 10, 0.0)
    moved = lambda y: float(np.abs(y[1:] - y[0]).max())              # noqa: E731
    assert moved(held) < 0.01 * sag, (moved(held), sag)             # 0.2 mm of a 10.8 cm sag
    assert moved(free) > 0.5 * sag, (moved(free), sag)              # 8.1 cm
