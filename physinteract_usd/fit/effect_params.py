"""The fitted effects' parameters, shared by both schedules ("bumps" and "ladder").

Each fitted parameter is an unconstrained leaf tensor: positive ones (damping coefficient, yield
stress, friction, Maxwell modulus and relaxation time) as their log, the ground's height as is (in
units of the problem's length scale, 5% of the object). Which effects are fitted: the stage's effect
APIs with `fit = true` (`FitSettings.fit_effects`); their start: a warm start's values (the previous
version's fitted ones), else the stage's, else (a null value: c = 0, tau_Y = inf, E_v = 0) a finite
guess (`effect_start`). An effect just switched on has no good start: `search_effects` finds one by
a 1-D search of the loss over its main parameter (forward passes only), the same way the uniform E
is found. No USD here.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import SimulationError
from .search import golden_section

POSITIVE = {"coefficient", "yieldStress", "friction", "modulus", "relaxationTime"}

# the parameter a new effect's start is searched over, and its range (lo, hi, "linear"|"log"),
# as functions of the scene's Young's modulus range (e_lo, e_hi)
SEARCHED = {
    "damping": ("coefficient", lambda e_lo, e_hi: (0.05, 200.0)),
    "plasticity": ("yieldStress", lambda e_lo, e_hi: (1e-3 * e_lo, 0.5 * e_hi)),
    "viscoelasticity": ("modulus", lambda e_lo, e_hi: (0.01 * e_lo, e_hi)),
    "ground": ("friction", lambda e_lo, e_hi: (0.02, 2.0)),
}


def effect_start(e_range: tuple[float, float], param: str, value: float) -> float:
    """A finite starting value for a fitted parameter whose value is its null (0 / inf)."""
    if math.isfinite(value) and value > 0:
        return value
    e_mid = math.sqrt(e_range[0] * e_range[1])
    return {"coefficient": 1.0, "yieldStress": 0.05 * e_mid, "modulus": 0.2 * e_mid, "relaxationTime": 0.1,
            "friction": 0.5}.get(param, value)


def effect_parameters(prob, fit_effects, start: dict | None = None) -> dict:
    """{effect: {param: unconstrained leaf tensor}} for the effects in `fit_effects` the problem
    switches on; start values from `start` ({effect: {param: value}}), else the problem's."""
    st = prob.scene.settings
    out = {}
    for e in fit_effects or ():
        if e not in prob.effects:
            continue
        vals = dict(prob.model.effects.params[e])
        vals.update({p: float(v) for p, v in ((start or {}).get(e) or {}).items() if p in vals})
        out[e] = {}
        for p, v in vals.items():
            v = effect_start((st.youngs_min, st.youngs_max), p, float(v))
            out[e][p] = torch.tensor(to_raw(p, v, prob.traj_scale), dtype=prob.tdtype, device=prob.tdev,
                                     requires_grad=True)
    return out


def to_raw(param: str, value: float, length_scale: float) -> float:
    return math.log(value) if param in POSITIVE else value / length_scale


def effect_values(raw: dict, length_scale: float) -> dict:
    """The parameters' values (tensors, differentiable) from their unconstrained leaves."""
    return {e: {p: (torch.exp(v) if p in POSITIVE else v * length_scale) for p, v in ps.items()}
            for e, ps in raw.items()}


def fitted_values(raw: dict, length_scale: float) -> dict:
    """{effect: {param: float}}: what a FitResult records."""
    return {e: {p: float(v.detach()) for p, v in ps.items()} for e, ps in effect_values(raw, length_scale).items()}


def search_effects(loss, raw: dict, effects: tuple, e_range: tuple[float, float], length_scale: float, *,
                   points: int = 6, refine: int = 4, log=None) -> dict:
    """Set the start of each effect in `effects` (a key of `raw`) by a 1-D search of `loss()` (a
    float: the loss at the current raw values, forward only) over its main parameter (`SEARCHED`):
    `points` log-spaced probes over the range, then `refine` golden-section steps around the best.
    A probe that goes unstable counts as infinite. Returns {effect: {"value", "loss", "probes"}}."""
    report = {}
    for e in effects:
        if e not in raw or e not in SEARCHED:
            continue
        p, rng = SEARCHED[e]
        if p not in raw[e]:
            continue
        lo, hi = (math.log(v) for v in rng(*e_range))
        leaf = raw[e][p]
        cache: dict[float, float] = {}

        def f(le):
            if le not in cache:
                with torch.no_grad():
                    leaf.fill_(le)
                try:
                    with torch.no_grad():
                        v = float(loss())
                except SimulationError:
                    v = float("inf")
                cache[le] = v if math.isfinite(v) else float("inf")
                if log:
                    log(f"{e} {p} {math.exp(le):.4g}: loss {cache[le]:.5f}")
            return cache[le]

        grid = np.linspace(lo, hi, max(int(points), 3))
        vals = [f(float(x)) for x in grid]
        i = int(np.argmin(vals))
        golden_section(f, grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)], refine)
        best = min(cache, key=cache.get)
        with torch.no_grad():
            leaf.fill_(best)
        report[e] = {"parameter": p, "value": math.exp(best), "loss": cache[best],
                     "probes": {f"{math.exp(k):.4g}": (round(v, 6) if math.isfinite(v) else None)
                                for k, v in sorted(cache.items())}}
    return report
