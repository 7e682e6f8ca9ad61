"""fit.ground_roll: the body's rotation about horizontal axes while on the ground (known answers: rigid rotations
of a point cloud; a simulated ball rolling vs a block sliding), and the note the fit prints from it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from physinteract_usd.fit.ground_roll import ROLL_NOTE_DEG, body_rotation, ground_roll, roll_note
from physinteract_usd.sim import GridSpec, MPMSolver, SimModel, SimState
from sim_helpers import block


def _cloud(seed=0, n=200):
    return np.random.default_rng(seed).uniform(-0.05, 0.05, (n, 3)) + np.array([0.0, 0.05, 0.0])


@pytest.mark.parametrize("rotvec", [(0.3, 0, 0), (0, 0, -0.5), (0.2, 0.4, 0.1), (0, 3.1, 0)])
def test_body_rotation_recovers_a_rigid_rotation_and_ignores_a_translation(rotvec):
    rest = _cloud()
    r = Rotation.from_rotvec(rotvec)
    x = r.apply(rest - rest.mean(0)) + rest.mean(0) + np.array([0.3, -0.1, 0.2])
    assert body_rotation(rest, x) == pytest.approx(np.array(rotvec), abs=1e-9)


def test_ground_roll_counts_horizontal_axes_on_the_ground_only():
    rest = _cloud()
    c = rest.mean(0)
    lo = rest[:, 1].min()

    def frames(rotvec, lift=0.0):
        r = Rotation.from_rotvec(rotvec)
        return np.stack([rest] + [r.apply(rest - c) * 1.0 + c + np.array([0, lift, 0]) for _ in range(3)])

    rolled = ground_roll(frames((np.radians(20), 0, 0)), lo, 0.02)
    assert rolled["degrees"] == pytest.approx(20, abs=0.01) and rolled["frame"] == 1
    assert ground_roll(frames((0, np.radians(40), 0)), lo, 0.02)["degrees"] < 1e-6      # yaw: a drag, not a roll
    assert ground_roll(frames((np.radians(20), 0, 0), lift=0.5), lo, 0.02) is None        # off the ground
    assert roll_note(frames((np.radians(20), 0, 0)), lo, 0.01).startswith("ground: the fitted motion rolls")
    assert roll_note(frames((np.radians(ROLL_NOTE_DEG / 2), 0, 0)), lo, 0.01) is None


def test_the_note_is_said_for_a_simulated_rolling_ball_and_not_for_a_sliding_block():
    h, mu, dx = 0.1, 0.3, 0.02
    sp = dx / 2
    R = 0.05
    g = np.arange(-R, R + 1e-9, sp) + sp / 2
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    ball = p[np.linalg.norm(p, axis=1) < R]
    ball = ball + np.array([0.1 + R, h - ball[:, 1].min() + 0.5 * sp, 0.1 + R])
    box = block((8, 4, 8), sp, (0.1, h + 0.5 * sp, 0.1))
    for pts, rolls in ((ball, True), (box, False)):
        grid = GridSpec.around(pts, dx, lower=(0.05, h - 0.04, 0.05), upper=(0.45, h + 0.15, 0.25))
        m = SimModel.create(pts, sp ** 3, 1000.0, 1e5, 0.3, grid=grid, fps=20, E_max=1e5, max_speed=0.5,
                            effects={"ground": {"height": h, "friction": mu}})
        x = MPMSolver(m).simulate(4, SimState.rest(m, v0=(0.5, 0, 0)))["x"]
        note = roll_note(x, h, dx)
        assert (note is not None) == rolls, (rolls, ground_roll(x, h, 1.5 * dx))


def test_the_fit_says_it_with_the_ground_it_fitted():
    """app.fit.ground_notes: the ground's height from the fitted effect parameters where fitted, else the stage's;
    nothing without a ground."""
    from types import SimpleNamespace as NS

    from physinteract_usd.app.fit import ground_notes

    rest = _cloud()
    c, lo = rest.mean(0), rest[:, 1].min()
    r = Rotation.from_rotvec((0, 0, np.radians(30)))
    x = np.stack([rest, r.apply(rest - c) + c])

    def job(effects):
        return NS(problem=NS(sim=NS(effects=effects, grid=NS(dx=0.01))))

    res = NS(positions=x, effect_parameters={})
    assert "rolls or tips on the ground (30 degrees" in ground_notes(job({"ground": {"height": lo}}), res)[0]
    assert ground_notes(job({}), res) == []
    assert ground_notes(job({"ground": {"height": lo - 1.0}}), res) == []                   # far below: no touch
    fitted = NS(positions=x, effect_parameters={"ground": {"height": lo}})                 # the fitted height wins
    assert len(ground_notes(job({"ground": {"height": lo - 1.0}}), fitted)) == 1
    assert "PHYSINTERACT_GROUND=penalty" in ground_notes(job({"ground": {"height": lo}}), res)[0]


def test_the_fit_says_nothing_of_a_roll_with_the_ground_at_the_particles(monkeypatch):
    """With PHYSINTERACT_GROUND=penalty the ground does not brake a roll (tests/test_rolling_ball.py): no note."""
    from types import SimpleNamespace as NS

    from physinteract_usd import simulation
    from physinteract_usd.app.fit import ground_notes

    rest = _cloud()
    c, lo = rest.mean(0), rest[:, 1].min()
    x = np.stack([rest, Rotation.from_rotvec((0, 0, np.radians(30))).apply(rest - c) + c])
    job = NS(problem=NS(sim=NS(effects={"ground": {"height": lo}}, grid=NS(dx=0.01))))
    res = NS(positions=x, effect_parameters={})
    assert len(ground_notes(job, res)) == 1
    monkeypatch.setattr(simulation, "GROUND_CONTACT", "penalty")
    assert ground_notes(job, res) == []
