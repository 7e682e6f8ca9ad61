"""The bumps schedule's start from a trend: log E linear along one axis of the object (FitSettings.trend_start; #24).

Why: an object graded along its length (a balloon's rubber thin at the bottom, a rope stiff at the top and frayed at
the end) is fitted from the uniform E, which sits near its stiff end's value where the motion is dominated by it (the
balloon: uniform optimum 3.1e4 Pa against 3.75e4 / 7.5e3 at its ends). From there the gradient at the soft end points
*stiffer* (docs/benchmarks/fit.md, "Rprop ... refuted"): the bumps' Adam, Rprop, Gauss-Newton, scaled uniform starts and a
finer grid all stayed in that basin (soft end 2.5-3.1x), while the truth's own field renders better (0.0087 against
0.0100). The parts start (`parts_start.py`) cannot help: such an object has one colour.

What: before the finest level, when the parts start was not taken, a field whose log E runs linearly from one end of
the object to the other, log E = (1 - t) a + t b with t in [0, 1] the particle's place along the axis (free particles'
extent), is searched along each candidate axis: gravity's and the free particles' principal axes more than
AXIS_APART off the ones before (at most 3). Each axis first gets its two ends' one-sided probes (an end x2, else x0.5:
the parts simplex's two-sided vertices); the axis whose best probe renders best gets the simplex
(`select.part_refine`, the parts start's rule: its probes so far reused). The result, projected onto the level's bumps,
is the start under the parts start's acceptance rule (`parts_start.accept`): it must render better than the current
start by at least KEEP_SHARE of what the trend's own field gained; else nothing changes (the field and the substep's
rung restored).
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch

from .parts_start import accept, forwards_are_cheap, refine_kwargs
from .substep import kept_rung

AXIS_APART = math.radians(30.0)   # a principal axis within this of an axis already tried adds nothing new
MAX_AXES = 3


def trend_axes(points: np.ndarray, gravity=None) -> list[np.ndarray]:
    """Unit axes to try a trend along: gravity's (if given and non-zero), then the principal axes of `points` (largest
    spread first), each kept only if more than AXIS_APART off every axis kept before; at most MAX_AXES."""
    pts = np.asarray(points, np.float64)
    cand = []
    if gravity is not None and np.linalg.norm(gravity) > 0:
        cand.append(np.asarray(gravity, np.float64) / np.linalg.norm(gravity))
    if len(pts) >= 3:
        _, _, vt = np.linalg.svd(pts - pts.mean(0), full_matrices=False)
        cand.extend(vt)
    out: list[np.ndarray] = []
    for a in cand:
        if all(abs(float(a @ b)) < math.cos(AXIS_APART) for b in out):
            out.append(a)
        if len(out) >= MAX_AXES:
            break
    return out


def trend_weights(points: np.ndarray, axis: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
    """(P, 2) weights of the two ends' log E: particle i's log E = w[i] @ (a, b), t from 0 at the free particles' low
    end along `axis` to 1 at their high end (clipped: held particles beyond take the end's value)."""
    pts = np.asarray(points, np.float64)
    s = pts @ np.asarray(axis, np.float64)
    ref = s[np.asarray(free, bool)] if free is not None and np.asarray(free, bool).any() else s
    lo, hi = float(ref.min()), float(ref.max())
    t = np.clip((s - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return np.stack([1.0 - t, t], axis=1)


def trend_start(prob, mat, s, trajs, eff, total_fn, probes: int, log=None) -> dict:
    """Start the field (`mat`, on the level's basis) from the best log-linear trend along one axis when it lowers the
    total loss. `total_fn()`: the fit's total loss at the current field (a forward). Returns the parts start's kind of
    record: {"forwards", "used", "kind": "trend", "axis", "log_e" (the two ends), "loss0", "loss", "trend_gain"}."""
    from .select import PartProbe, part_refine

    out = {"forwards": 0, "used": False, "kind": "trend", "parts": 2}
    sim = getattr(prob, "sim", None)
    bound0 = getattr(sim, "e_bound", None)
    x0 = np.asarray(prob.x0, np.float64)
    free = ~np.asarray(prob.held_particles(), bool)
    grav = getattr(getattr(prob.scene, "settings", None), "gravity", None)
    axes = trend_axes(x0[free] if free.sum() >= 3 else x0, grav)
    if not axes:
        return out
    with torch.no_grad():
        le_now = mat.log_e().detach().cpu().numpy()
        nu = mat.poisson().detach()
    u = float(np.mean(le_now))
    start = np.array([u, u])
    tr = [t.detach() for t in trajs] if trajs else None
    kw = refine_kwargs(2, probes, cheap=(not forwards_are_cheap(prob)) and os.environ.get("PHYSINTERACT_TREND_UNCUT") != "1")
    step = float(kw["step"])
    lo, hi = mat.lo + 1e-3, mat.hi - 1e-3
    probes_of: list = []
    with kept_rung(prob):
        for ax in axes:
            f = PartProbe(prob, list(range(1, prob.T)), None, nu, tr, eff, batch=s.select_sweep_batch,
                          weights=trend_weights(x0, ax, free))
            f0 = f(start)
            best = f0
            for j in range(2):     # the simplex's two-sided vertices: an end x2, else x0.5
                e = np.eye(2)[j]
                v = f(np.clip(start + step * e, lo, hi))
                if v >= f0:
                    v = min(v, f(np.clip(start - step * e, lo, hi)))
                best = min(best, v)
            probes_of.append((best, f, ax))
        best_screen, f, ax = min(probes_of, key=lambda r: r[0])
        kw.pop("step")
        r = part_refine(f, start, lo, hi, kw.pop("evals"), step, **kw)   # (its first vertices: the screen's, cached)
    n_probes = sum(len(g.cache) for _, g, _ in probes_of)
    gain = f(start) - float(r["loss"])
    values = np.exp(trend_weights(x0, ax, free) @ np.asarray(r["log_e"]))
    taken = accept(prob, mat, total_fn, values, gain, f(start), bound0)
    out.update(forwards=n_probes + 2, axis=[float(v) for v in ax], log_e=[float(v) for v in r["log_e"]],
               sweep_loss=float(r["loss"]), trend_gain=float(gain), axes=len(axes), **taken)
    if log:
        ea, eb = (math.exp(v) for v in r["log_e"])
        log(f"trend start: log E linear along ({ax[0]:+.2f}, {ax[1]:+.2f}, {ax[2]:+.2f}) from {ea:.4g} to {eb:.4g} Pa "
            f"({len(axes)} axes, {n_probes} probes); on the bumps loss {taken['loss0']:.5f} -> {taken['loss']:.5f}: "
            f"{'started there' if taken['used'] else 'not taken'} (the trend's own gain {gain:.5f})")
    return out


__all__ = ["trend_start", "trend_axes", "trend_weights", "AXIS_APART", "MAX_AXES"]
