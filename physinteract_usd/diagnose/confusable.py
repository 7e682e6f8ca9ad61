"""The honest verdict for a confusable pair (issue #22): when two effects of a known confusable pair
(`refit.NESTED_PAIRS`: damping vs ground friction, damping vs viscoelasticity) both pass the held-back
test and nothing the diagnosis measures tells them apart, it says so: one verdict "damping or ground
friction: the frames cannot tell them apart", both candidates' evidence, what capture would separate
them (from the physics of the two), and which one `effects add` should add if the user only wants the
error down.

**Separates** (a stated test, every part at the diagnosis's alpha, 0.05, the held-back test's own level):
the pair is told apart when either holds, else it is confusable:
1. *nested* (`app.diagnose.pair_step`, `refit.nested_pair`): refitted together, one is needed given the
   other (removing it costs held-back loss, the paired block test at p < alpha) while the other is not;
   both needed: not a mimic pair (both stay named, no confusable verdict);
2. *signature* (opt-in, `DiagnoseSettings.pair_signature`, damping vs ground): the ground's model fits
   the lowest points better than damping's at p < alpha (`refit.bottom_signature`). "No signature" alone
   does not separate: it is the absence of evidence, not evidence for damping.
The *direct* comparison of the two single refits (the paired block test from one's held-back residual to
the other's, both ways) is reported and chooses the effect to add, but it does **not** separate a known
confusable pair: a mimic can fit the held-back frames better than the truth. On foam_bar's hidden ground
(CPU, fit grid 16; docs/benchmarks/diagnose_named.md, 17th) damping's single refit fits them better than
the true ground's, while neither is needed given the other. By the nested identity (docs/diagnose.md, step
7: cost(a | b) - cost(b | a) = L(b) - L(a) on the same held-back elements) a nested winner also leads the
direct comparison; the nested test asks more: the winner needed *and* the other not.

Numpy only (through `refit`'s held-back test); no USD, no CLI."""

from __future__ import annotations

from .core import PHYSICAL, Diagnosis

# how a person calls an effect in the verdict's sentence
SPOKEN = {"damping": "damping", "ground": "ground friction", "viscoelasticity": "viscoelasticity",
          "plasticity": "plasticity"}

# the parameters `effects add` fits for each effect (its cost: fewer is cheaper and less prone to absorb the
# fit's own error)
PARAMETERS = {"damping": ("coefficient c [1/s]",), "ground": ("height h [m]", "friction mu"),
              "viscoelasticity": ("modulus E_v [Pa]", "relaxation time tau [s]"),
              "plasticity": ("yield stress tau_Y [Pa]",)}

# what the two effects do differently (the physics) and the capture that would show it
TO_SEPARATE = {
    frozenset(("damping", "ground")): (
        "damping (v <- v exp(-c dt) on every grid node) slows every moving part in proportion to its speed, "
        "wherever it is; a ground plane acts only on the particles at its height, stops them there and, by "
        "Coulomb friction (mu x the normal load, not proportional to speed), stops their sliding. A capture that "
        "separates them: (1) a free decay clear of the floor: lift the object (or take the table away) and let it "
        "swing after the release: damping still decays the swing at the same rate, a ground does nothing; (2) a "
        "longer contact with the floor: the object resting or sliding on it for several frames: a ground holds "
        "the lowest points at one height and stops their sliding within a few frames, damping only slows them "
        "exponentially and never holds them at a height; (3) a side view at floor level while the object is near "
        "it: whether the lowest points touch the floor (a flattened bottom pressed against it, or a gap) shows "
        "directly what a view from above cannot"),
    frozenset(("damping", "viscoelasticity")): (
        "damping slows every motion (a swing's amplitude decays at a constant frequency; a body held still feels "
        "nothing), a Maxwell branch (E_v, tau) makes the body stiffer in fast motion and relaxes its stress over "
        "tau. A capture that separates them: (1) hold the object deformed and still for a few tau: under a held "
        "load the shape keeps creeping with a Maxwell branch and not with damping; (2) a free swing after the "
        "release with several oscillations: damping decays the amplitude at the same frequency, a Maxwell branch "
        "shifts the frequency; (3) the same pull at two speeds: a viscoelastic body looks stiffer when pulled "
        "faster, a damped one reaches the same deflection"),
}


def _separated(diag: Diagnosis, a, b) -> tuple[str | None, dict]:
    """(why they are told apart or None, the tests' numbers) for two accepted candidates refitted on the
    same held-back frames (module doc: nested, signature; the direct comparison reported, not separating)."""
    from .refit import _alpha, held_back_test

    alpha = _alpha(diag)
    half = 0.5 * alpha          # the direct comparison, two-sided (reported; it does not separate: module doc)
    t_ab = held_back_test(diag, [(h[1], g[1], h[0]) for h, g in zip(a._held, b._held)])   # > 0: b lower
    t_ba = held_back_test(diag, [(g[1], h[1], g[0]) for h, g in zip(a._held, b._held)])   # > 0: a lower
    tests = {"direct": {"from": a.effect, "to": b.effect, "drop": float(t_ab["drop"]), "se": float(t_ab["se"]),
                        "p": float(t_ab["p"]), "p_reverse": float(t_ba["p"]), "alpha": alpha}}
    why = None
    tests["direct"]["better"] = (b.effect if t_ab["drop"] > 0 and t_ab["p"] < half else
                                 a.effect if t_ba["drop"] > 0 and t_ba["p"] < half else None)
    pt = a.pair_test if a.pair_test is not None and set(a.pair_test.get("pair", ())) == {a.effect, b.effect} else \
        b.pair_test if b.pair_test is not None and set(b.pair_test.get("pair", ())) == {a.effect, b.effect} else None
    if pt is not None:
        adds = pt.get("adds") or {}
        tests["nested"] = {e: {k: v for k, v in t.items()} for e, t in adds.items()}
        nested = pt.get("nested_winner", pt.get("winner")) if "signature" in pt else pt.get("winner")
        if why is None and nested is not None:
            why = f"refitted together, {nested} is needed and the other only mimics it"
        if why is None and adds and all(t.get("needed") for t in adds.values()):
            why = "refitted together, both are needed"
        sig = pt.get("signature")
        if sig is not None:
            tests["signature"] = {"bottom": sig.get("bottom"), "ground_signature": bool(sig.get("ground_signature"))}
            if why is None and sig.get("ground_signature"):
                why = "the ground's signature at the lowest points"
    return why, tests


def _share(c, L: float) -> float | None:
    return None if c.held_back_drop is None or not L > 0 else float(c.held_back_drop) / L


def _choose(a, b, direct: dict) -> tuple:
    """(the one `effects add` should add, why): the better on the held-back frames (the larger held-back drop)
    unless the two differ by less than one standard error of their direct paired test, then the cheaper (fewer
    parameters to fit), the better on a tie of both."""
    da, db = a.held_back_drop or 0.0, b.held_back_drop or 0.0
    better, worse = (a, b) if da >= db else (b, a)
    na, nb = len(PARAMETERS.get(a.effect, ())), len(PARAMETERS.get(b.effect, ()))
    close = abs(da - db) < float(direct.get("se") or 0.0)
    if close and na != nb:
        cheap, dear = (a, b) if na < nb else (b, a)
        return cheap, (f"the two lower the held-back loss alike ({SPOKEN[a.effect]} {da:.3g}, {SPOKEN[b.effect]} "
                       f"{db:.3g}: closer than their difference's standard error {direct['se']:.2g}), and "
                       f"{cheap.effect} is the cheaper model ({len(PARAMETERS[cheap.effect])} parameter"
                       f"{'s' if len(PARAMETERS[cheap.effect]) > 1 else ''} to fit against {len(PARAMETERS[dear.effect])})")
    return better, (f"its refit lowered the held-back loss more ({better.held_back_drop or 0.0:.3g} against "
                    f"{worse.effect}'s {worse.held_back_drop or 0.0:.3g}; {len(PARAMETERS.get(better.effect, ()))} "
                    f"parameter{'s' if len(PARAMETERS.get(better.effect, ())) != 1 else ''} to fit)")


def confusable_verdict(diag: Diagnosis) -> dict | None:
    """After the refits (`app.diagnose.refit_confusable`): the first named physical effect and the accepted
    mate of a known confusable pair with the largest held-back drop, refitted on the same held-back frames;
    when nothing separates them (module doc) returns the verdict's record and puts both in the named
    candidates, the one to add first: {"pair", "verdict", "separates" (the rule), "tests", "evidence": {effect:
    {...}}, "to_separate", "add", "add_why"}; `evidence`'s sentences are filled by the caller once the
    candidates' evidence is worded (`word_confusable`). None when it does not apply."""
    from .refit import NESTED_PAIRS, _same_folds

    named = [c for c in diag.results if c.significant and c.accepted and c.effect in PHYSICAL]
    if not named:
        return None
    top = named[0]
    if getattr(top, "_held", None) is None:
        return None
    mates = [c for c in diag.results if c is not top and c.accepted and c.effect in PHYSICAL
             and frozenset((c.effect, top.effect)) in NESTED_PAIRS and getattr(c, "_held", None) is not None
             and _same_folds(c._held, top._held)]
    if not mates:
        return None
    mate = max(mates, key=lambda c: c.held_back_drop or 0.0)
    why, tests = _separated(diag, top, mate)
    if why is not None:
        for c in (top, mate):
            c.note = f"told apart from {(mate if c is top else top).effect}: {why}; " + c.note
        return None
    add, add_why = _choose(top, mate, tests["direct"])
    other = mate if add is top else top
    # both named: the mate (explained away by the linear test, accepted on held-back frames) joins the candidates
    if not mate.significant:
        mate.significant = True
        mate.p_value, mate.drop = mate.marginal
        mate.relative_drop = mate.drop / diag.loss if diag.loss > 0 else 0.0
    res = diag.results
    for c in (add, other):
        res.remove(c)
    at = min([i for i, c in enumerate(res) if c.significant] or [0])
    res[at:at] = [add, other]
    pair = frozenset((top.effect, mate.effect))
    words = f"{SPOKEN[add.effect]} or {SPOKEN[other.effect]}: the frames cannot tell them apart"
    d = tests["direct"]
    L = _held_loss(diag, top)
    lo, hi, p_lo = (d["to"], d["from"], d["p"]) if d["drop"] >= 0 else (d["from"], d["to"], d["p_reverse"])
    out = {"pair": [add.effect, other.effect], "verdict": words,
           "separates": ("told apart when, refitted together, one is needed given the other (the paired held-back "
                         "block test at alpha) and the other is not, or (opt-in) the ground's signature at the lowest "
                         "points holds at alpha; neither held. The direct comparison of the two single refits does not "
                         "separate a known confusable pair (a mimic can fit the held-back frames better than the truth)"),
           "tests": tests,
           "evidence": {c.effect: {"held_back_drop": c.held_back_drop, "held_back_se": c.held_back_se,
                                   "held_back_p": c.held_back_p, "held_back_share": _share(c, L),
                                   "predicted_share": float(c.marginal[1]) / diag.loss if diag.loss > 0 else None,
                                   "estimate": dict(c.estimate or {}), "evidence": ""} for c in (add, other)},
           "to_separate": TO_SEPARATE.get(pair, ""), "add": add.effect, "add_why": add_why,
           "summary": (f"{words}: refitted alone, {_alone(add, L)}; {_alone(other, L)}; on the same held-back "
                       f"frames {lo}'s model leaves {abs(d['drop']):.3g} +- {d['se']:.2g} less than {hi}'s (p = "
                       f"{p_lo:.2g}" + (", below alpha / 2: but a mimic can fit better than the truth" if d.get("better")
                                        else "") + ")" + _nested_words(tests)
                       + f". To lower the error: `effects add {add.effect}`: {add_why}")}
    for c in (add, other):
        c.note = f"confusable with {(other if c is add else add).effect}: the frames cannot tell them apart; " + c.note
    return out


def _held_loss(diag: Diagnosis, c) -> float:
    """The base's loss over the candidate's held-back elements (folds pooled)."""
    import numpy as np

    r0 = diag._ctx.get("r0")
    if r0 is None:
        return 0.0
    r0 = np.asarray(r0)
    m = np.zeros(len(r0), bool)
    for mk, _ in c._held:
        m |= mk
    return float(np.mean(np.square(r0[m]))) if m.any() else 0.0


def _alone(c, L: float) -> str:
    s = _share(c, L)
    return (f"{c.effect} lowers the held-back loss by {c.held_back_drop or 0.0:.3g} +- {c.held_back_se or 0.0:.2g}"
            + (f" ({100 * s:.0f}%)" if s is not None else "") + f", p = {c.held_back_p if c.held_back_p is not None else float('nan'):.2g}")


def _nested_words(tests: dict) -> str:
    n = tests.get("nested")
    if not n:
        return ""
    parts = [f"removing {e} given the other costs {100 * (t.get('share') or 0.0):.1f}% (p = {t.get('p', 1.0):.2g})"
             for e, t in n.items()]
    return "; refitted together, " + ", ".join(parts) + ": neither needed given the other"


def word_confusable(diag: Diagnosis) -> None:
    """The candidates' evidence sentences into the confusable verdict's record (after `describe`)."""
    cf = getattr(diag, "confusable", None)
    if not cf:
        return
    for c in diag.results:
        if c.effect in cf["evidence"]:
            cf["evidence"][c.effect]["evidence"] = c.evidence
