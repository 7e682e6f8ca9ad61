"""The `simulate` interaction spec (`physinteract-usd simulate --help`) from what the artist
animated, as plain numbers: no bpy here (the add-on samples the Empty, this writes the JSON).

Everything is in the stage's frame (metres, Y up) and in the stage's frames (frame k = USD time
code k = Blender frame k after an import; frame 0 is the object at rest).

Kinds, as the panel names them:
- `drag` (pointAdherent): the particles within the Empty's radius at the grasp frame (or the
  selected points) are held and follow the Empty. The trajectory is the held particles' rest
  centroid moved by the Empty's displacement since the grasp frame: the Empty need not sit at the
  centroid, only its motion counts (the simulator drives the held particles by the trajectory's
  velocity).
- `poke` (pointNonAdherent): a sphere collider of the Empty's radius at the Empty's position.
- `push` (surfaceNonAdherent): a plane through the Empty's position, its normal the Empty's local
  +Z (the object is on the side the normal points to).
"""

from __future__ import annotations

import re

import numpy as np

KINDS = {"drag": "pointAdherent", "poke": "pointNonAdherent", "push": "surfaceNonAdherent"}


class SpecError(ValueError):
    """What the artist must change: one line."""


def sim_name(text: str) -> str:
    """A simulation name the CLI accepts (letters, digits, '_' and '-')."""
    name = re.sub(r"[^A-Za-z0-9_\-]+", "_", text or "").strip("_")
    return name or "resim"


def _round(a, nd=6):
    return np.round(np.asarray(a, np.float64), nd).tolist()


def build_spec(kind: str, positions, *, grasp: int = 0, release: int | None = None, radius: float = 0.0,
               normal=(0.0, 1.0, 0.0), indices=None, rest=None, name: str = "resim",
               keep_supports: bool = True, friction: float = 0.5, source: str = "") -> dict:
    """The spec dict. positions: (n, 3) the Empty's position per frame (stage frame); radius: the
    Empty's radius (m); indices: held particles (drag) or None to take those within `radius` of
    the Empty at `grasp`; rest: (P, 3) SimParticles' rest positions (needed for a drag)."""
    if kind not in KINDS:
        raise SpecError(f"interaction kind must be one of {', '.join(KINDS)}, not {kind!r}")
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    n = len(pos)
    if n < 2:
        raise SpecError("the resimulation needs at least 2 frames")
    if not np.isfinite(pos).all():
        raise SpecError("the Empty's positions are not finite")
    grasp = int(grasp)
    if not 0 <= grasp < n - 1:
        raise SpecError(f"the grasp frame {grasp} must lie in [0, {n - 1}) for {n} frames")
    if release is not None and not grasp < int(release) <= n:
        raise SpecError(f"the release frame {release} must come after the grasp frame {grasp} (and be <= {n})")
    if np.abs(pos[grasp:] - pos[grasp]).max() < 1e-6 and kind == "drag":
        raise SpecError(f"the Empty does not move after frame {grasp}: keyframe its location")
    c: dict = {"name": "blender", "type": KINDS[kind], "grasp_frame": grasp,
               "release_frame": None if release is None else int(release)}
    if kind == "drag":
        if rest is None:
            raise SpecError("a drag needs the stage's particles (import the stage first)")
        rest = np.asarray(rest, np.float64).reshape(-1, 3)
        if indices is not None and len(indices):
            idx = np.asarray(sorted(set(int(i) for i in indices)), np.int64)
            if idx.min() < 0 or idx.max() >= len(rest):
                raise SpecError(f"selected point indices must lie in [0, {len(rest)}): select points of the "
                                "imported SimParticles cloud")
            c["select"] = {"indices": idx.tolist()}
        else:
            if not radius > 0:
                raise SpecError("the Empty's radius (its display size) must be > 0")
            idx = np.where(np.linalg.norm(rest - pos[grasp], axis=1) <= radius)[0]
            if not len(idx):
                d = float(np.linalg.norm(rest - pos[grasp], axis=1).min())
                raise SpecError(f"no particle within the Empty's radius {radius:.3g} m at frame {grasp} (the "
                                f"nearest is {d:.3g} m away): move it onto the object or enlarge its display size")
            c["select"] = {"centre": _round(pos[grasp]), "radius": round(float(radius), 6)}
        centroid = rest[idx].mean(0)
        steps = np.clip(np.arange(n) - grasp, 0, None)[:, None] > 0
        traj = centroid + np.where(steps, pos - pos[grasp], 0.0)
        c["trajectory"] = _round(traj)
        c["particles"] = int(len(idx))  # informational: the CLI ignores unknown keys
    elif kind == "poke":
        if not radius > 0:
            raise SpecError("the Empty's radius (its display size) must be > 0")
        c["radius"] = round(float(radius), 6)
        c["trajectory"] = _round(pos)
    else:
        nrm = np.asarray(normal, np.float64)
        if not np.linalg.norm(nrm) > 0:
            raise SpecError("the push plane's normal (the Empty's +Z) is zero")
        c["normal"] = _round(nrm / np.linalg.norm(nrm))
        c["trajectory"] = _round(pos)
        c["friction"] = float(friction)
    spec = {"name": sim_name(name), "frames": n, "keep_supports": bool(keep_supports), "contacts": [c]}
    if source:
        spec["source"] = source
    return spec


def held_particles(spec: dict, rest) -> np.ndarray:
    """Which particles a drag spec holds (what the CLI computes from it)."""
    c = spec["contacts"][0]
    sel = c.get("select") or {}
    if "indices" in sel:
        return np.asarray(sel["indices"], np.int64)
    rest = np.asarray(rest, np.float64).reshape(-1, 3)
    return np.where(np.linalg.norm(rest - np.asarray(sel["centre"]), axis=1) <= sel["radius"])[0]
