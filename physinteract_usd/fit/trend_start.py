"""The bumps schedule's start from a trend: log E linear along one axis of the object (FitSettings.trend_start; #24).

Why: an object graded along its length (a balloon's rubber thin at the bottom, a rope stiff at the top and frayed at
the end) is fitted from the uniform E, which sits near its stiff end's value where the motion is dominated by it (the
balloon: uniform optimum 3.1e4 Pa against 3.75e4 / 7.5e3 at its ends). From there the gradient at the soft end points
*stiffer* (docs/benchmarks/fit.md, "Rprop ... refuted"): the bumps' Adam, Rprop, Gauss-Newton, scaled uniform starts and a
finer grid all stayed in that basin (soft end 2.5-3.1x), while the truth's own field renders better (0.0087 against
0.0100). The parts start (`parts_start.py`) cannot help: such an object has one colour.

What: before the finest level (ordered with the parts start by their screens: `starts_hook`), a field whose log E runs linearly from one end of
the object to the other, log E = (1 - t) a + t b with t in [0, 1] the particle's place along the axis (free particles'
extent), is searched along each candidate axis: gravity's and the free particles' principal axes more than
AXIS_APART off the ones before (at most 3). The search sees the training frames only (`select.holdout_frames`, as the
select schedule and the guard hold frames back). Each axis is first screened (`screen_moves`: tilted both ways about
its middle, the mean held, and each end alone x2 or / 2: 4-6 probes); the axes are ranked by their best screened
point, and the best one's simplex (`select.part_refine`, the parts start's rule) starts there. Either screen alone
lost a scene on the H200 (2026-11-28): ends alone picked a trend across the paper-size hemp_rope (its true trend
pivots about the middle), tilts alone a trend across the balloon (its true trend pivots about the stiff neck, where the
uniform E sits). The trend must then beat the uniform E on the held-back
frames by more than its one added coefficient predicts (`select.select_rule`; 2 forwards) and on so many of them
that a coin would not (sign test, SIGN_P): a slope that fits the training frames' noise, or one or two frames the
uniform E misses, does not carry over (the H200's small hemp_rope: a trend across the rope gaining 2%, MA 0.80 ->
0.24, before the held-back test). Refused, the next axis by its screen gets its simplex (at most TRIES). Kept, it becomes the fixed base of a nested field (`MaterialField.set_base`), the
level's bumps adding offsets from zero, under the parts start's acceptance rule (`parts_start.accept`: the total
loss must fall by KEEP_SHARE of the trend's gain). Not projected onto the bumps: they are near piecewise constant
(width 0.6 of their spacing) and hold a ramp as a staircase (the CPU's balloon at grid 24: a 7x trend at 0.0081
became 0.0138 on them, against 0.0184 uniform: refused). Else nothing changes (the field and the substep's rung
restored).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from .parts_start import accept, forwards_are_cheap, parts_start, refine_kwargs, restore_rung
from .select import SIGN_P, sign_test_p  # noqa: F401  (re-exported: the held-back test's sign rule)
from .substep import kept_rung

TREND_START_CUDA = 20   # FitSettings.trend_start's default where the fit runs on CUDA (`default_trend_probes`): the 12 named
                        # suite scenes from true contacts on 4 x H200 (2026-11-28, code df450ef): balloon 0.345 -> 1.000,
                        # hemp_rope 0.801 -> 0.959, glove 0.257 -> 0.272, knit_cap 0.412 -> 0.147, the other 8 unchanged;
                        # the paper-size hemp_rope 0.821 -> 1.000. Off on the CPU, as the parts start
TRIES = 2           # the axes (best screened first) whose simplex may be tried until one passes the held-back test
# select.SIGN_P (0.125): the trend lower on so many held-back frames that a fair coin would do so with p <= this
# (one-sided sign test: all of three, all 4 of a 14-frame clip's, 11 of 15): a slope bought by one or two frames
# the uniform E misses is no trend (the H200's paper-size hemp_rope: 8 of 15 lower, a trend
# across the rope of 0.6% taken, and the iterations it was charged cost the fit MA 0.82 -> 0.23)
AXIS_APART = math.radians(30.0)   # a principal axis within this of an axis already tried adds nothing new
MAX_AXES = 3


def default_trend_probes(prob, asked: int | None) -> int:
    """The trend start's probe cap for `prob`: what the settings ask, else TREND_START_CUDA where the problem's forwards
    are cheap (CUDA) and 0 (off) on the CPU."""
    if asked is not None:
        return int(asked)
    return TREND_START_CUDA if forwards_are_cheap(prob) else 0


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


def screen_moves(f, u0: np.ndarray, step: float, lo: float, hi: float) -> list[tuple]:
    """An axis' screen, as (a, b) moves in units of `step` from the uniform (u, u): tilted both ways about its middle
    ((1, -1), (-1, 1)), and each end alone moved x2, or / 2 where x2 renders no better than the uniform (the parts
    simplex's two-sided vertices). The tilt holds the mean the uniform E was fitted to; an end alone pivots about the
    other end, where the uniform E is pinned when that end dominates the motion (the balloon's neck)."""
    moves: list[tuple] = [(1.0, -1.0), (-1.0, 1.0)]
    f0 = f(u0)
    for j in range(2):
        d = tuple(1.0 if k == j else 0.0 for k in range(2))
        moves.append(d)
        if f(np.clip(u0 + step * np.array(d), lo, hi)) >= f0:
            moves.append(tuple(-v for v in d))
    return moves


def trend_start(prob, mat, s, trajs, eff, total_fn, probes: int, log=None) -> dict:
    """Start the field (`mat`, nested on the trend: `MaterialField.set_base`) from the best log-linear trend along one
    axis when it renders better on held-back frames and lowers the total loss. `total_fn()`: the fit's total loss at
    the current field (a forward). Returns the parts start's kind of record: {"forwards", "used", "kind": "trend",
    "axis", "log_e" (the two ends), "loss0", "loss", "trend_gain", "heldback"}."""
    return TrendStart(prob, mat, s, trajs, eff, probes, log).run(total_fn)


class TrendStart:
    """The trend start in two steps (as `parts_start.PartsStart`): `screen()` screens every axis (the module doc) and
    returns the best screened loss, `run(total_fn)` the best axes' simplex, the held-back test and the acceptance."""

    def __init__(self, prob, mat, s, trajs, eff, probes: int, log=None):
        from .select import PartProbe, problem_holdout

        self.prob, self.mat, self.s, self.eff, self.log = prob, mat, s, eff, log
        self.bound0 = getattr(getattr(prob, "sim", None), "e_bound", None)
        self.x0 = np.asarray(prob.x0, np.float64)
        self.free = ~np.asarray(prob.held_particles(), bool)
        grav = getattr(getattr(prob.scene, "settings", None), "gravity", None)
        self.axes = trend_axes(self.x0[self.free] if self.free.sum() >= 3 else self.x0, grav)
        self.train, self.val = problem_holdout(prob, s)
        self.ready = bool(self.axes and self.val)
        self.screened: list | None = None
        if not self.ready:
            return
        with torch.no_grad():
            le_now = mat.log_e().detach().cpu().numpy()
            self.nu = mat.poisson().detach()
        self.u = float(np.mean(le_now))
        self.tr = [t.detach() for t in trajs] if trajs else None
        # the simplex uncut on every device (the parts start cuts it on the CPU for the demo's time; the trend start is
        # opt-in there): cut, it stopped at a 2% gain on the tiny graded bar (tests/test_trend_start_bar.py) and at a 2x
        # trend on the CPU's balloon, where the GPU's uncut one found 5x
        kw = refine_kwargs(2, probes, cheap=False, extend=bool(getattr(s, "trend_extend", False)))
        self.step, self.evals, self.kw = float(kw.pop("step")), int(kw.pop("evals")), kw
        self.lo, self.hi = mat.lo + 1e-3, mat.hi - 1e-3
        self.u0 = np.array([self.u, self.u])
        self.fs = [PartProbe(prob, self.train, None, self.nu, self.tr, eff, batch=s.select_sweep_batch,
                             weights=trend_weights(self.x0, ax, self.free)) for ax in self.axes]

    def remember_uniform(self, value: float) -> None:
        """The uniform field's loss on the training frames, probed elsewhere (the parts start's screen): not run again."""
        if self.ready:
            self.fs[0].remember(self.u0, value)

    def screen(self) -> float:
        """Every axis screened (`screen_moves`); the best screened loss (inf: nothing to screen)."""
        if not self.ready:
            return float("inf")
        if self.screened is None:
            screened: list = []
            lo, hi, step, u0 = self.lo, self.hi, self.step, self.u0
            with kept_rung(self.prob):
                for ax, f in zip(self.axes, self.fs):
                    # (the screens one probe at a time: as tiled copies in groups of one rung each, the paper row's trend
                    # start took 25.0 s against 22.1 alone, same lease, same stage: 21k-particle copies cost their sum; #26)
                    if screened:    # the uniform E is the same field on every axis: probed once (#26: 2 of 3 axes' forwards)
                        f.remember(u0, screened[0][2](u0))
                    pts = [u0] + [np.clip(u0 + step * np.array(d), lo, hi) for d in screen_moves(f, u0, step, lo, hi)]
                    vals = [f(p) for p in pts]
                    i = int(np.argmin(vals))
                    screened.append((vals[i], pts[i], f, ax))
            screened.sort(key=lambda r: r[0])
            self.screened = screened
        return float(self.screened[0][0])

    @property
    def forwards(self) -> int:
        return sum(f.forwards for f in self.fs) if self.ready else 0

    def run(self, total_fn) -> dict:
        from .select import heldback_test, part_refine

        prob, mat, s, log = self.prob, self.mat, self.s, self.log
        out = {"forwards": 0, "used": False, "kind": "trend", "parts": 2}
        if not self.ready:
            if log:
                log("trend start: " + ("no axis" if not self.axes else "too few frames to hold any back") + "; not tried")
            return out
        self.screen()
        u0, lo, hi, step = self.u0, self.lo, self.hi, self.step
        screened = self.screened
        f0 = screened[0][2](u0)
        rec = None
        for rank, (v_screen, p_best, f, ax) in enumerate(screened[:TRIES]):
            if not v_screen < f0:
                break                                   # this axis' screen found nothing below the uniform E
            with kept_rung(prob):
                r = part_refine(f, p_best, lo, hi, self.evals, step, **self.kw)
            w = f.weights                           # the axis' weights its probe was built with
            ends = np.asarray(r["log_e"], np.float64)
            gain = f0 - float(r["loss"])
            values = np.exp(w @ ends)
            # the two fields on the held-back frames at one substep (the stiffer one's); one coefficient more (the slope)
            hb = heldback_test(prob, s, np.full(len(values), math.exp(self.u)), values, 1, self.nu, self.tr, self.eff,
                               self.val)
            keep, why, p_sign = hb["keep"], hb["why"], hb["sign_p"]
            rec = dict(axis=[float(v) for v in ax], log_e=[float(v) for v in ends], sweep_loss=float(r["loss"]),
                       trend_gain=float(gain), heldback=why, sign_p=p_sign, rank=rank, keep=keep, values=values,
                       screen_loss=float(v_screen), extended=int(r.get("extended", 0)))
            if log:
                log(f"trend start: log E linear along ({ax[0]:+.2f}, {ax[1]:+.2f}, {ax[2]:+.2f}) (axis {rank + 1} of "
                    f"{len(self.axes)} by its screen) from {math.exp(ends[0]):.4g} to {math.exp(ends[1]):.4g} Pa (on "
                    f"{len(self.train)} frames, its gain {gain:.5f}" + (f", {rec['extended']} probes past the cap while "
                                                                        "still descending" if rec["extended"] else "")
                    + f"); {why}" + ("" if keep else "; not taken"))
            if keep:
                break
        out.update(forwards=self.forwards + 2 * (0 if rec is None else rec["rank"] + 1), axes=len(self.axes))
        taken = {"used": False, "loss0": float("nan"), "loss": float("nan")}
        if rec is not None:
            out.update({k: v for k, v in rec.items() if k not in ("keep", "values")})
            if rec["keep"]:
                taken = accept(prob, mat, total_fn, rec["values"], rec["trend_gain"], f0, self.bound0, nest=True)
                out["forwards"] += 2
                if log:
                    log(f"trend start: on the bumps loss {taken['loss0']:.5f} -> {taken['loss']:.5f}: "
                        f"{'started there' if taken['used'] else 'not taken'}")
        elif log:
            log("trend start: no axis' screen renders better than the uniform E; not taken")
        if not taken["used"]:
            restore_rung(prob, self.bound0)
        out.update(taken)
        return out


def same_field_once(mat, total_fn):
    """`total_fn` remembered for the field it was last called at (`mat`'s coefficients and base, bitwise): a start
    not taken restores the field exactly (and the substep's rung), so the next start's reference loss is the same
    forward's (#26: one forward of the paper row's ~60 probes)."""
    seen: dict = {}

    def key():
        base = getattr(mat, "base", None)
        return (mat.theta.detach().cpu().numpy().tobytes(),
                None if base is None else base.detach().cpu().numpy().tobytes())

    def total():
        k = key()
        if k not in seen:
            seen.clear()
            seen[k] = float(total_fn())
        return seen[k]
    return total


STARTS_ORDERS = ("screened", "parts_first")


def starts_hook(parts: int, trend: int, order: str = "parts_first"):
    """`fit_bumps(before_finest=...)`: the parts start with at most `parts` probes (0: none) and the trend start with at
    most `trend` (0: none), the second only where the first was not taken. `order` (`FitSettings.starts_order`):
    "parts_first", the parts start (projected onto the bumps, or nested with `parts_nest`) then the trend start (the
    29th session's); "screened", both screened first on the same training frames (the parts simplex's first vertices,
    the trend's axis screens), the parts start nested (no projection onto the bumps: `parts_start` module doc), and the
    one whose screen renders lower runs its simplex first (#24 / #26: the paper-size hemp_rope's refused parts simplex
    was ~12 s of its fit, and a parts start refused for its projection let the trend start run by accident).
    The record is the one taken (else the last tried), its "forwards" every probe's; the fit keeps it as its model's
    "parts_start" (the key older versions wrote), "kind": "trend" for the trend start's, the other start's own record
    under its "parts_start" / "trend_start", with "order" and "screens" where screened."""
    if order not in STARTS_ORDERS:
        raise ValueError(f"starts_order must be one of {', '.join(STARTS_ORDERS)}, not {order!r}")

    def timed(start, total_fn):
        t0 = time.perf_counter()
        r = start.run(total_fn)
        r["seconds"] = round(time.perf_counter() - t0, 3) + getattr(start, "screen_seconds", 0.0)
        return r

    def hook(prob, mat, s, trajs, eff, total_fn, log=None):
        from .parts_start import PartsStart

        total_fn = same_field_once(mat, total_fn)   # both starts' accept test the uniform start's loss: one forward
        if order == "parts_first" or parts <= 0 or trend <= 0:
            rec = {"forwards": 0, "used": False, "parts": 0}
            if parts > 0:
                rec = timed(PartsStart(prob, mat, s, trajs, eff, parts, log), total_fn)
            if trend > 0 and not rec["used"]:
                t = timed(TrendStart(prob, mat, s, trajs, eff, trend, log), total_fn)
                t["forwards"] += rec["forwards"]
                if parts > 0:
                    t["parts_start"] = {k: v for k, v in rec.items() if k != "forwards"}
                rec = t
            return rec
        starts = {"parts": PartsStart(prob, mat, s, trajs, eff, parts, log, nest=True),
                  "trend": TrendStart(prob, mat, s, trajs, eff, trend, log)}
        screens = {}
        for name, st in starts.items():
            t0 = time.perf_counter()
            if name == "trend" and "parts" in screens and _same_uniform(starts["parts"], st):
                st.remember_uniform(starts["parts"].f(starts["parts"].start))   # the same field, the same frames
            screens[name] = st.screen()
            st.screen_seconds = round(time.perf_counter() - t0, 3)
        order_now = sorted((n for n in screens if math.isfinite(screens[n])), key=lambda n: (screens[n], n != "parts"))
        if log:
            log("starts: screened on the training frames, " + ", ".join(
                f"{n} {screens[n]:.5f}" for n in starts) + (f"; {order_now[0]} first" if order_now else "; neither"))
        tried: dict = {}
        for name in order_now:
            tried[name] = timed(starts[name], total_fn)
            if tried[name]["used"]:
                break
        if not tried:
            return {"forwards": sum(_screen_forwards(st) for st in starts.values()), "used": False, "parts": 0,
                    "order": order_now, "screens": screens}
        last = list(tried)[-1]
        rec = tried[last]
        rec["forwards"] = sum(r["forwards"] for r in tried.values()) + sum(
            _screen_forwards(starts[n]) for n in starts if n not in tried)
        for n, r in tried.items():
            if n != last:
                rec[f"{n}_start"] = {k: v for k, v in r.items() if k != "forwards"}
        rec.update(order=order_now, screens=screens)
        return rec
    return hook


def _same_uniform(parts, trend) -> bool:
    """Whether the parts start's start and the trend start's uniform are one field on the same frames (the field was
    uniform, as it is after the uniform level: every part's mean log E is the trend's)."""
    return (parts.ready and trend.ready and list(parts.frames) == list(trend.train)
            and bool(np.all(np.abs(parts.start - trend.u) <= 1e-9)))


def _screen_forwards(start) -> int:
    """The forwards a start's screen ran (a start never run past its screen)."""
    if not getattr(start, "ready", False):
        return 0
    f = getattr(start, "f", None)
    return (len(f.cache) - getattr(f, "given", 0)) if f is not None else int(getattr(start, "forwards", 0))


__all__ = ["trend_start", "TrendStart", "STARTS_ORDERS", "starts_hook", "same_field_once", "default_trend_probes", "TREND_START_CUDA", "screen_moves", "sign_test_p", "TRIES", "SIGN_P", "trend_axes", "trend_weights", "AXIS_APART", "MAX_AXES"]
