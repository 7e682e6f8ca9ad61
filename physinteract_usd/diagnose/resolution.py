"""The model's resolution error: the fitted model on a finer grid, in the diagnosis's residual (#22).

A fitted model's residual has three parts: the data's noise and the rendering's own error (the rest
frame's floor, `core._floor`), what the model lacks (the candidates), and the simulator's
discretisation: the video is the continuum, the model a grid. The third grows with the motion, so
the rest frame does not show it, and without a measure of it every clean capture whose truth is
finer than the fit reads `unexplained` (foam_bar's 20 controls on the H200: 2.1-2.9x the floor).

`resolution_change` simulates the base (its E and nu carried to the finer particles, its effects and
hand paths) on `refine.refine_scene`'s finer grid and takes its residual through the *same*
`ImageResidual` (pixels, weights, photometric and floor projectors fixed at the coarse base): the
change d = r_fine - r_coarse is how far the frames move when only the resolution changes. Its mean
square, `change`, is on the loss's scale. The finer model is not refitted (that would be a fit); its 1-D
stiffness scan (`resolution_change(scales=...)`: the base's E field x s) says whether a finer model wants
another E (the fit's resolution bias of E, #24). `resolution_error` takes two splits and extrapolates their
changes (`richardson`) to the coarse model's own error, or one split at an assumed order (`one_level`: the
CPU's default, a sixth of the cost), which `core.conclude` weighs in the verdict.

No USD, no CLI: a FitProblem, a BaseState and an ImageResidual in, numbers out.
"""

from __future__ import annotations

import copy
import math
import time

import numpy as np
import torch
from scipy.optimize import brentq

from ..refine import REFINE, refine_scene
from ..errors import SimulationError
from .residual import loss


def fine_problem(prob, split: int = REFINE):
    """(the finer FitProblem, parent index) of `prob` (a fit.FitProblem): its scene refined
    (`refine.refine_scene`), its contacts (hand paths included) carried, its effects and settings."""
    from ..fit.problem import FitProblem

    fine_sd, contacts, parent = refine_scene(prob.scene, split, contacts=prob.contacts)
    fp = FitProblem(fine_sd, prob.obs, contacts, effects=dict(prob.effects), device=prob.device,
                    dtype="float64" if prob.tdtype == torch.float64 else "float32", weights=prob.weights,
                    traj_sigma_px=prob.traj_sigma_px)
    return fp, parent


def residual_on(res, prob):
    """`res` (an ImageResidual) rendering through `prob` instead: the same pixels, weights and projectors."""
    r = copy.copy(res)
    r.prob = prob
    return r


def resolution_change(prob, base, res, r0: np.ndarray, *, split: int = REFINE, scales=(),
                      log=None, keep: dict | None = None) -> dict:
    """The base simulated on the grid `split` x finer (module doc). Returns {"split", "particles": (coarse, fine),
    "substeps": (coarse, fine), "loss", "loss_fine", "change" (mean square of d), "cos" (d against r0:
    > 0 where the finer model moves the frames toward the video), "scan": [(s, loss_fine at E x s)],
    "seconds"}; {"split", "failed": why} when the finer model cannot be built or goes unstable. `keep`: a dict
    that receives the change vector d under its split."""
    log = log or (lambda *a: None)
    t0 = time.perf_counter()
    try:
        fp, parent = fine_problem(prob, split)
    except (ValueError, SimulationError) as exc:
        log(f"resolution check skipped: {exc}")
        return {"split": int(split), "failed": str(exc)}
    pi = torch.as_tensor(parent, dtype=torch.long, device=base.E.device)
    E, nu = base.E[pi].to(fp.tdtype), base.nu[pi].to(fp.tdtype)
    eff = {e: dict(p) for e, p in base.effects.items()}
    rf = residual_on(res, fp)
    out = {"split": int(split), "particles": [int(len(prob.x0)), int(len(fp.x0))]}
    try:
        fp.sim.ensure_stable(float(E.max()) * max([1.0, *scales]))
        with torch.no_grad():
            x, F = fp.sim.simulate(E, nu, None, effects=eff)
        r1 = rf(x, F)
        scan = []
        for s in scales:
            with torch.no_grad():
                xs, Fs = fp.sim.simulate(E * float(s), nu, None, effects=eff)
            scan.append((float(s), loss(rf(xs, Fs))))
    except SimulationError as exc:
        log(f"resolution check: the finer model went unstable ({exc})")
        return dict(out, failed=str(exc))
    d = r1 - r0
    if keep is not None:
        keep[split] = d
    n0, nd = float(np.linalg.norm(r0)), float(np.linalg.norm(d))
    out.update(substeps=[int(prob.sim.substeps), int(fp.sim.substeps)], loss=loss(r0), loss_fine=loss(r1),
               change=loss(d), cos=float(-(d @ r0) / (n0 * nd)) if n0 > 0 and nd > 0 else 0.0, scan=scan,
               seconds=time.perf_counter() - t0)
    return out


def richardson(changes: dict) -> dict:
    """The coarse model's own discretisation error from two refinements (Richardson): with the frames'
    error ~ h^p, the change to the grid split a (cell / a) is d_a = e(h / a) - e(h) = e(h) (a^-p - 1), so
    |d_b| / |d_a| = (1 - b^-p) / (1 - a^-p) gives p, and the coarse model's error |e(h)| = |d_a| / (1 - a^-p).
    `changes`: {split: mean square of d_split} (the loss's scale) for two splits a < b. The order is kept
    within [1/2, 4] (outside: not the asymptotic range; the estimate then says so, `clipped`). Returns
    {"order", "order_raw", "error" (a mean square: the loss's scale), "clipped"}."""
    (a, ca), (b, cb) = sorted((int(k), float(v)) for k, v in changes.items())
    if not ca > 0:
        return {"order": None, "order_raw": None, "error": 0.0, "clipped": False}
    ratio = math.sqrt(max(cb, 0.0) / ca)

    def g(p):
        return (1.0 - b ** -p) / (1.0 - a ** -p)

    lo, hi = 0.5, 4.0
    # g falls from log b / log a (p -> 0) to 1 (p -> inf): a root where the ratio lies between them, else the
    # ratio is past one end (a finer change as large as p -> 0 allows: raw 0; no larger than the first: raw inf)
    if ratio >= g(1e-6):
        raw = 0.0
    elif ratio <= g(50.0):
        raw = math.inf
    else:
        raw = float(brentq(lambda q: g(q) - ratio, 1e-6, 50.0, xtol=1e-12))
    p = float(min(max(raw, lo), hi))
    return {"order": p, "order_raw": raw if math.isfinite(raw) else None,
            "error": ca / (1.0 - a ** -p) ** 2, "clipped": bool(p != raw)}


# one refinement alone cannot measure the order: it is assumed first order, the order of MPM's transfers in practice
# and at or below what two refinements measured almost everywhere (foam_bar's 36 GPU cases 1.2-2.3 on most, one
# 0.86; the CPU demo's bar 1.18, bow_tie at grid 16 1.17, the walkthrough's control 2.4; development data). A lower
# order reads a larger error from the same change (x4 at p = 1, x2.6 at 1.4), so the one-level check errs toward
# "the grid explains it", never toward a false alarm
ASSUMED_ORDER = 1.0


def one_level(change: float, split: int, order: float = ASSUMED_ORDER) -> dict:
    """The coarse model's error from one refinement at an assumed order p: |e(h)| = |d_a| / (1 - a^-p)
    (`richardson` with p given, not measured). Same keys as `richardson`, "assumed": True."""
    c = max(float(change), 0.0)
    return {"order": float(order), "order_raw": None, "error": c / (1.0 - float(split) ** -float(order)) ** 2,
            "clipped": False, "assumed": True}


def resolution_error(prob, base, res, r0: np.ndarray, *, splits=(2, 3), log=None, keep: dict | None = None) -> dict:
    """The base's own discretisation error on the diagnosis's residual: `resolution_change` at two
    splits, extrapolated by `richardson`; at one split (the CPU's default: ~16x a forward instead of ~100x),
    `one_level` at `ASSUMED_ORDER`. Returns {"levels": [the changes' dicts], "order", "error" (a mean
    square on the loss's scale), "cos" (the two changes' directions; None with one split), "seconds"}; "error"
    None and "failed" (why) when a finer model could not be simulated. `keep`: a dict that receives each
    split's change vector d_split."""
    t0 = time.perf_counter()
    keep = {} if keep is None else keep          # {split: the change d_split}: the caller's, when given
    levels = []
    for m in splits:
        lv = resolution_change(prob, base, res, r0, split=m, log=log, keep=keep)
        levels.append(lv)
        if "failed" in lv:
            return {"levels": levels, "order": None, "error": None, "failed": lv["failed"],
                    "seconds": time.perf_counter() - t0}
    a, b = splits[0], splits[-1]
    if len(splits) == 1:
        out = one_level(levels[0]["change"], a)
        out.update(levels=levels, cos=None, seconds=time.perf_counter() - t0)
        return out
    da, db = keep[a], keep[b]
    na, nb = float(np.linalg.norm(da)), float(np.linalg.norm(db))
    out = richardson({a: levels[0]["change"], b: levels[-1]["change"]})
    out.update(levels=levels, cos=float(da @ db / (na * nb)) if na > 0 and nb > 0 else 0.0,
               seconds=time.perf_counter() - t0)
    return out


__all__ = ["fine_problem", "residual_on", "resolution_change", "richardson", "one_level", "resolution_error",
           "ASSUMED_ORDER"]
