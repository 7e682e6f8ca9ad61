"""`diagnose`: rank what the stage's fitted model lacks (docs/diagnose.md).

Reads the stage's current fit version (its E field, Poisson's ratio, fitted trajectories and
effects), its video, silhouettes and hand masks; builds the fit's problem with every candidate
effect switched on at its null value (a superset simulator); runs the projected score tests
(`diagnose.diagnose_problem`), refits the top candidates briefly (`diagnose.refit`), words the
evidence, and stores the diagnosis on the fit layer under the version's report
(`usd.diagnosis_io`). Returns the design's JSON: {"verdict", "reason", "candidates": [{"effect",
"score", "predicted_loss_drop", "realized_loss_drop", "estimate", "evidence"}]} plus what was
tested ("tested"), the loss and its floor, and the cost."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from .jsonsafe import json_safe
from ..diagnose import CANDIDATES, PHYSICAL, BaseState, DiagnoseSettings, conclude, describe, diagnose_problem
from ..diagnose.refit import judge_on_rest, judge_probe, refit_effect
from ..errors import InputError, SimulationError
from .adapters import effects_with_fitted, load_observations, nuisance_effects, read_scene, stage_contacts


def superset_effects(sd, present: dict) -> dict:
    """The stage's effects (with their fitted values) plus every other effect at its null: no
    damping, a yield stress never reached, a ground plane a metre below the grid, no Maxwell branch."""
    out = {e: dict(p) for e, p in present.items()}
    out.setdefault("damping", {"coefficient": 0.0})
    # a yield stress no stress reaches (the adjoint of tau_Y = inf is not finite)
    out.setdefault("plasticity", {"yieldStress": 1e6 * float(sd.settings.youngs_max)})
    out.setdefault("ground", {"height": float(sd.settings.domain_min[1]) - 1.0, "friction": 0.5})
    out.setdefault("viscoelasticity", {"modulus": 0.0, "relaxationTime": 0.1})
    return out


def _best_start(prob, base, settings, starts: int, iterations: int, log):
    """The base refitted briefly from `starts` starts (`diagnose`); returns (the base to score
    against, a JSON-able account {"starts": [{"factor", "loss", "median_E"}], "base_loss", "chosen"
    (the factor of the start scored against; None: the stage's fit as it is), "local_minimum",
    "not_converged", "note", "seconds"})."""
    import torch

    from ..diagnose import BaseState
    from ..diagnose.refit import refit_base
    from ..diagnose.residual import ImageResidual, loss

    out = {"starts": [], "base_loss": None, "chosen": None, "local_minimum": False, "not_converged": False,
           "note": "", "seconds": 0.0}
    if starts <= 1:
        return base, out
    t0 = time.perf_counter()
    res = ImageResidual(prob, max_pixels=settings.max_pixels)
    sim = prob.sim

    def at_rung(E, nu) -> float:
        """The diagnosis's loss of a field at the substep its own stiffness takes (the simulator's
        adaptive substep otherwise depends on the fields simulated before: not comparable)."""
        if getattr(sim, "adaptive", False):
            b = sim.bound_for(float(E.max()))
            if b != sim.e_bound:
                sim._use_bound(b)
        try:
            with torch.no_grad():
                x, F = prob.simulate(E, nu, None, effects=base.effects)
            return loss(res(x, F))
        except SimulationError:
            return math.inf

    thr = 1.0 - settings.min_relative_drop
    refits = []
    if BATCHED_REFITS == "always" or (BATCHED_REFITS == "cuda" and str(prob.tdev).startswith("cuda")):
        # on a GPU the starts run in lockstep, one tiled rollout per iteration (fit/batched.py; the
        # same steps as refit_base's, tests/test_fit_batched.py)
        from ..fit.batched import refit_regions_batched

        labels = base.labels if base.labels is not None else np.zeros(len(prob.x0), np.int64)
        E0, st = base.E.detach().cpu().numpy(), prob.scene.settings
        les = [[math.log(float(np.clip(f * np.median(E0[labels == r]), 1.001 * st.youngs_min, 0.999 * st.youngs_max)))
                for r in range(int(labels.max()) + 1)] for f in START_FACTORS[:starts]]
        log(f"base refits from the E field x {', '.join(f'{f:g}' for f in START_FACTORS[:starts])} "
            f"({iterations} iterations, batched)")
        for f, g in zip(START_FACTORS[:starts], refit_regions_batched(prob, labels, les, float(base.nu.median()),
                                                                       iterations, log=log)):
            refits.append({"factor": float(f), "E": g["E"], "nu": g["nu"], "loss": math.inf,
                           "fit_loss": g["fit_loss"], **({"note": f"refit {g['note']}"} if "note" in g else {})})
    if not refits:
        # on the CPU each start in its own process where the machine has the cores (`workers.fork_map`)
        from ..workers import fork_map

        def one(f):
            log(f"base refit from the E field x {f:g} ({iterations} iterations)")
            return refit_base(prob, base, f, iterations=iterations, res=res)

        refits = fork_map(one, START_FACTORS[:starts], device=prob.tdev, log=log)
    best, own = None, None
    for r in refits:             # judged after all of them, each at its own substep
        if r["E"] is not None:
            r["loss"] = at_rung(r["E"], r["nu"])
        out["starts"].append({"factor": r["factor"], "loss": r["loss"],
                              "median_E": None if r["E"] is None else float(r["E"].median()),
                              **({"note": r["note"]} if "note" in r else {})})
        if r["factor"] == 1.0:
            own = r
    L0 = at_rung(base.E, base.nu)         # last: the simulator stays at the stage's base's substep
    out["base_loss"] = L0
    for r in refits:
        if r["E"] is not None and r["loss"] < L0 * thr and (best is None or r["loss"] < best["loss"]):
            best = r
    out["seconds"] = time.perf_counter() - t0
    if best is None:
        return base, out
    at_rung(best["E"], best["nu"])        # the simulator at the chosen base's substep
    local = best["factor"] != 1.0 and (own is None or best["loss"] < own["loss"] * thr)
    out.update(chosen=best["factor"], local_minimum=bool(local), not_converged=not local)
    how = (f"{L0:.3g} -> {best['loss']:.3g}, {100 * (1 - best['loss'] / L0):.0f}% lower; median E "
           f"{float(base.E.median()):.3g} -> {float(best['E'].median()):.3g} Pa")
    if local:
        mine = "" if own is None or not math.isfinite(own["loss"]) else \
            f"; its own field refitted alike: {own['loss']:.3g}"
        out["note"] = (f"the base fit was at a local minimum: a start at its E field x {best['factor']:g} reaches a "
                       f"lower loss ({how}{mine}); the candidates are scored against that base; refit with "
                       "`fit --fresh` before diagnosing")
    else:
        out["note"] = (f"the base fit was not converged: {iterations} more iterations from its own E field lower the "
                       f"loss ({how}); the candidates are scored against that base; fit longer before diagnosing")
    log(out["note"])
    labels = region_labels(best["E"].cpu().numpy())
    return BaseState(best["E"], best["nu"], base.effects, labels, measured=base.measured), out


def refit_confusable(diag, refit: int, iterations: int, log=print) -> None:
    """Step 7 of the method (docs/diagnose.md): the top `refit` significant candidates, each with the
    candidates it explains away (its confusable rivals, `CandidateResult.rivals`), refitted briefly
    on shared held-back frames, against the base refitted alike (`refit.refit_null`); each accepted by
    a paired test over the held-back blocks (`refit.held_back_test`). Within a group the held-back
    frames decide (`refit.compare_rivals`): a rival takes the group's place only when its held-back
    residual is significantly below the selected one's (or the selected one was not accepted); a
    rival that wins is named, with its own marginal test, the others follow."""
    from ..diagnose.core import estimate_of
    from ..diagnose.refit import compare_rivals, group_frames, refit_null

    ctx = diag._ctx
    prob = ctx["prob"]
    groups, jobs = [], []
    for cr in [c for c in diag.significant][: int(refit)]:
        group = [cr]
        for b in cr.rivals:                      # a rival is refitted from its own (marginal) estimate
            b.best, b.step = b.marginal_probe
            b.estimate = estimate_of(b, prob)
            group.append(b)
        folds = int(getattr(ctx.get("settings"), "refit_folds", 1))
        val = group_frames(diag, group, folds=folds) if len(group) > 1 else None
        null = None
        if any(c.effect in PHYSICAL for c in group):
            from ..diagnose.refit import held_back_folds

            if val is None:
                col = cr.probes[cr.best].column if cr.best >= 0 else None
                val = held_back_folds(prob.T, 4, ctx["res"], col, folds)
            log(f"refitting the base alone ({iterations} iterations, held-back frames {val}): the control")
            null = refit_null(diag, val, iterations=iterations)
        for c in group:
            if c.effect in PHYSICAL:
                # refitted below, from where it stands now (a rival's start was just set from its own estimate)
                jobs.append((c, val, null, {"best": c.best, "step": c.step, "estimate": dict(c.estimate or {})}))
            elif c.rest_only:
                judge_on_rest(diag, c)
            else:
                judge_probe(diag, c, frames=val)
        groups.append(group)
    _refit_all(diag, jobs, iterations, log)
    for c in diag.significant[int(refit):]:
        # a camera cause tested on the rest frames costs no refit: judged whatever its rank (its drop, on those
        # frames alone, is small beside the moving frames' candidates and would rarely reach the top N)
        if c.rest_only and c.accepted is None and int(refit) >= 1:
            judge_on_rest(diag, c)
    holm(diag)
    for group in groups:
        cr = group[0]
        if len(group) < 2:
            continue
        win = compare_rivals(diag, cr, group)
        pt = pair_step(diag, win, group, iterations, log) if PAIR_STEP else None
        if pt is not None and pt["winner"] is not None:
            win = next(c for c in group if c.effect == pt["winner"])
        elif win is cr and cr.effect in TIE_PAIR:
            # the paired rival test could not tell them apart: damping vs viscoelasticity, the frames after
            # the release decide (`tie_break_after_release`)
            mate = next((c for c in group[1:] if c.effect in TIE_PAIR and c.effect != cr.effect), None)
            got = _after_release(diag, cr, mate) if mate is not None else None
            if got is not None:
                win = got[0]
        if win is cr:
            continue
        # the rival explains the held-back frames better: it is named in the selected one's place
        win.significant = True
        win.p_value, win.drop = win.marginal
        win.relative_drop = win.drop / diag.loss if diag.loss > 0 else 0.0
        win.rivals = [cr] + [b for b in cr.rivals if b is not win]
        for b in win.rivals:
            b.rival_of = win.effect
        win.rival_of, cr.rivals = None, []
        win.note = (f"named in place of {cr.effect} (a confusable pair, |cos| {win.collinearity:.2f}): held-back "
                    f"drop {win.held_back_drop:.3g} +- {win.held_back_se:.2g} against "
                    f"{cr.held_back_drop if cr.held_back_drop is not None else float('nan'):.3g}"
                    + ("" if cr.accepted else f" ({cr.effect} not accepted)")
                    + (f"; {pt['why']}" if pt is not None and pt["winner"] == win.effect else "") + "; " + win.note)
        res = diag.results
        res.remove(win)
        res.insert(res.index(cr), win)
    order_accepted(diag, int(refit))
    tie_break_after_release(diag)
    if getattr(ctx.get("settings"), "confirmed", False):
        # the named ones (accepted on held-back frames) first, in their order; then the significant ones
        # not confirmed; then the rest
        res = diag.results
        sig = [c for c in res if c.significant]
        res[:] = ([c for c in sig if c.accepted] + [c for c in sig if not c.accepted]
                  + [c for c in res if not c.significant])


def _refit_all(diag, jobs: list, iterations: int, log=print) -> None:
    """The physical candidates' refits (`refit.refit_effect`), each independent of the others: on the CPU each in
    its own process where the machine has the cores (`workers.fork_map`), their results set on the candidates
    here, in order, as if refitted one after another."""
    from ..workers import fork_map

    def one(job):
        c, val, null, start = job
        for k, v in start.items():
            setattr(c, k, v)
        log(f"refitting with {c.effect} ({iterations} iterations, warm-started)")
        refit_effect(diag, c, iterations=iterations, log=None, frames=val, null=null)
        return {k: v for k, v in vars(c).items() if k not in ("rivals", "probes")}

    for (c, *_), got in zip(jobs, fork_map(one, jobs, device=diag._ctx["prob"].tdev, log=log)):
        c.__dict__.update(got)


CONFUSABLE_VERDICT = True   # a confusable pair both accepted and told apart by nothing measured: one verdict for the
                            # two, "damping or ground friction: the frames cannot tell them apart" (issue #22,
                            # `diagnose.confusable`); False: the first of the two named, as before
PAIR_STEP = True   # the nested comparison of a confusable pair both accepted on the same held-back frames
                   # (`pair_step`, issue #22); False: the order of the held-back drops / the rival test alone


def _decided(a, b) -> bool:
    """a and b were told apart by the nested comparison (`pair_step`): no later reordering undoes it."""
    pt = getattr(a, "pair_test", None)
    return bool(pt and pt.get("decided") and set(pt["pair"]) == {a.effect, b.effect})


def pair_step(diag, win, group, iterations: int, log=print) -> dict | None:
    """A confusable pair both accepted on the same held-back frames: two physical effects (`refit.NESTED_PAIRS`:
    damping vs ground, damping vs viscoelasticity) or a physical effect and the interaction cause that mimics it
    (`refit.INTERACTION_PAIRS`: damping vs a grasp or release frame moved, ...). `win` (the group's choice so far)
    and the accepted mate with the largest held-back drop are refitted together and each is judged by what it adds
    given the other (`refit.nested_pair`, `refit.nested_with_interaction`: drop-one held-back loss). One more refit
    a fold, only where such a pair is confirmed. The result goes on both (`pair_test`) and in their notes; returns
    it (its `winner` names the one the data needs, None when not told apart) or None when it does not apply."""
    from ..diagnose.refit import (INTERACTION_PAIRS, NESTED_PAIRS, _same_folds, bottom_signature, nested_pair,
                                  nested_with_interaction)

    if not (win.accepted and getattr(win, "_held", None) is not None):
        return None
    pairs = (NESTED_PAIRS + INTERACTION_PAIRS) if win.effect in PHYSICAL else INTERACTION_PAIRS
    mates = [c for c in group if c is not win and c.accepted and frozenset((c.effect, win.effect)) in pairs
             and getattr(c, "_held", None) is not None and _same_folds(c._held, win._held)]
    if not mates:
        return None
    mate = max(mates, key=lambda c: c.held_back_drop or 0.0)
    log(f"refitting {win.effect} and {mate.effect} together ({iterations} iterations): what each adds given the other")
    if win.effect in PHYSICAL and mate.effect in PHYSICAL:
        pt = nested_pair(diag, win, mate, iterations=iterations)
    else:
        phys, inter = (win, mate) if win.effect in PHYSICAL else (mate, win)
        pt = nested_with_interaction(diag, phys, inter, iterations=iterations)
    if pt is None:
        return None
    if getattr(diag._ctx.get("settings"), "pair_signature", False) and {win.effect, mate.effect} == {"damping", "ground"}:
        # the physical signature decides the pair (opt-in until measured on the GPU's cases): the ground is named
        # when its model fits the lowest points better than damping's (`refit.bottom_signature`), else damping
        dmp, gnd = (win, mate) if win.effect == "damping" else (mate, win)
        sig = bottom_signature(diag, dmp, gnd)
        if sig is not None:
            pt["signature"] = sig
            pt["nested_winner"] = pt["winner"]
            pt["winner"] = "ground" if sig["ground_signature"] else "damping"
            pt["decided"] = True
            pt["why"] = f"{sig['why']}; {pt['why']}"
    joint = pt.pop("_joint", None)
    for c in (win, mate):
        c.pair_test, c._pair_joint = pt, joint
        c.note = f"pair step: {pt['why']}; " + c.note
    return pt


def holm(diag) -> None:
    """Holm's step-down correction over every candidate judged on held-back frames (the selected ones
    and their rivals, each by its paired test, `refit._accept`): sorted by held-back p, the i-th of k
    (from 0) stays accepted only when p < alpha / (k - i) and every one before it did. The family's
    chance of accepting any candidate that is no better than the base stays <= alpha, however many
    are refitted (without it, three independent null refits at 0.05 each would name one in ~14% of
    the runs). Each one's note says the level it needed."""
    from ..diagnose.refit import _alpha

    tested = sorted([c for c in diag.results if c.held_back_p is not None and c.accepted is not None],
                    key=lambda c: c.held_back_p)
    k, a, stop = len(tested), _alpha(diag), False
    for i, c in enumerate(tested):
        lvl = a / (k - i)
        ok = (not stop) and c.accepted and c.held_back_p < lvl
        if c.accepted and not ok:
            c.note = (f"not accepted after Holm's correction over {k} held-back tests (p {c.held_back_p:.3g}, "
                      f"needed < {lvl:.3g}" + (", after an earlier one failed" if stop else "") + "); " + c.note)
        if not ok:
            stop = True
        c.accepted = bool(ok)
        c.held_back_level = lvl


def order_accepted(diag, refit: int) -> None:
    """Two selected candidates (not a confusable pair: each significant once the other is in) both
    accepted on the same held-back frames: the later one is named first when its held-back residual
    is below the first's by the paired test at alpha (`refit.held_back_test`), as a rival would be
    (on the H200's foam_bar damping@2, viscoelasticity was named before damping, whose held-back
    drop was 1.2e-3 against 7.4e-4). Its `rival_test` records the comparison."""
    from ..diagnose.refit import _alpha, _same_folds, held_back_test

    acc = [c for c in diag.significant[:refit]
           if c.effect in PHYSICAL and c.accepted and getattr(c, "_held", None) is not None]
    if len(acc) < 2:
        return
    first = acc[0]
    best, bt = None, None
    for c in acc[1:]:
        if not _same_folds(c._held, first._held) or _decided(c, first):
            continue
        t = held_back_test(diag, [(h[1], g[1], h[0]) for h, g in zip(first._held, c._held)])
        c.rival_test = {"against": first.effect, "drop": t["drop"], "se": t["se"], "p": t["p"]}
        if t["p"] < _alpha(diag) and t["drop"] > 0 and (bt is None or t["drop"] > bt["drop"]):
            best, bt = c, t
    if best is None:
        return
    best.note = (f"named before {first.effect} (both accepted): on the same held-back frames its residual is "
                 f"{bt['drop']:.3g} +- {bt['se']:.2g} lower (p = {bt['p']:.3g}); " + best.note)
    res = diag.results
    res.remove(best)
    res.insert(res.index(first), best)


TIE_PAIR = frozenset(("damping", "viscoelasticity"))


def _after_release(diag, a, b) -> tuple | None:
    """The after-release comparison of two accepted candidates refitted on the same held-back frames
    whose held-back drops overlap within their standard errors (`tie_break_after_release`): (winner,
    loser, {"after_release_from", "winner", "drop", "se", "p"}), or None when it does not apply."""
    from ..diagnose.evidence import release_frame
    from ..diagnose.refit import _same_folds, held_back_test

    if not (a.accepted and b.accepted and getattr(a, "_held", None) is not None
            and getattr(b, "_held", None) is not None and _same_folds(a._held, b._held)):
        return None
    if abs(a.held_back_drop - b.held_back_drop) > math.hypot(a.held_back_se or 0.0, b.held_back_se or 0.0):
        return None
    ctx = diag._ctx
    R = release_frame(ctx["prob"])
    if R is None:
        return None
    after = ctx["res"].frame_of() >= R
    trip = [(ha[1], hb[1], ha[0] & after) for ha, hb in zip(a._held, b._held)]
    if not any(t[2].any() for t in trip):
        return None
    t = held_back_test(diag, trip)                 # from a's residual to b's: > 0 when b is lower after release
    win, lose = (b, a) if t["drop"] > 0 else (a, b)
    if win is a:                                   # the paired test in the winner's direction
        t = held_back_test(diag, [(hb, ha, m) for ha, hb, m in trip])
    out = {"after_release_from": int(R), "winner": win.effect, "drop": t["drop"], "se": t["se"], "p": t["p"]}
    win.rival_test = dict(win.rival_test or {}, against=lose.effect, after_release=out)
    win.note = (f"named before {lose.effect}: the two held-back drops overlap ({win.held_back_drop:.3g} +- "
                f"{win.held_back_se:.2g} and {lose.held_back_drop:.3g} +- {lose.held_back_se:.2g}); on the held-back "
                f"frames after the release (frame {R} on, where damping slows every motion and a viscoelastic branch "
                f"only relaxes the shape) its residual is {t['drop']:.3g} +- {t['se']:.2g} lower; " + win.note)
    return win, lose, out


def tie_break_after_release(diag, pair=TIE_PAIR) -> dict | None:
    """Damping and viscoelasticity both accepted, their held-back drops overlapping within their
    standard errors (|D_a - D_b| <= sqrt(se_a^2 + se_b^2)): the one whose refitted model leaves the
    lower residual on the held-back frames **after the release** is named first. After the release no
    load is held, and the two differ most there: damping slows every motion (the swing's amplitude,
    the rigid part of it too), a Maxwell branch only relaxes the shape toward rest; while the hand
    pulls, both change the frames alike (on the tests' tiny bar their projected columns' |cos| is 0.66
    before the release, 0.24-0.47 after it). A tie-break, not a test: the difference's paired test is
    reported (`rival_test["after_release"]`), not required. For two selected candidates (both
    significant); a confusable pair (one the other's rival) is decided in `refit_confusable` by the
    same comparison where the paired rival test cannot tell them apart. Returns that comparison, or
    None when it does not apply (not both accepted, not the same folds, drops apart, no release or no
    held-back frame after it)."""
    acc = {c.effect: c for c in diag.significant if c.effect in pair and c.accepted}
    if len(acc) != 2:
        return None
    a, b = (acc[e] for e in sorted(pair))
    if _decided(a, b):                             # the nested comparison told them apart (`pair_step`)
        return None
    got = _after_release(diag, a, b)
    if got is None:
        return None
    win, lose, out = got
    res = diag.results
    if res.index(win) > res.index(lose):
        res.remove(win)
        res.insert(res.index(lose), win)
    return out


def region_labels(E: np.ndarray, max_regions: int = 8) -> np.ndarray | None:
    """Regions of a piecewise-constant field (its distinct values), None for a smooth field."""
    vals, inv = np.unique(np.round(np.log(np.maximum(E, 1e-30)), 6), return_inverse=True)
    return inv.astype(np.int64) if len(vals) <= max_regions else None


RESOLUTION_DEFAULT = {"cuda": (2, 3), "cpu": (2,)}   # `diagnose --resolution` unless said: on the GPU two
                                                   # refinements, ~7 s a diagnosis (foam_bar, H200); on the CPU one
                                                   # (cell / 2 at an assumed order: the demo's bar 146 s, where cell / 3
                                                   # alone took 753 s)


def parse_resolution(spec, device: str = "cpu") -> tuple:
    """`diagnose --resolution`'s splits: None: the device's default (`RESOLUTION_DEFAULT`); False or "off":
    off; True: (2, 3); else one or two different whole numbers 2-4 (one: `resolution.one_level`, an assumed order)."""
    if spec is None:
        return RESOLUTION_DEFAULT["cuda" if str(device).startswith("cuda") else "cpu"]
    if spec is False or (isinstance(spec, str) and spec.strip().lower() == "off"):
        return ()
    if spec is True:
        return (2, 3)
    try:
        sp = tuple(int(v) for v in (spec.split(",") if isinstance(spec, str) else spec))
    except (TypeError, ValueError):
        raise InputError("--resolution", f"must be one or two splits of the cell such as 2,3, got {spec!r}") from None
    if len(sp) not in (1, 2) or len(set(sp)) != len(sp) or not all(2 <= v <= 4 for v in sp):
        raise InputError("--resolution", f"must be one or two different splits of the cell, each 2, 3 or 4, got {spec!r}")
    return tuple(sorted(sp))


def parse_candidates(spec) -> tuple:
    if spec is None:
        return CANDIDATES
    names = tuple(s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip())
    bad = [n for n in names if n not in CANDIDATES]
    if bad:
        raise InputError("--candidates", f"unknown candidate {bad[0]!r}; known: {', '.join(CANDIDATES)}")
    return names


BATCHED_REFITS = "cuda"           # the base refits' starts in lockstep (fit/batched.py): "cuda", "always", "never"
START_FACTORS = (1.0, 0.5, 2.0)   # the base refits' starts: the E field x these (`--starts N`: the first N;
                                  # 1: none, the stage's fit as it is)



def problem_and_base(sd, present, **problem_kw):
    """The stage's diagnosis problem (its fitted trajectories on the superset simulator: every effect at its
    null, `present` at their fitted values) and the base model (the stage's E and nu within the settings'
    bounds, the measured paths as the trajectories' anchors). `problem_kw`: FitProblem's device, dtype, ..."""
    import torch

    from ..fit.problem import FitProblem

    obs = load_observations(sd)
    fitted = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    measured = stage_contacts(sd)       # their trajectories: the measured paths (T0)
    contacts = [c.replace(trajectory=np.asarray(fitted[c.name])) if c.name in fitted and c.is_interaction else c
                for c in measured]
    prob = FitProblem(sd, obs, contacts, effects=superset_effects(sd, present), **problem_kw)
    paths = [measured[ci].trajectory if measured[ci].trajectory is not None else t.detach().cpu().numpy()
             for ci, t in prob.traj_slots]
    st = sd.settings
    E = torch.as_tensor(np.clip(sd.youngs_modulus, st.youngs_min, st.youngs_max), dtype=prob.tdtype, device=prob.tdev)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, st.poisson_max), dtype=prob.tdtype, device=prob.tdev)
    return prob, BaseState(E, nu, superset_effects(sd, present), region_labels(sd.youngs_modulus), measured=paths)


def diagnose(stage_path, *, refit: int = 3, refit_iterations: int = 8, candidates=None, write_stage: bool = True,
             device: str = "cpu", dtype: str = "float32", seed: int = 0, max_pixels: int = 6000,
             progress: bool = True, log=print, starts: int = 3, trajectory_sigma_px: float | None = None,
             refit_folds: int | None = None, floor_rule: bool = False, gate: float | None = None,
             pair_signature: bool = False, resolution=None, resolution_column: bool = False) -> dict:
    """Diagnose the stage's current fit (module doc); returns the JSON-able diagnosis.

    `starts`: 1 scores the stage's fit as it is; 2 or 3 first refit the base briefly
    (`refit_iterations`, the path kept) from its own E field and from it x 0.5 (and x 2), and score
    against the best base when one reaches a loss lower by more than the verdict's practical
    threshold (`DiagnoseSettings.min_relative_drop` of the loss), saying so: "a local minimum" when
    another start beats the fit's own field refitted alike, "not converged" when its own does. `trajectory_sigma_px`: the measured hand path's pixel uncertainty
    (default the fit's, `fit.interaction_check.TRAJ_SIGMA_PX`) that bounds the path's freedom. `floor_rule`:
    the model of the fit's own error in place of the 3% size gate (`DiagnoseSettings.floor_rule`, opt-in:
    True or "full", or "match": only the superset's substeps matched to the base's, or "rest": matched, the
    camera causes judged on the frames before the first grasp and `heterogeneity` priced as the fit's own
    model selection). `gate`: the size gate (a share of the loss a significant candidate must predict) in
    place of the rule's (3%, or 0 under a floor rule where refits confirm). `resolution`: the fit's own
    resolution error in the verdict (`DiagnoseSettings.resolution`: True for cell / 2 and / 3, or the
    splits (one: that split at an assumed order), False / "off" for none; None: `RESOLUTION_DEFAULT`, (2, 3) with
    CUDA and (2,) on the CPU: the base simulated on those finer grids costs ~16x and ~80x a forward). `resolution_column`: the check's change at
    its first split also a base column (`DiagnoseSettings.resolution_column`, opt-in). `pair_signature`: damping vs ground,
    both accepted, decided by the ground's signature at the lowest points (`DiagnoseSettings.pair_signature`,
    opt-in)."""
    t0 = time.perf_counter()
    stage_path = Path(stage_path)
    if refit is None or isinstance(refit, bool) or int(refit) < 0:
        raise InputError("--refit", f"must be a whole number >= 0, got {refit!r}")
    if refit_iterations is None or int(refit_iterations) < 1:
        raise InputError("--refit-iterations", f"must be a whole number >= 1, got {refit_iterations!r}")
    if starts is None or isinstance(starts, bool) or not 1 <= int(starts) <= len(START_FACTORS):
        raise InputError("--starts", f"must be 1, 2 or 3, got {starts!r}")
    if refit_folds is not None and (isinstance(refit_folds, bool) or refit_folds not in (1, 2)):
        raise InputError("--refit-folds", f"must be 1 or 2, got {refit_folds!r}")
    if trajectory_sigma_px is not None and not float(trajectory_sigma_px) > 0:
        raise InputError("--trajectory-sigma", f"must be a number of pixels > 0, got {trajectory_sigma_px!r}")
    if floor_rule not in (False, True, "full", "match", "rest"):
        raise InputError("--floor-rule", f"must be full, match or rest, got {floor_rule!r}")
    if gate is not None and (isinstance(gate, bool) or not 0.0 <= float(gate) < 1.0):
        raise InputError("--gate", f"must be a share of the loss in [0, 1), got {gate!r}")
    cands = parse_candidates(candidates)
    sd = read_scene(stage_path)
    if not sd.reports or sd.current_report is None:
        raise InputError(stage_path, "has no fit to diagnose: run `physinteract-usd fit` first")
    from ..devices import cpu_threads
    from ..workers import workers_for

    cpu_threads(device)     # one torch thread on the CPU, as the fit (and its worker processes: `workers`)
    workers_for(1)          # a bad PHYSINTERACT_WORKERS said now, not after the first minutes
    version = int(sd.current_version or sd.current_report["version"])
    present = effects_with_fitted(sd)
    skipped = [e for e in cands if e in present]
    cands = tuple(e for e in cands if e not in present)
    try:
        prob, base = problem_and_base(sd, present, device=device, dtype=dtype, traj_sigma_px=trajectory_sigma_px)
    except ValueError as exc:
        raise InputError(stage_path, str(exc)) from None
    settings = DiagnoseSettings(candidates=cands, seed=seed, max_pixels=max_pixels, confirmed=int(refit) >= 1,
                                floor_rule=floor_rule)
    if refit_folds is not None:
        settings.refit_folds = int(refit_folds)
    settings.pair_signature = bool(pair_signature)
    settings.resolution = parse_resolution(resolution, device)
    if resolution_column and not settings.resolution:
        raise InputError("--resolution-column", "needs the resolution check (--resolution)")
    settings.resolution_column = bool(resolution_column)
    if settings.match_substeps:           # before the base starts: every base refit steps as the fit did
        from ..diagnose.core import match_base_substeps

        match_base_substeps(prob, base, log)
    base, starts_out = _best_start(prob, base, settings, int(starts), int(refit_iterations), log)
    if gate is not None:      # after the base starts: their "local minimum" threshold stays the 3% one
        settings.min_relative_drop = settings.floor_min_relative_drop = float(gate)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = lambda it, desc: tqdm(it, desc=desc, unit="candidate", leave=False, dynamic_ncols=True)  # noqa: E731
    diag = diagnose_problem(prob, base, settings, log=log, progress=bar, evidence=describe)
    nuisance = nuisance_effects(sd.current_report)
    for e in skipped:
        if e in nuisance:
            c = (sd.current_report.get("effect_parameters") or {}).get(e, {}).get("coefficient")
            diag.notes.append(f"{e} was fitted with E as a nuisance (fit --nuisance-damping, c {c:.3g} 1/s): it is in "
                              "the base model, not a candidate; refit without --nuisance-damping to test it, or "
                              f"`effects add {e}` to keep it as the model's")
        else:
            diag.notes.append(f"{e} is already in the model (fitted): not a candidate")
    diag.base_starts = starts_out
    if starts_out.get("note"):
        diag.notes.insert(0, starts_out["note"])
    tc = diag.trajectory_check
    if tc and tc.get("suspect"):
        diag.notes.extend(tc["notes"])
    refit_confusable(diag, int(refit), int(refit_iterations), log)
    if CONFUSABLE_VERDICT and int(refit) >= 1:
        from ..diagnose.confusable import confusable_verdict

        diag.confusable = confusable_verdict(diag)
    conclude(diag)
    if starts_out.get("chosen") is not None:
        diag.reason = f"{diag.reason} [{starts_out['note']}]"
    for cr in diag.significant:       # the evidence again: the refit's estimate is the better number
        try:
            cr.evidence = describe(cr.effect, cr, diag._ctx)
        except Exception as exc:  # noqa: BLE001
            cr.evidence = f"(evidence unavailable: {exc})"
    if diag.confusable:
        from ..diagnose.confusable import word_confusable

        word_confusable(diag)
    diag.cost["seconds"] = time.perf_counter() - t0
    out = json_safe(diag.to_dict())
    out.update({"stage": str(stage_path), "version": version})
    if write_stage:
        from ..usd.diagnosis_io import write_diagnosis

        out["stage_layer"] = write_diagnosis(stage_path, sd.fps, sd.n_frames, version, out)
    return out
