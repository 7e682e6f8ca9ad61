"""`effects`: switch a physical effect of the model on or off (`add`, `remove`) and say which are on
(`list_effects`). An effect is its API schema (`PhysInteractDampingAPI` ...) on /World/PhysInteract,
authored in the user's root layer (usd/effects_io.py), with start values and a `fit` flag; the next
`fit` warm-starts from the current version and fits the new parameters too (app/fit.py), as a new
version, so `report` shows the error across versions.

Effects and parameters (sim/effects.py; short aliases accepted):
  damping          coefficient c [1/s]                          null 0
  plasticity       yieldStress tau_Y [Pa]                       null inf
  ground           height h [m], friction mu                    null: off
  viscoelasticity  modulus E_v [Pa], relaxationTime tau [s]     null E_v = 0
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..scene import SceneData
from ..sim.effects import EFFECT_NAMES, PARAMETERS, canonical, validate_values
from ..usd.effects_io import apply_effect, remove_effect, root_values
from .adapters import read_scene

UNITS = {"coefficient": "1/s", "yieldStress": "Pa", "height": "m", "friction": "", "modulus": "Pa",
         "relaxationTime": "s"}


def check_name(stage_path, name: str) -> str:
    if name not in EFFECT_NAMES:
        raise InputError(stage_path, f"unknown effect {name!r}: one of {', '.join(EFFECT_NAMES)}")
    return name


def start_values(sd: SceneData, name: str) -> dict:
    """Sensible start values of an effect just switched on (none is its null value, which a log
    parameter cannot start from): damping 1/s; a yield stress of 5% and a Maxwell modulus of 20% of
    the middle of the allowed E range, relaxing in 0.1 s; a ground at the object's lowest particle,
    friction 0.5. The fit searches the main parameter anyway (fit/effect_params.py)."""
    st = sd.settings
    e_mid = math.sqrt(st.youngs_min * st.youngs_max)
    if name == "damping":
        return {"coefficient": 1.0}
    if name == "plasticity":
        return {"yieldStress": 0.05 * e_mid}
    if name == "viscoelasticity":
        return {"modulus": 0.2 * e_mid, "relaxationTime": 0.1}
    y = float(np.min(sd.particles_positions[:, 1])) - 0.5 * st.particle_spacing
    return {"height": y, "friction": 0.5}


def diagnosed_values(stage_path, sd: SceneData, name: str) -> dict:
    """The start values `diagnose` estimated for `name` on the current version, when its diagnosis
    is on the stage (usd/diagnosis_io.py); {} otherwise. Only positive, finite parameter values."""
    if sd.current_version is None:
        return {}
    try:
        from ..usd.diagnosis_io import read_diagnosis
    except ImportError:       # a physinteract-usd without `diagnose`
        return {}
    try:
        d = read_diagnosis(stage_path, sd.current_version) or {}
    except (InputError, OSError, ValueError):
        return {}
    for c in d.get("candidates") or []:
        if c.get("effect") != name:
            continue
        out = {}
        for p in PARAMETERS[name]:
            v = (c.get("estimate") or {}).get(p)
            if isinstance(v, (int, float)) and math.isfinite(v) and (v > 0 or p == "height"):
                out[p] = float(v)
        return out
    return {}


def _parse_params(stage_path, name: str, params: dict | None) -> dict:
    out = {}
    for k, v in (params or {}).items():
        try:
            p = canonical(name, k)
        except KeyError:
            raise InputError(stage_path, f"effect {name} has no parameter {k!r}: it has "
                             f"{', '.join(PARAMETERS[name])}") from None
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise InputError(stage_path, f"{name} {p} must be a number, got {v!r}") from None
        if math.isnan(x) or (math.isinf(x) and p != "yieldStress"):
            raise InputError(stage_path, f"{name} {p} must be finite, got {v!r}")
        try:
            validate_values(name, p, x)
        except ValueError as exc:
            raise InputError(stage_path, str(exc)) from None
        out[p] = x
    return out


def add(stage_path, name: str, params: dict | None = None, *, fixed: bool = False) -> dict:
    """Switch `name` on in the root layer, with `params` ({parameter or alias: value}) over the
    start values (what the root already says of it, else what `diagnose` estimated on the current
    version, else `start_values`), fitted by the next `fit` unless `fixed`. Returns {"stage",
    "effect", "values", "source" (per parameter: given | yours | diagnose v<N> | default), "fit",
    "layer"}."""
    stage_path = Path(stage_path)
    check_name(stage_path, name)
    given = _parse_params(stage_path, name, params)
    sd = read_scene(stage_path)
    if name in sd.effects:
        raise InputError(stage_path, f"effect {name} is already on (`effects list` shows it; "
                         f"`effects remove {name}` first to start it afresh)")
    authored_before = {k: v for k, v in root_values(stage_path, name).items() if k != "fit"}
    diagnosed = diagnosed_values(stage_path, sd, name)
    values = {**start_values(sd, name), **diagnosed, **authored_before, **given}
    authored = apply_effect(stage_path, name, values, fit=not fixed, keep_authored=False)
    source = {p: ("given" if p in given else "yours" if p in authored_before else
                  f"diagnose v{sd.current_version}" if p in diagnosed else "default") for p in values}
    return {"stage": str(stage_path), "effect": name, "values": {k: v for k, v in authored.items() if k != "fit"},
            "source": source, "fit": not fixed, "layer": str(stage_path)}


def remove(stage_path, name: str) -> dict:
    """Switch `name` off (its API and the root's values of it removed). Returns {"stage", "effect",
    "removed": [attribute names], "layer"}."""
    stage_path = Path(stage_path)
    check_name(stage_path, name)
    sd = read_scene(stage_path)
    if name not in sd.effects:
        on = ", ".join(sd.effects) or "none"
        raise InputError(stage_path, f"effect {name} is not on (on: {on})")
    removed = remove_effect(stage_path, name)
    return {"stage": str(stage_path), "effect": name, "removed": removed, "layer": str(stage_path)}


def list_effects(stage_path) -> dict:
    """{"stage", "current_version", "effects": [{"effect", "on", "fit", "parameters": {p: {"value"
    (the stage's: the start value), "fitted" (the current version's, or None), "unit"}},
    "fitted_in": [versions whose fit had it]}]} for every effect name, on ones first."""
    stage_path = Path(stage_path)
    sd = read_scene(stage_path)
    rep = sd.current_report
    fitted = (rep or {}).get("effect_parameters") or {}
    out = []
    for name in EFFECT_NAMES:
        on = name in sd.effects
        vals = sd.effects.get(name, {})
        params = {}
        for p in PARAMETERS[name]:
            v = vals.get(p) if on else None
            f = fitted.get(name, {}).get(p) if on else None
            params[p] = {"value": None if v is None else float(v), "fitted": None if f is None else float(f),
                         "unit": UNITS[p]}
        out.append({"effect": name, "on": on, "fit": bool(vals.get("fit", True)) if on else None,
                    "parameters": params,
                    "fitted_in": [int(r["version"]) for r in sd.reports if name in r.get("effects", [])]})
    out.sort(key=lambda d: not d["on"])
    return {"stage": str(stage_path), "current_version": sd.current_version, "effects": out}
