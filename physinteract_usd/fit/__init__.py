"""Analysis-by-synthesis: the joint fit of the material field and the interaction trajectory
through the differentiable simulator and renderer. No USD here.

`fit(problem, settings)` runs the schedule `settings.schedule` names: "ladder" (model selection,
uniform E then regions split by score tests; `ladder.py`), "bumps" (a coarse-to-fine field of
Gaussian bumps; `optimize.py`) or "select" (a dense uniform sweep, then uniform vs the bumps field
by held-back frames; `select.py`). Two options of any schedule (#24): `uniform_guard` (bumps: the
field only where its held-back loss clearly beats the uniform model's) and `unconstrained_floor` (the
particles the video does not constrain marked and filled from their neighbours)."""

from .ladder import fit_ladder
from .material import MaterialField
from .optimize import FitResult, FitSettings, fit_bumps
from .parts_start import default_probes
from .trend_start import default_trend_probes, starts_hook
from .problem import FitProblem, LossWeights, Observations
from .select import fill_unconstrained, fit_guarded, fit_select

SCHEDULES = {"ladder": fit_ladder, "bumps": fit_bumps, "select": fit_select}


def fit(prob: FitProblem, settings: FitSettings | None = None, **kw) -> FitResult:
    """Fit `prob` with `settings` (defaults: FitSettings()); keyword arguments go to the schedule
    (progress, log, start, on_iteration, uniform_e)."""
    s = settings or FitSettings()
    if s.schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {', '.join(SCHEDULES)}, not {s.schedule!r}")
    tw = float(getattr(s, "track_weight", 0.0) or 0.0)
    if not tw >= 0:
        raise ValueError(f"track_weight must be >= 0, got {tw}")
    if tw > 0 and prob.tracks is None:
        raise ValueError("track_weight > 0 needs point tracks in the fit's observations (Observations.tracks)")
    prob.weights.track = tw      # the point tracks' term (fit/tracks_loss.py) counts in every schedule's loss
    if s.parts_start is None:    # the parts start's default: on CUDA, off on the CPU (recorded as resolved). In
        # place, not a copy: a stop mutates the caller's settings while the fit runs (confidence_probes = 0)
        s.parts_start = default_probes(prob, None)
    if s.trend_start is None:    # the trend start's default: on CUDA, off on the CPU (recorded as resolved)
        s.trend_start = default_trend_probes(prob, None)
    if s.schedule == "bumps" and s.uniform_guard:     # the field only where it clearly beats one number (#24)
        r = fit_guarded(prob, s, **kw)
    else:
        ps, ts = int(getattr(s, "parts_start", 0) or 0), int(getattr(s, "trend_start", 0) or 0)
        starts = s.schedule == "bumps" and (ps > 0 or ts > 0) and kw.get("start") is None
        if starts:
            kw = {**kw, "before_finest": starts_hook(ps, ts, getattr(s, "starts_order", "parts_first"))}   # #24: foam_bar's parts, balloon's trend
        if getattr(s, "skip_searched_uniform", False) is None:   # resolved in place (recorded): where the starts run
            s.skip_searched_uniform = bool(starts)
        r = SCHEDULES[s.schedule](prob, s, **kw)
    if float(s.unconstrained_floor) > 0 and not r.interrupted and int(s.iterations) > 0:
        # what the video does not constrain (#24; not on a stop's zero-iteration last pass)
        r = fill_unconstrained(prob, r, s, s.unconstrained_floor, log=kw.get("log"))
    return r


__all__ = ["fit", "fit_ladder", "fit_bumps", "fit_select", "FitSettings", "FitResult", "FitProblem", "Observations",
           "LossWeights", "MaterialField", "SCHEDULES"]
