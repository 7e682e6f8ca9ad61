"""The `simulate` interaction spec: a JSON file describing a new interaction (which particles, how
they move, when), read into `contacts.ContactSet`s. `INTERACTION_DOC` is what `simulate --help`
shows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..contacts import ContactSet
from ..errors import InputError
from ..scene import SceneData

INTERACTION_DOC = """Interaction spec (JSON) for `simulate`:
{
  "name": "pull_petal",            optional; default: the file's stem
  "frames": 40,                    optional; default: the stage's frame count
  "keep_supports": true,           keep the fitted stage's fixed contact sets (default true)
  "contacts": [
    {"type": "pointAdherent",      pointAdherent | pointNonAdherent | surfaceNonAdherent | fixed
     "select": {"centre": [x, y, z], "radius": 0.03},   which particles (rest positions, metres);
                                   or {"indices": [...]} or {"contact": "hand"} (a stage contact set)
     "grasp_frame": 2, "release_frame": 30,
     "displacement": [0.05, 0.1, 0.0]   moved smoothly over the grasp window; or
     "trajectory": [[x, y, z], ...]     positions per frame (frames entries); or
     "velocity": [vx, vy, vz]           constant while grasped
    },
    {"type": "pointNonAdherent", "radius": 0.02, "trajectory": [[x, y, z], ...]},
    {"type": "surfaceNonAdherent", "normal": [0, -1, 0], "trajectory": [[x, y, z], ...], "friction": 0.5}
  ]
}"""


def parse_interaction(path, sd: SceneData):
    """The interaction spec at `path` for the stage `sd` -> (spec dict, frames, [ContactSet]): every
    contact checked (one-line InputError naming the file and the entry); the stage's supports kept
    unless `keep_supports` is false."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        spec = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("contacts"), list) or not spec["contacts"]:
        raise InputError(path, "expected an object with a non-empty 'contacts' list (see `simulate --help`)")
    n = _spec_int(path, "'frames'", spec.get("frames", sd.n_frames))
    if n < 2:
        raise InputError(path, "'frames' must be at least 2")
    x0 = sd.particles_positions
    by_name = {c.name: c for c in sd.contacts}
    out = []
    for i, c in enumerate(spec["contacts"]):
        where = f"contacts[{i}]"
        if not isinstance(c, dict):
            raise InputError(path, f"{where}: expected an object with a 'type'")
        t = c.get("type")
        if t not in ("pointAdherent", "pointNonAdherent", "surfaceNonAdherent", "fixed"):
            raise InputError(path, f"{where}: type must be pointAdherent, pointNonAdherent, surfaceNonAdherent or fixed")
        idx = np.zeros(0, np.int64)
        if t in ("pointAdherent", "fixed"):
            sel = c.get("select")
            if not isinstance(sel, dict):
                raise InputError(path, f"{where}: needs 'select' (centre+radius, indices or contact)")
            if "indices" in sel:
                raw = sel["indices"]
                if not isinstance(raw, list) or not raw or not all(isinstance(v, int) and not isinstance(v, bool) for v in raw):
                    raise InputError(path, f"{where}: 'indices' must be a non-empty list of integers")
                idx = np.asarray(raw, np.int64)
                if idx.min() < 0 or idx.max() >= len(x0):
                    raise InputError(path, f"{where}: indices must lie in [0, {len(x0)})")
            elif "contact" in sel:
                if sel["contact"] not in by_name:
                    raise InputError(path, f"{where}: the stage has no contact set '{sel['contact']}' "
                                     f"(it has {', '.join(by_name) or 'none'})")
                idx = by_name[sel["contact"]].indices
            elif "centre" in sel and "radius" in sel:
                centre = _spec_vec3(path, f"{where}: 'centre'", sel["centre"])
                radius = _spec_float(path, f"{where}: 'radius'", sel["radius"])
                idx = np.where(np.linalg.norm(x0 - centre, axis=1) <= radius)[0]
                if len(idx) == 0:
                    raise InputError(path, f"{where}: no particle within {sel['radius']} m of {sel['centre']}")
            else:
                raise InputError(path, f"{where}: 'select' needs centre+radius, indices or contact")
        g = _spec_int(path, f"{where}: 'grasp_frame'", c.get("grasp_frame", 0))
        r = c.get("release_frame")
        r = None if r is None else _spec_int(path, f"{where}: 'release_frame'", r)
        if not 0 <= g < n - 1:
            raise InputError(path, f"{where}: grasp_frame must lie in [0, {n - 1}) for {n} frames")
        if r is not None and not g < r <= n:
            raise InputError(path, f"{where}: release_frame must lie in ({g}, {n}] (after grasp_frame)")
        traj = None
        if t != "fixed":
            if "trajectory" in c:
                try:
                    traj = np.asarray(c["trajectory"], float)
                except (TypeError, ValueError):
                    traj = None
                if traj is None or traj.shape != (n, 3) or not np.isfinite(traj).all():
                    raise InputError(path, f"{where}: trajectory must be {n} positions [x, y, z]")
            elif "displacement" in c:
                start = x0[idx].mean(0) if len(idx) else np.zeros(3)
                d = _spec_vec3(path, f"{where}: 'displacement'", c["displacement"])
                s = np.clip((np.arange(n) - g) / max((r if r is not None else n - 1) - g, 1), 0, 1)
                s = s * s * (3 - 2 * s)
                traj = start + s[:, None] * d
            elif "velocity" in c:
                start = x0[idx].mean(0) if len(idx) else np.zeros(3)
                v = _spec_vec3(path, f"{where}: 'velocity'", c["velocity"])
                steps = np.clip(np.arange(n) - g, 0, (r if r is not None else n) - g)
                traj = start + steps[:, None] / sd.fps * v
            else:
                raise InputError(path, f"{where}: give a trajectory, a displacement or a velocity")
            if t in ("pointNonAdherent", "surfaceNonAdherent") and "trajectory" not in c:
                raise InputError(path, f"{where}: a {t} collider needs a 'trajectory' (positions per frame)")
        normal = _spec_vec3(path, f"{where}: 'normal'", c.get("normal", (0.0, 1.0, 0.0)))
        if t == "surfaceNonAdherent" and not np.linalg.norm(normal) > 0:
            raise InputError(path, f"{where}: 'normal' must be a non-zero vector")
        out.append(ContactSet(str(c.get("name", f"{t}{i}")), t, idx, g, r, traj,
                              radius=_spec_float(path, f"{where}: 'radius'", c.get("radius", 0.0)),
                              normal=tuple(normal), friction=_spec_float(path, f"{where}: 'friction'", c.get("friction", 0.5)),
                              source="user"))
        if t == "pointNonAdherent" and not out[-1].radius > 0:
            raise InputError(path, f"{where}: pointNonAdherent needs a radius > 0")
    pinned = [c for c in out if c.type in ("pointAdherent", "fixed")]
    for a in range(len(pinned)):
        for b in range(a):
            if np.intersect1d(pinned[a].indices, pinned[b].indices).size:
                raise InputError(path, f"contacts '{pinned[b].name}' and '{pinned[a].name}' hold the same "
                                 "particles (each particle follows one contact)")
    if spec.get("keep_supports", True):
        used = set(np.concatenate([c.indices for c in out])) if out else set()
        for c in sd.contacts:
            if c.type == "fixed":
                keep = np.array([i for i in c.indices if i not in used], np.int64)
                if len(keep):
                    out.append(ContactSet(c.name, "fixed", keep, source=c.source))
    return spec, n, out


def _spec_int(path, what, v) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(path, f"{what} must be an integer, not {_json_repr(v)}")
    return int(v)


def _spec_float(path, what, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise InputError(path, f"{what} must be a number, not {_json_repr(v)}")
    return float(v)


def _spec_vec3(path, what, v) -> np.ndarray:
    if (not isinstance(v, (list, tuple)) or len(v) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in v)):
        raise InputError(path, f"{what} must be three numbers [x, y, z], not {_json_repr(v)}")
    return np.asarray(v, float)


def _json_repr(v) -> str:
    s = json.dumps(v)
    return s if len(s) <= 40 else s[:37] + "..."
