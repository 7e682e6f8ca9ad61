"""The phases of an interaction, frame by frame: `rest` (nothing has touched the object yet),
`load` (the hand holds it and moves), `hold` (the hand holds it still), `release` (the first
moments after the hand lets go) and `free` (the object on its own: swinging, settling, resting
on its supports). From the contacts' grasp / release frames and the hand's trajectory."""

from __future__ import annotations

import numpy as np

PHASES = ("rest", "load", "hold", "release", "free")
PHASE_COLORS = {"rest": "#d9d9d9", "load": "#fdae6b", "hold": "#9ecae1", "release": "#fb6a4a", "free": "#a1d99b"}
RELEASE_SECONDS = 0.15   # how long after the release the `release` phase lasts (at least one frame)


def frame_phases(contacts, n_frames: int, fps: float, trajectories: dict | None = None, *,
                 still_fraction: float = 0.1, release_seconds: float = RELEASE_SECONDS) -> list[str]:
    """One phase name per frame. `contacts`: `contacts.ContactSet`s (supports are ignored);
    `trajectories`: {contact name: (T, 3)} that override the contacts' own (e.g. the fitted ones).
    The hand is moving into frame k when its step from k - 1 exceeds `still_fraction` of its
    largest step while it acts (and 10 micrometres)."""
    T = int(n_frames)
    inter = [c for c in contacts if c.is_interaction]
    if not inter:
        return ["rest"] + ["free"] * (T - 1) if T else []
    trajectories = trajectories or {}
    step = np.zeros(T)
    active = np.zeros(T, bool)
    for c in inter:
        act = np.array([c.active(k) for k in range(T)])
        active |= act
        tr = trajectories.get(c.name, c.trajectory)
        if tr is None or len(tr) < 2:
            continue
        tr = np.asarray(tr, float)[:T]
        d = np.zeros(T)
        d[1:len(tr)] = np.linalg.norm(np.diff(tr, axis=0), axis=1)
        step = np.maximum(step, np.where(act, d, 0.0))
    moving = step > max(still_fraction * (step.max() if step.size else 0.0), 1e-5)
    first = min(c.grasp_frame for c in inter)
    n_release = max(1, int(round(release_seconds * fps)))
    out, last_release = [], None
    for k in range(T):
        if active[k]:
            out.append("load" if moving[k] else "hold")
        elif k < first or (k == 0):
            out.append("rest")
        else:
            if last_release is None or (k > 0 and active[k - 1]):
                last_release = k
            out.append("release" if k - last_release < n_release else "free")
    return out


def phase_runs(phases: list[str]) -> list[tuple[str, int, int]]:
    """[(phase, first frame, last frame)] of the consecutive runs."""
    runs = []
    for k, p in enumerate(phases):
        if runs and runs[-1][0] == p and runs[-1][2] == k - 1:
            runs[-1] = (p, runs[-1][1], k)
        else:
            runs.append((p, k, k))
    return runs
