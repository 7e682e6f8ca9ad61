"""A ball launched along the floor: the known answer for a rigid solid sphere is that friction slows its slide and
spins it up until it rolls, at t_s = 2 v0 / (7 mu g), at v = 5/7 v0, and it then rolls on at that speed (no rolling
resistance). With the ground at the grid nodes (`ground_contact="nodes"`, the default) our MPM gets the slide right and
the roll wrong: a rolling ball's nodes about its contact move into the plane (ahead of it) and out (behind), so the
ground's projection brakes the roll, more on a coarser grid. This is why, on the world suite's floor captures, our
simulator does not reproduce the truth's motion at any E and the fits' E wanders (23rd session,
docs/benchmarks/world_fits.md: "Floor objects"); that roll is a strict xfail. With the ground at the particles
(`ground_contact="penalty"`, kernels.ground_impulse: a push that depends on a particle's depth alone, friction at its
contact point, both scattered through the grid) the ball rolls on (24th session)."""

from __future__ import annotations

import numpy as np
import pytest

from physinteract_usd.sim import GridSpec, MPMSolver, SimModel, SimState

G, RHO = 9.81, 1000.0
H, V0, MU, R, E, FPS = 0.1, 0.5, 0.3, 0.05, 1e5, 20


def _roll(dx: float, frames: int = 12, contact: str = "nodes") -> np.ndarray:
    """The ball's mean velocity along x over the frames (frame 0 = launch), a 5 cm ball of E 1e5 Pa, particles at dx/2,
    the ground at the grid nodes (today's default) or at the particles (`SimModel.ground_contact`)."""
    sp = dx / 2
    g = np.arange(-R, R + 1e-9, sp) + sp / 2
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    p = p[np.linalg.norm(p, axis=1) < R]
    pts = p + np.array([0.1 + R, H - p[:, 1].min() + 0.5 * sp, 0.1 + R])
    grid = GridSpec.around(pts, dx, lower=(0.05, H - 0.04, 0.05),
                           upper=(0.1 + 2 * R + 1.1 * V0 * frames / FPS, H + 2 * R + 0.05, 0.15 + 2 * R))
    m = SimModel.create(pts, sp ** 3, RHO, E, 0.3, grid=grid, fps=FPS, E_max=E, max_speed=V0,
                        effects={"ground": {"height": H, "friction": MU}}, ground_contact=contact)
    out = MPMSolver(m).simulate(frames, SimState.rest(m, v0=(V0, 0, 0)))
    return out["v"][:, :, 0].mean(1)


@pytest.fixture(scope="module")
def rolls():
    return {dx: _roll(dx) for dx in (0.02, 0.01)}


def test_the_slide_ends_at_five_sevenths_of_the_launch_speed(rolls):
    """t_s = 2 v0 / (7 mu g) = 0.049 s: at the first frame (0.05 s) the ball has just stopped slipping, v = 5/7 v0
    (within 4%, at 5 and 10 cells across): the ground's Coulomb friction and the ball's spin-up are right."""
    assert 2 * V0 / (7 * MU * G) < 1 / FPS
    for dx, v in rolls.items():
        assert v[1] / V0 == pytest.approx(5 / 7, rel=0.04), dx


def test_the_roll_is_braked_less_on_a_finer_grid(rolls):
    """The braking is the grid's: 10 cells across the ball keep it rolling longer than 5 (the world captures' finer
    truths roll further than their fits)."""
    coarse, fine = rolls[0.02], rolls[0.01]
    assert fine[4] > 2 * coarse[4] and fine[6] > 3 * coarse[6]


def test_a_ball_spinning_in_the_air_keeps_its_spin():
    """Without the ground (and gravity) APIC keeps a ball's spin (to 0.2% over 0.6 s): the braking is the ground's."""
    dx, w = 0.01, 10.0
    sp = dx / 2
    g = np.arange(-R, R + 1e-9, sp) + sp / 2
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    p = p[np.linalg.norm(p, axis=1) < R]
    c = np.array([0.2, 0.2, 0.2])
    m = SimModel.create(p + c, sp ** 3, RHO, E, 0.3, grid=GridSpec.around(p + c, dx, lower=(0.05,) * 3, upper=(0.35,) * 3),
                        fps=FPS, E_max=E, max_speed=w * R, gravity=(0, 0, 0))
    st = SimState.rest(m)
    st.v.assign(np.stack([-w * p[:, 1], w * p[:, 0], 0 * p[:, 0]], 1).astype(np.float32))
    C = np.zeros((len(p), 3, 3), np.float32)
    C[:, 0, 1], C[:, 1, 0] = -w, w
    st.C.assign(C)
    out = MPMSolver(m).simulate(12, st)
    r = out["x"][-1] - out["x"][-1].mean(0)
    v = out["v"][-1] - out["v"][-1].mean(0)
    spin = np.sum(r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0]) / np.sum(r[:, 0] ** 2 + r[:, 1] ** 2)
    assert spin == pytest.approx(w, rel=2e-3)


@pytest.mark.xfail(strict=True, reason="the ground at the grid nodes (the default) brakes a rolling ball (10 cells "
                                       "across: 0.51 v0 at 0.15 s, 0.27 v0 at 0.3 s, 0.05 v0 at 0.6 s, where a rigid "
                                       "ball rolls on at 0.71 v0); ground_contact='penalty' rolls (below), not yet the "
                                       "default (#24)")
def test_a_rolling_ball_rolls_on(rolls):
    v = rolls[0.01]
    assert np.all(v[1:7] / V0 > 0.6)


@pytest.fixture(scope="module")
def rolls_penalty():
    return {dx: _roll(dx, contact="penalty") for dx in (0.02, 0.01)}


def test_on_the_particles_ground_a_ball_slides_then_rolls_on_at_five_sevenths(rolls_penalty):
    """The particles' ground: the slide ends a little later than the rigid ball's 0.049 s (0.78-0.82 v0 at 0.05 s:
    the soft floor's contact takes a few ms to form), by 0.1 s the ball rolls at 5/7 v0 within 8% (measured 0.67 and
    0.70 v0 at 5 and 10 cells across), and it rolls on at 5/7 v0 within 13% to 0.6 s (measured: within 9% and 11.5%)
    losing less than 10% of its speed from 0.1 to 0.6 s (measured 3% and 5%). Not yet the rigid ball's no loss at
    all: a slow loss remains, which grows with the floor's stiffness (kernels.GROUND_K, GROUND_BETA; docs/sim.md). (The
    grid nodes' ground: 0.05 v0 at 0.6 s.)"""
    for dx, v in rolls_penalty.items():
        assert 5 / 7 < v[1] / V0 < 0.9, (dx, v / V0)
        assert v[2] / V0 == pytest.approx(5 / 7, rel=0.08), (dx, v / V0)
        assert np.all(np.abs(v[2:] / V0 / (5 / 7) - 1) < 0.13), (dx, v / V0)
        assert v[12] > 0.9 * v[2], (dx, v / V0)


def _rest(dx: float, contact: str) -> tuple[np.ndarray, np.ndarray]:
    """A 5 cm ball of E 1e5 Pa set down at rest on the ground for 0.4 s: (its sink below its contact height h + sp / 2
    per frame [m], its sideways drift per frame [m])."""
    sp = dx / 2
    g = np.arange(-R, R + 1e-9, sp) + sp / 2
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    p = p[np.linalg.norm(p, axis=1) < R]
    pts = p + np.array([0.1 + R, H - p[:, 1].min() + 0.5 * sp, 0.1 + R])
    grid = GridSpec.around(pts, dx, lower=(0.05, H - 0.04, 0.05), upper=(0.15 + 2 * R, H + 2 * R + 0.05, 0.15 + 2 * R))
    m = SimModel.create(pts, sp ** 3, RHO, E, 0.3, grid=grid, fps=FPS, E_max=E,
                        effects={"ground": {"height": H, "friction": MU}}, ground_contact=contact)
    out = MPMSolver(m).simulate(8, SimState.rest(m))
    return (H + 0.5 * sp) - out["x"][:, :, 1].min(1), out["x"][:, :, 0].mean(1) - pts[:, 0].mean()


def test_on_the_particles_ground_a_resting_ball_sinks_about_as_far_as_on_the_nodes():
    """The push is elastic: a ball set down at rest sinks into it and bobs (measured, lowest particle below its
    contact height: at most 6.6 mm at 5 cells across, 7.5 mm at 10, 1.6-3.3 mm at 0.4 s), as far as the grid nodes'
    band lets it (5.9 and 3.8 mm, still): no more than 1.25x the nodes' on average over 0.1-0.4 s, less than a fifth
    of its radius at any time, and it does not wander sideways."""
    for dx in (0.02, 0.01):
        pen, drift = _rest(dx, "penalty")
        nodes, _ = _rest(dx, "nodes")
        assert pen.max() < 0.2 * R, (dx, pen)
        assert pen[2:].mean() < 1.25 * nodes[2:].mean(), (dx, pen, nodes)
        assert pen.max() > 0.0
        assert np.abs(drift).max() < 0.05 * dx / 2


def _standing_cylinder(contact: str) -> tuple[float, float]:
    """A round bar (radius 19 mm, 10 cm long, E 3.6e4 Pa: dev_0518's) set down at rest, its particles on a lattice a
    quarter spacing off its axis: the bottom is a flat row of 4 particles (16 mm wide) and the centre of mass lies 1.25
    mm to one side of that row's middle, inside it. A rigid body so made stands; a soft one tilts a little toward its
    centre of mass and stays. Returns (its largest rotation about its axis [deg], its largest sideways shift [m]) over
    0.4 s."""
    rad, length, sp, e = 0.019, 0.1, 0.004, 3.6e4
    n = int(2 * rad / sp) + 1
    g = (np.arange(n) - (n - 1) / 2) * sp + 0.25 * sp
    gx = np.arange(0, length, sp)
    p = np.stack(np.meshgrid(gx, g, g, indexing="ij"), -1).reshape(-1, 3)
    p = p[np.hypot(p[:, 1], p[:, 2]) < rad]
    p = p + np.array([0.1, H - p[:, 1].min() + 0.5 * sp, 0.15])
    grid = GridSpec.around(p, 2 * sp, lower=(0.05, H - 0.03, 0.05), upper=(0.25, H + 0.08, 0.25))
    m = SimModel.create(p, sp ** 3, RHO, e, 0.3, grid=grid, fps=30, E_max=e,
                        effects={"ground": {"height": H, "friction": 0.7}}, ground_contact=contact)
    x = MPMSolver(m).simulate(12, SimState.rest(m))["x"]
    r0 = p - p.mean(0)
    rot, shift = [], []
    for xk in x:
        d = xk - xk.mean(0)
        a = np.arctan2(d[:, 1], d[:, 2]) - np.arctan2(r0[:, 1], r0[:, 2])
        rot.append(abs(np.degrees(np.median((a + np.pi) % (2 * np.pi) - np.pi))))
        shift.append(abs((xk - p).mean(0)[2]))
    return max(rot), max(shift)


def test_a_round_bar_whose_weight_lies_over_its_bottom_stands_on_the_nodes_ground():
    """Measured: it rocks to 5.9 deg and back, shifting 2.4 mm at most (a rigid one would not move at all)."""
    rot, shift = _standing_cylinder("nodes")
    assert rot < 10.0 and shift < 0.004, (rot, shift)


@pytest.mark.xfail(strict=True, reason="the particles' ground is too soft against tipping: the bar rolls 29 deg and "
                   "shifts 9.5 mm in 0.33 s (docs/sim.md; dev_0518's truth rolled 40 deg before its grasp)")
def test_a_round_bar_whose_weight_lies_over_its_bottom_stands_on_the_particles_ground():
    rot, shift = _standing_cylinder("penalty")
    assert rot < 10.0 and shift < 0.004, (rot, shift)
