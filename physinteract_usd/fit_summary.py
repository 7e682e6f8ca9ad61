"""What a fit said about E, in short (`fit --json`, `info`, the report): the material model's
summary and the identifiability sentence. Pure Python, outside the `fit` package (whose import
loads torch and Warp) so that `info` stays fast; `fit.select` re-exports these names."""

from __future__ import annotations

import math


def sweep_interval(sweep: dict, rise: float) -> list[float] | None:
    """The hull of the uniform E values whose loss is within `rise` (a share) of the best one seen
    (the sweep's points and the refinements'): [E_lo, E_hi] Pa. Unlike the interval from the
    curvature at a minimum, it holds a flat or bumpy curve's every near-best stretch, so a video
    that does not determine E gets a wide interval. None without a finite value."""
    pts = [(float(e), float(v)) for e, v in sweep.items() if v is not None and math.isfinite(float(v))]
    if not pts:
        return None
    best = min(v for _, v in pts)
    near = [e for e, v in pts if v <= best * (1.0 + rise)]
    return [min(near), max(near)]


# how wide (hi / lo) the uniform interval may be for E to count as determined within the MA
# tolerance (+-20%: 1.2 / 0.8 = 1.5), roughly (within 2x either way: 4)
DETERMINED_RATIO, ROUGH_RATIO = 1.5, 4.0


def identifiability(model_sum: dict, confidence_mean: float | None, e_median: float,
                    rise: float = 0.01) -> dict:
    """What the video says about E, plainly: {"interval": [lo, hi] | None, "ratio", "level":
    "determined" | "rough" | "undetermined" | "unknown", "sentence"}. The interval is the
    uniform sweep's near-best hull (`sweep_interval`, schedule select); without a sweep, the bumps
    start search's probes (`uniform_probe_interval`, a lower bound of the width: wider than 4x is
    "undetermined" for sure), else the fit's mean confidence (the share of the object whose E is
    likely within 20%)."""
    iv = model_sum.get("uniform_sweep_interval")
    pv = model_sum.get("uniform_probe_interval")
    out = {"interval": iv, "ratio": None, "level": "unknown", "sentence": ""}
    if not iv and pv and pv[1] / pv[0] > ROUGH_RATIO:
        # the bumps start search's few probes: their near-best hull is a lower bound of the width
        out.update(interval=pv, ratio=pv[1] / pv[0], level="undetermined",
                   sentence=f"this video does not determine E: uniform E from {pv[0]:.3g} to {pv[1]:.3g} Pa (at "
                            f"least) fit within {rise:.0%} of the best the start search found; the median "
                            f"{e_median:.3g} Pa is one choice among many (`fit --schedule select` sweeps the "
                            "whole range)")
        return out
    if iv:
        ratio = iv[1] / iv[0]
        out["ratio"] = ratio
        level = "determined" if ratio <= DETERMINED_RATIO else "rough" if ratio <= ROUGH_RATIO else "undetermined"
        out["level"] = level
        span = (f"a uniform E anywhere in {iv[0]:.3g} .. {iv[1]:.3g} Pa fits within {rise:.0%} of the best"
                if ratio > 1.001 else
                f"no other uniform E of the sweep comes within {rise:.0%} of the best, {iv[0]:.3g} Pa")
        if level == "determined":
            out["sentence"] = f"E is determined by this video: {span}"
        elif level == "rough":
            out["sentence"] = (f"E is determined only roughly ({ratio:.1f}x wide): {span}; take the interval, not "
                               "the number")
        else:
            out["sentence"] = (f"this video does not determine E: {span} ({ratio:.0f}x wide); the median "
                               f"{e_median:.3g} Pa is one choice among many. A release with free swinging, a sag "
                               "under gravity or a larger deformation would pin it down")
    elif confidence_mean is not None:
        out["level"] = "determined" if confidence_mean >= 0.8 else "rough" if confidence_mean >= 0.4 else "undetermined"
        if out["level"] != "determined":
            out["sentence"] = (f"E may not be determined by this video: mean confidence {confidence_mean:.2f} (the "
                               "share of the object whose E is likely within 20%); `fit --schedule select` sweeps "
                               "a uniform E and gives the interval")
    unc = model_sum.get("unconstrained") or {}
    n_free = (unc.get("of") or 0) - (unc.get("held") or 0)
    if unc.get("barely_strained") and n_free > 0:
        # the particles the clip barely strains (`fill_unconstrained`): their E is their neighbours'
        share = unc["barely_strained"] / n_free
        out["unconstrained_share"] = share
        out["sentence"] = ((out["sentence"] + "; ") if out["sentence"] else "") + (
            f"{share:.0%} of the free particles barely strain in this clip (< {unc['floor']:g} x the median): the "
            "video does not see their E, which is the material they are attached to (confidence 0)")
    return out


def model_summary(model: dict | None) -> dict:
    """The material model a fit chose, in short (`fit --json`, the report): the schedule, the model
    chosen, the uniform stage's E, curve shape and minima, each model's training and held-back
    losses and the test's verdict."""
    m = model or {}
    out = {"schedule": m.get("schedule", "bumps")}
    if "chosen" in m:
        out["chosen"] = m["chosen"]
    uni = m.get("uniform_stage")
    if uni:
        out["uniform_e"] = uni["e"]
        out["uniform_curve"] = uni["shape"]
        out["uniform_minima"] = [{"e": x["e"], "loss": x["loss"], "interval": x["interval"]} for x in uni["minima"]]
        if uni.get("sweep"):
            out["uniform_sweep_interval"] = sweep_interval(uni["sweep"], uni.get("rise", 0.01))
    if m.get("uniform_probes") and not uni:
        out["uniform_probe_interval"] = sweep_interval(m["uniform_probes"], 0.01)
    if "models" in m:
        out["losses"] = {k: {"training": v["training"], "held_back": v["held_back"], "median_e": v.get("median_e")}
                         for k, v in m["models"].items()}
    if "tests" in m:          # each step's test, simple to complex: "parts" (vs uniform), "field" (vs the kept one)
        out["test"] = "; ".join(f"{k}: {v.get('why', '')}" for k, v in m["tests"].items())
        out["tests"] = {k: {"kept": bool(v.get("keep_field")), "why": v.get("why", "")} for k, v in m["tests"].items()}
    elif "test" in m:
        out["test"] = m["test"].get("why", "")
    if m.get("field_from"):
        out["field_from"] = m["field_from"]
    pr = m.get("parts")
    if pr:                    # the parts step: the candidate kept, each part's E and intervals
        parts = {"why": pr["why"]} if "why" in pr else {"kind": pr.get("kind"), "e": pr.get("e")}
        final = pr.get("final")
        best = None
        for c in pr.get("candidates", []):
            for st in c.get("starts", []):
                if c.get("kind") == pr.get("kind") and (best is None or st["loss"] < best["loss"]):
                    best = st
            parts.setdefault("candidates", []).append(
                {"kind": c["kind"], "parts": c["parts"], "particles": c.get("particles"),
                 "sweep": [{"from_e": st["from_e"], "e": st["e"], "loss": st["loss"]} for st in c.get("starts", [])]})
        if pr.get("unconstrained"):                         # particles the clip barely strains: no part of their own
            parts["unconstrained"] = pr["unconstrained"]
        if best is not None:
            parts["sweep_interval"] = best["interval"]      # each part's E within 1% of its line's best
        if final:
            parts["final"] = final                          # with the chosen model's 95% intervals
        out["parts"] = parts
    g = m.get("guard")
    if g:                       # the bumps field against one number on held-back frames (`fit_guarded`)
        out["guard"] = ({"why": g["why"]} if "chosen" not in g else
                        {"chosen": g["chosen"], "rejected": g["rejected"], "why": g["test"]["why"],
                         "held_back": {k: v["held_back"] for k, v in g["models"].items()}})
    if m.get("unconstrained"):  # the particles the video does not constrain (`fill_unconstrained`)
        out["unconstrained"] = {k: v for k, v in m["unconstrained"].items() if k != "rule"}
    if "regions" in m:          # the ladder's
        out["regions"] = m["regions"]
    return out
