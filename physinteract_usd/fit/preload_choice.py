"""Does the scan carry its weight? The fit decides where the stage does not say (#23).

A scan of a real object shows it at rest on whatever holds it: already sagged, its material already stressed. Started
stress-free, the model sags again from the scan, and a fit makes E stiff to stop it (6-21x on settled world captures,
docs/benchmarks/world.md). Our own synthetic truths, and some captures made by others, start stress-free instead and
do sag in the video. Which one a capture is, the user often does not know; the frames do: a model started the wrong
way moves where the video is still, or stays still where the video sags.

`choose_preload` runs the fit's uniform start search (golden section over one log E) under both hypotheses, the scan
stress-free and the scan preloaded (`sim.preload`), and keeps the one whose best uniform loss is lower: both have the
same freedom (one E), so the lower loss is the better explanation. The stress-free scan (the model as it was before
this choice) is kept unless the preload is lower by more than `MARGIN` of it: where the object barely sags under its
weight the two hypotheses render alike (the bundled sample: 0.4% apart at the same E) and the choice changes nothing
worth a switch. No USD here: the caller records the choice on the stage.
"""

from __future__ import annotations

from ..errors import SimulationError

# The preload is kept only where its best uniform loss is below (1 - MARGIN) x the stress-free one's. Measured
# (development data, 7-probe searches; docs/benchmarks/world.md, 37th session): on the 12 suite scenes (stress-free
# truths) the preload from 0.4% lower (foam_bar, the same E) to 228% higher; on three settled world captures 3.5%,
# 15.5% and 35% lower; one older default capture (a truth that starts unloaded) 7.8% lower.
MARGIN = 0.02
# ... and said to be unsure where the two best losses are within UNSURE of each other while their E differ more than
# UNSURE_E times (dev_0546 settled: 3.5% apart, 549 Pa preloaded against 26 kPa stress-free)
UNSURE, UNSURE_E = 0.10, 3.0


def choose_preload(prob, evals: int, log=None, stress_free: tuple[float, float] | None = None) -> dict:
    """Decide between the scan stress-free and preloaded on `prob` (a FitProblem whose simulation starts stress-free)
    by each one's best uniform-E loss (`optimize.uniform_loss`, `evals` golden-section probes); `stress_free`: the
    stress-free search's (E, loss) where the caller has it already. Leaves `prob.sim` on the chosen hypothesis and
    returns {"preload": bool, "uniform_e": the chosen one's E, "probes": its search's probes, "unsure": the frames
    barely tell them apart while their E differ, "loss": {...}, "E": {...}, "reason": str}. Where
    nothing holds the object at frame 0 (no support, no ground) the preload cannot be, and the search is skipped."""
    from .optimize import uniform_loss

    sim = prob.sim
    try:
        sim.use_preload(True)
    except ValueError as exc:
        sim.use_preload(False)
        out = {"preload": False, "uniform_e": None if stress_free is None else stress_free[0], "probes": {},
               "unsure": False, "loss": {}, "E": {}, "reason": f"{exc}; the scan stress-free"}
        if log:
            log(f"preload: {out['reason']}")
        return out
    seen = {True: {}, False: {}}
    try:
        e_pre, l_pre = uniform_loss(prob, evals, seen=seen[True])
    except SimulationError as exc:        # no finite preloaded probe: the stress-free scan, as before
        e_pre, l_pre = None, float("inf")
        if log:
            log(f"preload: no finite probe preloaded ({exc})")
    sim.use_preload(False)
    try:
        e_free, l_free = stress_free if stress_free is not None else uniform_loss(prob, evals, seen=seen[False])
    except SimulationError:
        if e_pre is None:                 # neither holds together: the fit's own error, as before the choice
            raise
        e_free, l_free = None, float("inf")
    chosen = l_pre < (1.0 - MARGIN) * l_free
    sim.use_preload(chosen)
    rel = (l_free - l_pre) / l_free if 0 < l_free < float("inf") else (1.0 if chosen else 0.0)
    if chosen and e_free is None:
        reason = (f"the scan looks settled on its supports: preloaded (best uniform loss {l_pre:.6g} at E {e_pre:.4g} "
                  "Pa); stress-free the simulation went unstable or left the grid at every E tried")
    elif chosen:
        reason = (f"the scan looks settled on its supports: preloaded, the best uniform loss is {100 * rel:.1f}% lower "
                  f"({l_pre:.6g} at E {e_pre:.4g} Pa against {l_free:.6g} at {e_free:.4g} Pa stress-free)")
    else:
        reason = (f"the scan taken stress-free: the best uniform loss preloaded is "
                  + (f"{l_pre:.6g} at E {e_pre:.4g} Pa against {l_free:.6g} at {e_free:.4g} Pa stress-free "
                     f"({100 * rel:+.1f}%, the preload needs > {100 * MARGIN:.0f}% lower)"
                     if e_pre is not None else "not finite"))
    spread = max(e_pre, e_free) / min(e_pre, e_free) if e_pre is not None and e_free is not None else 1.0
    unsure = abs(rel) < UNSURE and spread > UNSURE_E
    if unsure:
        reason += (f"; the frames barely tell the two apart while their E differ {spread:.0f}x: if you know how the "
                   "object was scanned, say it (init --preload or --no-preload)")
    if log:
        log(f"preload: {reason} (init --preload / --no-preload decides it instead)")
    return {"preload": bool(chosen), "uniform_e": e_pre if chosen else e_free, "probes": seen[bool(chosen)],
            "unsure": bool(unsure),
            "loss": {"preloaded": l_pre, "stress_free": l_free},
            "E": {"preloaded": e_pre, "stress_free": e_free}, "reason": reason}
