"""Gradients of the differentiable MPM rollout against central finite differences (float64).

Every scene runs >= 60 substeps with contacts and a fixed support active; the loss weighs every
frame's positions and deformation gradients with random weights. For each input (per-particle E,
nu, every parameter of every enabled effect, every trajectory) a random direction is drawn and the
analytic directional derivative is compared with a central difference: relative error < 1e-4.

Kinks (friction stick/slip, yield, push-only contact) are not smoothed: the scenes sit away from
the switch points, and the checks use steps (1e-5 of the direction for material and effect
parameters, 1e-6 for trajectories, which move contacts) small enough that no switch is crossed;
collider and ground boundaries use the smoothed (C1) contact band the fit also uses. The first two
scenes' partial pin / collider blends act as rates (`blend_dt` != dt, as the fit's simulations
with the field's substep use them), the third's once per substep.

The rollout does not record on a wp.Tape (it launches each kernel's adjoint itself, every kernel
reading inputs and writing separate outputs), so wp.config.verify_autograd_array_access, which
checks Tape recordings and forces a full rebuild of the module, is not used: these FD checks are
what would catch an input overwritten in place.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
from sim_helpers import block, directional_check, rel_err

TOL = 1e-4
DX = 0.05
SP = DX / 2


def _weights(T, P, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(T + 1, P, 3, generator=g, dtype=torch.float64),
            torch.randn(T + 1, P, 3, 3, generator=g, dtype=torch.float64))


def _run_checks(ro, E0, nu0, effects, trajs, seed=0):
    """FD-check d/dE, d/dnu, each effect parameter and each trajectory of rollout ``ro``."""
    P = ro.P
    T = ro.T
    W, WF = _weights(T, P)
    names = [(e, p) for e, ps in effects.items() for p in ps]
    tkeys = sorted(trajs)

    def loss(E, nu, *rest):
        eff = {}
        for (e, p), v in zip(names, rest[:len(names)]):
            eff.setdefault(e, {})[p] = v
        tr = dict(zip(tkeys, rest[len(names):]))
        x, F = ro(E, nu, effects=eff, trajectories=tr)
        return (x * W).sum() + 0.1 * (F * WF).sum()

    args = [torch.as_tensor(E0, dtype=torch.float64), torch.as_tensor(nu0, dtype=torch.float64)]
    scales = [float(np.mean(E0)) * 0.1, 0.02]
    for e, p in names:
        v = effects[e][p]
        args.append(torch.tensor(float(v), dtype=torch.float64))
        scales.append(abs(float(v)) if v != 0 else 1.0)
    for k in tkeys:
        args.append(torch.as_tensor(trajs[k], dtype=torch.float64))
        scales.append(0.01)
    # FD step: 1e-5 of the direction for the material and effect parameters (smooth: a smaller
    # step only adds round-off), 1e-6 for trajectories (they move contacts: a smaller step is less
    # likely to straddle a contact kink)
    eps = [1e-5] * (2 + len(names)) + [1e-6] * len(tkeys)
    res = directional_check(loss, args, scales, eps=eps, seed=seed)
    labels = ["E", "nu"] + [f"{e}.{p}" for e, p in names] + [f"trajectory[{k}]" for k in tkeys]
    report = {lab: (an, fd, rel_err(an, fd)) for lab, (an, fd) in zip(labels, res)}
    bad = {k: v for k, v in report.items() if not v[2] < TOL}
    assert not bad, f"FD mismatch: {bad}"
    # a derivative that is identically zero would pass trivially: require signal everywhere
    zero = [k for k, v in report.items() if abs(v[1]) < 1e-9]
    assert not zero, f"zero directional derivatives (no signal) for {zero}: {report}"
    return report


@pytest.mark.parametrize("ground_contact", ["nodes", "penalty"])
def test_grad_pull_on_ground_fixed_corotated(ground_contact):
    """Fixed corotated, damping + ground (sliding, kinetic friction), a grasp that pulls and a clamp; the ground at
    the grid nodes and at the particles (kernels.ground_impulse: its adjoint is Warp's, fed by p2g's)."""
    # the particles' ground is push-only at each particle's contact height (a kink): the block starts a fifth of its
    # spacing into it, so that no bottom particle sits on the switch or crosses it
    pts = block((5, 3, 3), SP, (0.2, 0.1 - (0.2 * SP if ground_contact == "penalty" else 0.0), 0.25))
    P = len(pts)
    T = 3
    eff = {"damping": {"coefficient": 3.0}, "ground": {"height": 0.1, "friction": 0.3}}
    m = SimModel.create(pts, SP ** 3, 1000.0, 3e3, 0.3, grid=GridSpec((0, 0, 0), DX, (14, 10, 14)), fps=15,
                        substeps=20, E_max=2e4, dtype="float64", effects=eff, blend_dt=1.0 / (15 * 50),
                        ground_contact=ground_contact)
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1e-9)[0]
    traj = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0.0, 0.03, T + 1)
    traj[:, 1] += np.linspace(0.0, 0.01, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=right, trajectory=traj),
                    Contact("fixed", indices=left[:4])], n_frames=T)
    ro = Rollout(m, ctrl)
    assert m.substeps * T >= 50
    E0 = np.full(P, 3e3) * np.linspace(0.8, 1.2, P)
    _run_checks(ro, E0, np.full(P, 0.3), eff, {0: traj})


def test_grad_pin_rule_per_contact_kind():
    """The supports' own pin rule (SimModel.support_rule, the band; the grasp's the default): a short block held by a
    clamp at one end and pulled at the other, so that a node between them takes both pins' mass and mixes the two
    rules by the clamp's share of it (the supports' mass, gsm, and its hand-written adjoint in p2g_scatter_adj). The
    clamp takes hold after a frame of the grasp's pull: where it holds its particles then depends on E (a clamp held
    from rest would hold them where they were, and gsm's adjoint would not matter)."""
    pts = block((5, 3, 3), SP, (0.2, 0.1, 0.25))
    P = len(pts)
    T = 3
    m = SimModel.create(pts, SP ** 3, 1000.0, 3e3, 0.3, grid=GridSpec((0, 0, 0), DX, (14, 10, 14)), fps=15,
                        substeps=20, E_max=2e4, dtype="float64", support_rule=(2.0, 0.15), blend_dt=1.0 / (15 * 50))
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1e-9)[0]
    traj = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0.0, 0.03, T + 1)
    traj[:, 2] += np.linspace(0.0, -0.01, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=right, trajectory=traj),
                    Contact("fixed", indices=left, grasp_frame=1)], n_frames=T)
    ro = Rollout(m, ctrl)
    E0 = np.full(P, 3e3) * np.linspace(0.8, 1.2, P)
    _run_checks(ro, E0, np.full(P, 0.3), {}, {0: traj})


def test_grad_plasticity_viscoelasticity_sphere_release():
    """Plasticity (yielding) + viscoelasticity, a sphere pushing down, a grasp released mid-rollout, a clamp."""
    pts = block((4, 4, 4), SP, (0.25, 0.15, 0.25))
    P = len(pts)
    T = 4
    eff = {"plasticity": {"yieldStress": 40.0}, "viscoelasticity": {"modulus": 800.0, "relaxationTime": 0.05}}
    m = SimModel.create(pts, SP ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), DX, (12, 12, 12)), fps=20,
                        substeps=16, E_max=1e4, dtype="float64", effects=eff, blend_dt=1.0 / (20 * 7))
    bottom = np.nonzero(pts[:, 1] < pts[:, 1].min() + 1e-9)[0]
    side = np.nonzero((pts[:, 0] > pts[:, 0].max() - 1e-9) & (pts[:, 1] > pts[:, 1].min() + 1e-9))[0]
    top_c = np.array([pts[:, 0].mean() - 0.01, pts[:, 1].max() + 0.045, pts[:, 2].mean() + 0.005])
    sph = np.repeat(top_c[None], T + 1, 0)
    sph[:, 1] -= np.linspace(0.0, 0.04, T + 1)
    grab = np.repeat(pts[side].mean(0)[None], T + 1, 0)
    grab[:, 0] += np.linspace(0.0, 0.02, T + 1)
    ctrl = Control([Contact("fixed", indices=bottom),
                    Contact("pointNonAdherent", trajectory=sph, radius=0.04, friction=0.2),
                    Contact("pointAdherent", indices=side, trajectory=grab, release_frame=2)], n_frames=T)
    ro = Rollout(m, ctrl)
    assert m.substeps * T >= 50
    # plasticity must act in this scene (else its gradient check is vacuous)
    with torch.no_grad():
        x_pl, _ = ro(effects={"plasticity": {"yieldStress": 40.0}})
        x_el, _ = ro(effects={"plasticity": {"yieldStress": float("inf")}})
    assert float((x_pl - x_el).abs().max()) > 1e-4
    E0 = np.full(P, 2e3) * np.linspace(0.9, 1.1, P)
    _run_checks(ro, E0, np.full(P, 0.3), eff, {1: sph, 2: grab})


def test_grad_neo_hookean_capsule_and_plane():
    """Neo-Hookean, a capsule pushing sideways, a moving plane with friction lifting, a clamp, damping."""
    pts = block((4, 3, 4), SP, (0.25, 0.15, 0.25))
    P = len(pts)
    T = 3
    eff = {"damping": {"coefficient": 1.0}}
    m = SimModel.create(pts, SP ** 3, 1000.0, 2e3, 0.35, material="neoHookean",
                        grid=GridSpec((0, 0, 0), DX, (12, 12, 12)), fps=15, substeps=20, E_max=1e4,
                        dtype="float64", effects=eff)
    back = np.nonzero(pts[:, 2] > pts[:, 2].max() - 1e-9)[0]
    cap = np.repeat(np.array([pts[:, 0].min() - 0.03, pts[:, 1].mean(), pts[:, 2].mean() - 0.01])[None], T + 1, 0)
    cap[:, 0] += np.linspace(0.0, 0.03, T + 1)
    plane = np.repeat(np.array([pts[:, 0].mean(), pts[:, 1].min() - 0.012, pts[:, 2].mean()])[None], T + 1, 0)
    plane[:, 1] += np.linspace(0.0, 0.02, T + 1)
    plane[:, 0] += np.linspace(0.0, 0.01, T + 1)
    ctrl = Control([Contact("pointNonAdherent", shape="capsule", radius=0.02, axis=(0.0, 0.03, 0.0),
                            trajectory=cap, friction=0.0),
                    Contact("surfaceNonAdherent", trajectory=plane, normal=(0.0, 1.0, 0.0), friction=0.4),
                    Contact("fixed", indices=back[:3])], n_frames=T)
    ro = Rollout(m, ctrl)
    assert m.substeps * T >= 50
    E0 = np.full(P, 2e3) * np.linspace(0.9, 1.1, P)
    _run_checks(ro, E0, np.linspace(0.3, 0.38, P), eff, {0: cap, 1: plane})


def test_matfunc_adjoints():
    """The custom adjoints of the SVD-based matrix functions at F = I, repeated and distinct singular values."""
    from physinteract_usd.sim.kernels import get_kernels
    K = get_kernels("float64")
    rng = np.random.default_rng(3)
    Fs = np.stack([np.eye(3), np.diag([1.2, 1.0, 1.0]), np.eye(3) * 1.05,
                   np.eye(3) + 0.2 * rng.standard_normal((3, 3)), np.diag([0.8, 0.8, 1.3])])
    n = len(Fs)
    cs = rng.uniform(0.3, 0.9, n)
    W = rng.standard_normal((n, 3, 3))

    def ev(F, c):
        o = wp.zeros((n, 6), dtype=wp.float64)
        wp.launch(K.eval_matfuncs, n, [wp.array(F, dtype=wp.mat33d), wp.array(c, dtype=wp.float64),
                                       wp.array(W, dtype=wp.mat33d)], [o])
        return o.numpy().copy()

    for col in (0, 2, 3, 4, 5):  # polar R, dev_scale, Maxwell stress, FC and NH Kirchhoff stress
        Fa = wp.array(Fs, dtype=wp.mat33d, requires_grad=True)
        ca = wp.array(cs, dtype=wp.float64, requires_grad=True)
        o = wp.zeros((n, 6), dtype=wp.float64, requires_grad=True)
        tape = wp.Tape()
        with tape:
            wp.launch(K.eval_matfuncs, n, [Fa, ca, wp.array(W, dtype=wp.mat33d)], [o])
        seed = np.zeros((n, 6))
        seed[:, col] = 1.0
        tape.backward(grads={o: wp.array(seed, dtype=wp.float64)})
        gF, gc = Fa.grad.numpy(), ca.grad.numpy()
        assert np.all(np.isfinite(gF)) and np.all(np.isfinite(gc))
        D = rng.standard_normal((n, 3, 3))
        dc = rng.standard_normal(n)
        eps = 1e-6
        fd = (ev(Fs + eps * D, cs + eps * dc)[:, col] - ev(Fs - eps * D, cs - eps * dc)[:, col]) / (2 * eps)
        an = (gF * D).sum((1, 2)) + gc * dc
        np.testing.assert_allclose(an, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())


def test_grad_initial_deformation_gradient():
    """`Rollout(..., F0=...)` (#23: a prestressed scan starts with the stress that holds it up): the gradient with
    respect to frame 0's deformation gradient, and E's and the trajectory's beside it, against central differences;
    a call without F0 after one with it starts from the identity again, bit for bit as a fresh rollout."""
    pts = block((4, 3, 3), SP, (0.2, 0.2, 0.25))
    P, T = len(pts), 3
    m = SimModel.create(pts, SP ** 3, 1000.0, 3e3, 0.3, grid=GridSpec((0, 0, 0), DX, (12, 12, 12)), fps=15,
                        substeps=20, E_max=2e4, dtype="float64")
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1e-9)[0]
    traj = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    traj[:, 1] += np.linspace(0.0, 0.02, T + 1)
    ro = Rollout(m, Control([Contact("pointAdherent", indices=right, trajectory=traj),
                             Contact("fixed", indices=left)], n_frames=T))
    W, WF = _weights(T, P)
    g = torch.Generator().manual_seed(7)
    F0 = torch.eye(3, dtype=torch.float64).expand(P, 3, 3) + 0.02 * torch.randn(P, 3, 3, generator=g,
                                                                               dtype=torch.float64)
    E0 = torch.full((P,), 3e3, dtype=torch.float64)

    def loss(E, F0_, tr):
        x, F = ro(E, torch.full((P,), 0.3, dtype=torch.float64), trajectories={0: tr}, F0=F0_)
        return (x * W).sum() + 0.1 * (F * WF).sum()

    res = directional_check(loss, [E0, F0, torch.as_tensor(traj)], [300.0, 0.01, 0.01], eps=[1e-5, 1e-5, 1e-6])
    for lab, (an, fd) in zip(("E", "F0", "trajectory"), res):
        assert rel_err(an, fd) < TOL and abs(fd) > 1e-9, (lab, an, fd)
    x1, F1 = ro(E0, torch.full((P,), 0.3, dtype=torch.float64), trajectories={0: torch.as_tensor(traj)})
    fresh = Rollout(m, Control([Contact("pointAdherent", indices=right, trajectory=traj),
                                Contact("fixed", indices=left)], n_frames=T))
    x2, F2 = fresh(E0, torch.full((P,), 0.3, dtype=torch.float64), trajectories={0: torch.as_tensor(traj)})
    assert torch.equal(x1, x2) and torch.equal(F1, F2) and torch.equal(F1[0], torch.eye(3, dtype=torch.float64
                                                                                         ).expand(P, 3, 3))
