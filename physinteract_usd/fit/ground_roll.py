"""Does a fitted motion roll or tip on the ground? (#24)

Our simulator's ground acts on grid nodes, and a body rolling on it is braked where a rigid ball rolls on (the
known answer, 5/7 of the launch speed kept: tests/test_rolling_ball.py keeps ours, 10 cells across, at 0.27 of it
after 0.3 s), more on a coarser grid. So a fit whose motion rolls or tips on the ground finds the E that trades that
braking against the rest of the clip, not the material's (the world suite's floor balls: 0.2-0.3x;
docs/benchmarks/world_fits.md, "Floor objects"). `ground_roll` measures the body's rotation about horizontal axes
while it touches the plane; `roll_note` says it to the user, with what to do."""

from __future__ import annotations

import numpy as np

ROLL_NOTE_DEG = 5.0     # a rotation about a horizontal axis, while on the ground, worth a note


def body_rotation(rest: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The rotation vector [rad] of the best rigid fit (Kabsch) taking `rest` (P, 3) to `x` (P, 3)."""
    a = rest - rest.mean(0)
    b = x - x.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    angle = np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    if angle < 1e-9:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = np.linalg.norm(axis)
    if n < 1e-12:   # a half turn: the axis from the symmetric part
        w, v = np.linalg.eigh(r + r.T)
        axis, n = v[:, -1], 1.0
    return angle * axis / n


def ground_roll(positions: np.ndarray, height: float, near: float) -> dict | None:
    """The largest rotation (degrees) of the body about a horizontal axis (y is up) over the frames where its lowest
    particle is within `near` [m] of the ground plane y = `height`, and the frame; None when it never touches.
    `positions`: (T, P, 3), frame 0 at rest."""
    x = np.asarray(positions, np.float64)
    best, frame = 0.0, None
    for t in range(1, len(x)):
        if x[t, :, 1].min() - height > near:
            continue
        rv = body_rotation(x[0], x[t])
        deg = float(np.degrees(np.hypot(rv[0], rv[2])))
        if frame is None or deg > best:
            best, frame = deg, t
    return None if frame is None else {"degrees": best, "frame": frame}


def roll_note(positions: np.ndarray, height: float, cell: float) -> str | None:
    """One line for the user when the motion rolls or tips on the ground by `ROLL_NOTE_DEG` or more (touching: the
    lowest particle within 1.5 cells of the plane); None otherwise."""
    r = ground_roll(positions, height, 1.5 * cell)
    if r is None or r["degrees"] < ROLL_NOTE_DEG:
        return None
    return (f"ground: the fitted motion rolls or tips on the ground ({r['degrees']:.0f} degrees about a horizontal "
            f"axis by frame {r['frame']}); our simulator's ground at the grid nodes brakes a roll, more on a coarser "
            f"grid, so the fitted E is likely biased: trust it less, fit at a finer grid (init --grid), or put the "
            f"ground at the particles (PHYSINTERACT_GROUND=penalty, docs/sim.md)")
