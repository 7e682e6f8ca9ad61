"""The bumps schedule's start from parts (FitSettings.parts_start: by default on CUDA, off on the CPU; #24, foam_bar).

Why: Adam moves each bump amplitude by about its learning rate per iteration. From the uniform E,
a two-part object whose parts sit 5x apart (foam_bar: 37.5 / 7.5 kPa) needs the soft part's bumps
to travel ~1.5 in the field's logit units; the suite's 20-iteration fit gives the finest level 15
iterations on a cosine from lr 0.1, ~0.8 in all, so it ends halfway down a loss that falls all the
way to the truth (docs/benchmarks/fit.md, "foam_bar stops short": the loss along the line from the
fit to the truth falls monotonically, and a fit started at the truth stays there). A Gauss-Newton
step on the 8 amplitudes did not help: the textured images' residuals are linear over a few pixels
only, so its quadratic model overshoots (same section).

What: before the finest level, the appearance candidate's parts (`select.part_candidates`: colour
clusters cut into connected parts, held particles joined to their neighbours) get one log E each by
a Nelder-Mead simplex from the uniform E (`select.part_refine`, forward passes only, the loss the
fit minimises; the path, nu and effects held). Their field, projected onto the level's bumps, is
where the level's Adam starts, if it renders better than the uniform start by at least half what the
parts' own field gained (KEEP_SHARE) and the simplex found anything at all; else nothing changes.
The simplex is cheap on the CPU (#24, 2026-11-27): at most 3 (m + 1) probes for m parts (`probe_budget`; 9 for
two, under the fit's cap), its first vertices two-sided (a part whose x2 renders worse is tried at x0.5: from
the uniform E one part softens and another stiffens), stopped when its last m + 1 probes bring no new best
(STALL_TOL); every probe under `substep.kept_rung` (the adaptive substep's rung left as found). On CUDA, where a
forward costs ~1 s, the simplex gets the cap's probes and no stall stop (`refine_kwargs(cheap=False)`): the cut
lost telephone_cable's start on the H200 (2026-11-27b), and an uncut run extends the cut one's path, so it finds at
least what the cut one found (docs/benchmarks/fit.md, "Why the cheap start lost telephone_cable").
Where the colours make no regions (one colour, or a pattern's interleaved classes: PARTS_MIN_SEPARATION), the parts
by shape take their place (`FitSettings.parts_by_shape`, 33rd session: `select.shape_candidate`, thin against thick
by the particles' local thickness, one E per class, also only where they lie apart): a glove's palm and fingers on the
H200 suite, MA 0.27 -> 0.87 (docs/benchmarks/fit.md, top). An object of one colour and one thickness has no such
parts, and its fit is unchanged. The probes are charged to the
level's iteration budget (a forward and a backward per iteration) when the start is taken; one not
taken leaves the fit exactly as without it (the field and the adaptive substep's rung restored), its probes'
time extra.
`FitSettings.parts_nest` (opt-in, 30th session): judged and held as the trend start is (fit/trend_start.py): the
simplex on the training frames, the parts' field kept only if it beats the uniform E on the held-back frames (one
coefficient per part more, and the sign test: `select.heldback_test`), then the fixed base of a nested field, exact.
Why: the projection onto the bumps is a least-squares fit in the field's logit, where a part the simplex pushed to the
range's top (the paper-size hemp_rope's 5.994e4 of [1e3, 6e4]) has a logit of ~8.3 that leaks into its neighbours
(a synthetic rope on 8 bumps: soft neighbours of such a part at 5.2e4, 6.4x their 8,227 Pa; at 4e4, 1.9e4); such
a start is refused for its projection, not for what the parts render. Opt-in in the "parts_first" order; in the
default "screened" order (`trend_start.starts_hook`, 31st session) the parts start is always nested, and kept also
where its held-back drop is clear though a short clip has too few frames for the sign test (`clear_drop`; the H200
suite: foam_bar 0.37 -> 0.975, bow_tie 0.57 -> 0.951; docs/benchmarks/fit.md, top).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import SimulationError
from .substep import kept_rung

PARTS_CLEAR_DROP = 0.25   # a nested parts start (`clear_drop`) is kept where its held-back drop is at least this share of the
                          # held-back loss, though lower on too few of a short clip's held-back frames for the sign test
                          # (all 4 of 4 at p <= 1/8): on the H200 suite (2026-11-29, development data) the sign rule refused
                          # foam_bar's parts (3 of 4 lower, 45% drop; MA 0.94 -> 0.37) and bow_tie's (2 of 4, 57%; 0.79 ->
                          # 0.57), and kept it off balloon_dog's (3 of 4, 6%). Parts only: a trend is the best of up to 3
                          # axes' searches, the parts one candidate fixed by the colours, and the sign rule is what
                          # refused balloon's wrong first axis (3 of 4 lower, 40% drop) for its right second one
PARTS_MIN_SEPARATION = 1.4  # the colour parts are tried only where they lie apart as regions (`regions.separation`): on the
                            # 12 suite scenes (2026-11-29, development data) the parts that were right scored 2.2-4.4
                            # (foam_bar 3.1, bow_tie 4.4, flower 3.8, telephone_cable 2.2; tow_rope's strap and hooks 2.1),
                            # the two colour classes of a pattern 0.25-0.92 (glove's checker 0.55, taken on held-back
                            # frames on the H200 and MA 0.27 -> 0.19; hemp_rope, toy_rope, balloon, balloon_dog,
                            # knit_cap, basketball). A layer between two others (~0.87) is refused with the patterns
KEEP_SHARE = 0.5   # the bumps must keep this share of the parts' gain: where their projection loses most of it
                   # (balloon_dog at grid 16 on the CPU: 4 parts 0.0301 -> 0.0142, on 8 bumps 0.0298), the basis
                   # cannot hold the parts and the start is a distorted one (it cost that fit MA 0.54 -> 0.24)
SIMPLEX_STEP = math.log(2.0)   # the first simplex: each part's E x 2 (the parts of a composite differ by ~2-10x)
PROBES_PER_DIM = 3             # the simplex's probes: at most this many per vertex of an m-part simplex (3 (m + 1):
                               # 9 for two parts, 12 for three), and never more than the fit's cap (`probes`)
STALL_TOL = 0.005              # ... and it stops once its last m + 1 probes (a simplex's worth) brought no new best
                               # this much (relative) below the best before them: the fit's plateau_tol on probes
                               # (the demo: 8 probes instead of 11 at 2 (m + 1), the same start; the cost: a narrow
                               # valley's descent may stop at ~75% of its gain, tests/test_parts_start_restore.py)


def stall_window(parts: int) -> int:
    """The simplex's stall window (probes without a new best) for `parts` parts."""
    return int(parts) + 1


def probe_budget(parts: int, cap: int) -> int:
    """The simplex's probe budget for `parts` parts under the fit's cap (`FitSettings.parts_start`)."""
    return max(min(int(cap), PROBES_PER_DIM * (int(parts) + 1)), int(parts) + 2)


EXTEND_CAP = 3        # the uncut simplex (CUDA) of the parts start goes on past its cap while still descending (`select.part_refine`'s
                     # `extend`), up to this many times the cap, until its last 2 (m + 1) probes bring no new best STALL_TOL below
                     # the best before them: foam_bar at 36 frames (the small capture, H200 and this VM alike) stopped at
                     # the cap of 20 at 3.21e4 / 1.056e4 Pa (truth 3.75e4 / 7.5e3), refused on the held-back frames (7 of 12
                     # lower), MA 0.483; the same simplex reached 3.80e4 / 7.79e3 by probe 35 (docs/benchmarks/fit.md, top)


def extend_window(parts: int) -> int:
    """The extended simplex's stall window: two simplices' worth of probes (a descent along a narrow valley brings a new
    best every few probes, not every m + 1: the window of `stall_window` would stop foam_bar's at the cap)."""
    return 2 * (int(parts) + 1)


def refine_kwargs(parts: int, cap: int, cheap: bool = True, extend: bool = False) -> dict:
    """`select.part_refine`'s arguments for the start's simplex over `parts` parts under the fit's cap. `cheap` (a
    forward is dear: the CPU): 3 (m + 1) probes and the stall stop (the demo's +83..104 CPU s cut to +16). Else (CUDA,
    a forward ~1 s): the cap's probes, no stall stop: the 12 suite scenes on the H200 (2026-11-27b) lost
    telephone_cable's start to the cut (MA 0.728 -> 0.228: its simplex stopped at [1, 2, 1]x, the 20-probe one found
    the coil's 0.86x after ~20 probes), and a longer run of the same simplex only extends the cut one's path.
    `extend` (uncut only): past the cap while still descending (EXTEND_CAP, `extend_window`)."""
    if not cheap:
        evals = max(int(cap), int(parts) + 2)
        kw = dict(evals=evals, step=SIMPLEX_STEP, two_sided=True)
        if extend:
            kw["extend"] = (EXTEND_CAP * evals, extend_window(parts), STALL_TOL)
        return kw
    return dict(evals=probe_budget(parts, cap), step=SIMPLEX_STEP, stall=(stall_window(parts), STALL_TOL), two_sided=True)


PARTS_START_CUDA = 20   # FitSettings.parts_start's default where the fit runs on CUDA (`default_probes`): the 12 suite
                        # scenes from true contacts on the H200 (code f114153, 2026-11-27c) gained with it and lost
                        # none (foam_bar 0.37 -> 0.94, telephone_cable 0.23 -> 0.73, flower 0.01 -> 0.31; mean 0.40 ->
                        # 0.51). Off on the CPU: the demo's fit +16-20 CPU s for no MA (docs/benchmarks/fit.md)


def default_probes(prob, asked: int | None) -> int:
    """The parts start's probe cap for `prob`: what the settings ask (`FitSettings.parts_start`), else
    PARTS_START_CUDA where the problem's forwards are cheap (CUDA) and 0 (off) on the CPU."""
    if asked is not None:
        return int(asked)
    return PARTS_START_CUDA if forwards_are_cheap(prob) else 0


def forwards_are_cheap(prob) -> bool:
    """Whether the problem's forwards are cheap enough for the cap's probes (its tensors on CUDA)."""
    return str(getattr(prob, "tdev", "cpu")).startswith("cuda")


def parts_start(prob, mat, s, trajs, eff, total_fn, probes: int, log=None, refine=None, nest: bool | None = None) -> dict:
    """Start the field (`mat`, on the level's basis) from the appearance parts' fitted E when it
    lowers the total loss. `total_fn()`: the fit's total loss at the current field (a forward).
    `refine(m)`: the simplex's `select.part_refine` arguments for m parts (default `refine_kwargs(m, probes)`; a
    benchmark's other rule, benchmarks/parts_simplex_trace.py). `nest`: judged on held-back frames and held as the
    nested base (None: `s.parts_nest`). Returns {"forwards", "used", "parts", "log_e", "loss0", "loss"}."""
    return PartsStart(prob, mat, s, trajs, eff, probes, log, refine, nest).run(total_fn)


class PartsStart:
    """The parts start in two steps, so that `trend_start.starts_hook` can rank it against the trend start before
    either's simplex runs (#24/#26): `screen()` probes the simplex's first vertices (each part x2, or / 2 where x2 renders
    no better: `select.first_vertices`, the very points `part_refine` probes first, so its simplex takes them from the
    probe's cache) and each part's contrast, `run(total_fn)` the rest (`parts_start`)."""

    def __init__(self, prob, mat, s, trajs, eff, probes: int, log=None, refine=None, nest: bool | None = None):
        from .regions import separation
        from .select import PartProbe, part_candidates, problem_holdout

        self.prob, self.mat, self.s, self.eff, self.log = prob, mat, s, eff, log
        self.bound0 = getattr(getattr(prob, "sim", None), "e_bound", None)   # the adaptive substep's rung before the probes
                                                                              # (restored if not taken)
        cands = [c for c in part_candidates(prob, s, None) if c["kind"] == "appearance" and c["parts"] > 1]
        self.screened = None
        self.separation = None    # regions.separation of the parts tried or refused (the colour's, else the shape's)
        self.by = "colour"        # what the parts are: "colour" (the appearance's), "thickness" (the shape's: `shape_parts`)
        self.thickness_m = ()     # the shape parts' median local thicknesses (thin, thick), metres
        labels = cands[0]["labels"] if cands else None
        x0 = getattr(prob, "x0", None)
        if labels is not None and x0 is not None:
            # a pattern's colour classes (a checker, stripes) are not regions of a material: each is spread over the
            # whole object, interleaved with the other, and the data can prefer such a split for the wrong reasons
            self.separation = separation(np.asarray(x0), np.asarray(labels))
            if self.separation < PARTS_MIN_SEPARATION:
                labels = None
                if log:
                    log(f"parts start: the colour parts are interleaved (separation {self.separation:.2f} < "
                        f"{PARTS_MIN_SEPARATION}: a pattern, not regions); not tried")
        # (FitSettings.parts_by_shape defaults True; a settings object without the field, e.g. a test's, has none)
        if labels is None and x0 is not None and bool(getattr(s, "parts_by_shape", False)):
            labels = self.shape_parts(prob, s, log)
        self.ready = labels is not None
        if not self.ready:
            return
        self.labels = labels
        self.m = int(self.labels.max()) + 1
        with torch.no_grad():
            self.le_now = mat.log_e().detach().cpu().numpy()
            self.nu = mat.poisson().detach()
        self.tr = [t.detach() for t in trajs] if trajs else None
        self.nest = bool(getattr(s, "parts_nest", False)) if nest is None else bool(nest)
        self.frames, self.val = list(range(1, prob.T)), []
        if self.nest:   # judged as the trend start is: the simplex on the training frames, the held-back ones decide
            train, val = problem_holdout(prob, s)
            self.frames, self.val = (train if val else self.frames), val
        self.f = PartProbe(prob, self.frames, self.labels, self.nu, self.tr, eff, batch=s.select_sweep_batch)
        self.start = np.array([float(np.mean(self.le_now[self.labels == j])) for j in range(self.m)])
        kw = dict(refine(self.m)) if refine is not None else refine_kwargs(self.m, probes,
                                                                            cheap=not forwards_are_cheap(prob), extend=True)
        self.evals, self.step, self.kw = kw.pop("evals"), kw.pop("step"), kw
        self.lo, self.hi = mat.lo + 1e-3, mat.hi - 1e-3

    def shape_parts(self, prob, s, log=None):
        """The parts by thickness (`select.shape_candidate`) where they lie apart as regions (`regions.separation` at
        least PARTS_MIN_SEPARATION), else None; said in the log either way."""
        from .regions import separation
        from .select import shape_candidate

        c = shape_candidate(prob, s)
        if c is None:
            return None
        sep = separation(np.asarray(prob.x0), np.asarray(c["labels"]))
        thin, thick = c["thickness_m"]
        if sep < PARTS_MIN_SEPARATION:
            if log:
                log(f"parts start: the thin ({1e3 * thin:.0f} mm) and thick ({1e3 * thick:.0f} mm) parts are interleaved "
                    f"(separation {sep:.2f} < {PARTS_MIN_SEPARATION}); not tried")
            return None
        self.by, self.thickness_m, self.separation = "thickness", (thin, thick), sep
        if log:
            log(f"parts start: the colours make no regions; {c['parts']} parts by thickness (thin {1e3 * thin:.0f} mm, "
                f"thick {1e3 * thick:.0f} mm, separation {sep:.2f})")
        return c["labels"]

    def screen(self) -> float:
        """The lowest loss among the start, the simplex's first vertices (cached in the probe: the simplex takes them
        from there) and each part's contrast (the part x2, the others / 2: m probes more), inf where there are no parts.
        The contrasts are the trend screen's tilts for parts: one part alone moved by x2 renders a step between two
        parts 5x apart worse than a trend tilted x2 both ways does, so a screen of single moves would rank a two-part
        object's trend first (tests/test_trend_start.py)."""
        from .select import first_vertices

        if not self.ready:
            return float("inf")
        with kept_rung(self.prob):
            vals = first_vertices(self.f, self.start, self.step, self.lo, self.hi, two_sided=self.kw.get("two_sided", False))
            if self.m >= 2 and math.isfinite(vals[0]):
                for j in range(self.m):
                    d = np.full(self.m, -self.step)
                    d[j] = self.step
                    vals.append(self.f(np.clip(self.start + d, self.lo, self.hi)))
        self.screened = float(min(vals))
        return self.screened

    def run(self, total_fn) -> dict:
        from .select import heldback_test, part_refine

        prob, mat, s, log = self.prob, self.mat, self.s, self.log
        out = {"forwards": 0, "used": False, "parts": 0, "by": self.by}
        if self.by == "thickness":
            out["thickness_m"] = [float(v) for v in self.thickness_m]
        if not self.ready:
            if self.separation is not None:      # interleaved parts: said so when it was built
                out["separation"] = self.separation
            elif log:
                log("parts start: the object's colours make one part"
                    + (" and its shape one thickness" if getattr(self.s, "parts_by_shape", False) else "")
                    + "; the uniform start stays")
            return out
        m, f, start, labels, bound0 = self.m, self.f, self.start, self.labels, self.bound0
        with kept_rung(prob):      # the probes leave the substep's rung as they found it (each probe does too)
            r = part_refine(f, start, self.lo, self.hi, self.evals, self.step, **self.kw)
        out.update(parts=m, forwards=len(f.cache) - getattr(f, "given", 0), log_e=[float(v) for v in r["log_e"]], sweep_loss=float(r["loss"]),
                   stalled=bool(r.get("stalled", False)), extended=int(r.get("extended", 0)))
        if self.screened is not None:
            out["screen_loss"] = self.screened
        gain_parts = f(start) - float(r["loss"])          # what the parts' own field gained (reconstruction)
        out["parts_gain"] = gain_parts
        values = np.exp(np.asarray(r["log_e"]))[labels]
        nest, frames = self.nest, self.frames
        if nest and self.val:
            hb = heldback_test(prob, s, np.exp(self.le_now), values, m - 1, self.nu, self.tr, self.eff, self.val)
            keep, why = clear_drop(hb)
            out.update(heldback=why, sign_p=hb["sign_p"], forwards=out["forwards"] + 2, nested=True)
            if not keep:
                restore_rung(prob, bound0)
                out.update(used=False, loss0=float("nan"), loss=float("nan"))
                if log:
                    log(f"parts start: {m} parts by {self.by} at E " + ", ".join(f"{math.exp(v):.4g}" for v in r["log_e"])
                        + f" Pa (simplex on {len(frames)} frames, {len(f.cache)} probes{_past_cap(out)}); {why}; not taken")
                return out
        taken = accept(prob, mat, total_fn, values, gain_parts, f(start), bound0, nest=nest)
        out["forwards"] += 2
        out.update(taken)
        loss0, loss1 = taken["loss0"], taken["loss"]
        if log:
            es = ", ".join(f"{math.exp(v):.4g}" for v in r["log_e"])
            log(f"parts start: {m} parts by {self.by} at E {es} Pa (simplex, {len(f.cache)} probes{_past_cap(out)}"
                f"{', stalled' if out['stalled'] and not out['extended'] else ''}); {'nested' if nest else 'on the bumps'} "
                f"loss {loss0:.5f} -> {loss1:.5f}: {'started there' if out['used'] else 'not taken'}"
                f" (the parts' own gain {gain_parts:.5f})")
        return out


def _past_cap(rec: dict) -> str:
    return f", {rec['extended']} past the cap while still descending" if rec.get("extended") else ""


def clear_drop(hb: dict) -> tuple[bool, str]:
    """A nested parts start's held-back verdict from `select.heldback_test`'s record: kept where the test keeps it, or
    where its field's mean drop beats the price of its coefficients and is at least PARTS_CLEAR_DROP of the held-back
    loss, however many of the (few) frames it is lower on. Returns (keep, why)."""
    rule = hb.get("rule") or {}
    drop, loss0 = rule.get("mean_drop"), rule.get("loss0")
    if hb["keep"] or drop is None or not loss0 or not math.isfinite(float(drop)):
        return bool(hb["keep"]), hb["why"]
    clear = bool(drop > rule.get("penalty", 0.0) and drop >= PARTS_CLEAR_DROP * loss0)
    share = drop / loss0
    return clear, hb["why"] + (f"; but {share:.0%} of the held-back loss >= {PARTS_CLEAR_DROP:.0%}: kept" if clear else "")


def accept(prob, mat, total_fn, values: np.ndarray, gain: float, ref: float, bound0=None, nest: bool = False) -> dict:
    """Put the per-particle E `values` (a start's own field, which gained `gain` over its start's loss `ref`) on
    `mat`'s basis (`nest`: as the fixed base of a nested field, the bumps' offsets zero: exact) and keep it if the
    total loss falls by at least KEEP_SHARE of `gain`; else restore the field and the adaptive substep's rung
    (`bound0`, as before the probes). Returns {"used", "loss0", "loss"}."""
    theta0, base0 = mat.theta.detach().clone(), getattr(mat, "base", None)
    try:
        loss0 = float(total_fn())
        if nest:
            mat.set_base(np.asarray(values, np.float64))
        else:
            mat.set_values(np.asarray(values, np.float64))
        loss1 = float(total_fn())
    except SimulationError:
        loss0, loss1 = float("nan"), float("inf")
    # a search that found nothing (gain within the plateau tolerance: the H200's toy_rope, tow_rope and basketball
    # all ended at their start, 0.00000) gives no start, though the bumps' projection of the uniform E may render a
    # hair better: "taken", it was charged 6 of the level's iterations for nothing (basketball MA 0.294 -> 0.290)
    used = bool(gain > STALL_TOL * abs(ref) and loss1 < loss0 and (loss0 - loss1) >= KEEP_SHARE * gain)
    if not used:
        if nest:
            mat.base = base0
        with torch.no_grad():
            mat.theta = theta0.clone().requires_grad_(True)
        restore_rung(prob, bound0)
    return {"used": used, "loss0": loss0, "loss": loss1}


def restore_rung(prob, bound0) -> None:
    """Put the adaptive substep back on the rung `bound0` it had before a start's probes: they simulated stiffer
    fields, and the substep's hysteresis may keep their rung, so the fit would go on at another step (the H200's
    hemp_rope: a start not taken, MA 0.801 -> 0.485)."""
    sim = getattr(prob, "sim", None)
    if bound0 is not None and getattr(sim, "adaptive", False) and sim.e_bound != bound0:
        sim._use_bound(bound0)


def parts_start_hook(probes: int):
    """`fit_bumps(before_finest=...)`: the parts start with at most `probes` probes (with the trend start after it:
    `trend_start.starts_hook`)."""
    def hook(prob, mat, s, trajs, eff, total_fn, log=None):
        return parts_start(prob, mat, s, trajs, eff, total_fn, probes, log)
    return hook


__all__ = ["parts_start", "PartsStart", "clear_drop", "PARTS_CLEAR_DROP", "PARTS_MIN_SEPARATION", "accept", "restore_rung", "parts_start_hook", "default_probes", "PARTS_START_CUDA", "forwards_are_cheap", "probe_budget", "refine_kwargs", "stall_window", "SIMPLEX_STEP", "PROBES_PER_DIM", "STALL_TOL", "EXTEND_CAP", "extend_window"]
