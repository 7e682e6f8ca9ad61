"""`fit`: the joint fit of the material field and the interaction trajectory to the stage's video,
written into the stage's fit layer as a new model version.

The steps, each usable on its own (benchmarks and experiments swap a part):
1. `prepare_fit`: read the stage, its observations, its contacts (running extraction when it has
   none; or the ground truth's with `contact_from`; or the caller's `contacts`), effects, settings
   and the resumed start -> a `FitJob`;
2. `run_fit`: size a guessed support on the first fit, then the optimiser (`fit.fit`) -> FitResult;
3. `write_fit_layer` (usd.fit_io) -> a new version (usd/versions.py: its snapshot in
   `<stem>.versions/v<N>.usdc`; current when its loss is the lowest, with `keep_best`).
`fit` runs the three and returns a `FitOutcome`.

Stopping (docs/versions.md): SIGINT and SIGTERM ask the fit to stop; the simulator acts on it
between frames, the optimiser keeps its best iterate, the confidence estimate is skipped, and the
best iterate is written as an `interrupted` version (never current over a complete one). Every
`checkpoint_every` iterations the best iterate goes to `<stem>.versions/checkpoint.npz`, which
`resume` goes on from after a kill -9; a written version removes it."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import stopping
from ..devices import cpu_threads
from ..errors import InputError
from ..fit import FitProblem, FitResult, FitSettings
from ..fit import fit as optimise
from ..fit.optimize import select_supports
from ..fit.select import identifiability, model_summary
from ..fit.problem import Observations
from ..scene import SceneData
from ..sim.kernels import preload as preload_kernels
from ..usd.fit_io import write_fit_layer
from ..usd.layout import LayerPaths
from ..usd.versions import read_version_start
from . import budget
from .adapters import (load_observations, nuisance_effects, read_scene, stage_contacts, stage_effects, true_contacts,
                       true_hand_masks)
from .fit_checkpoint import FitTracker, fingerprint, load_checkpoint, remove_checkpoint

DEFAULT_ITERATIONS = 60
WARM_ITERATIONS = 20     # a refit after `effects add / remove` starts where the current version ended
CHECKPOINT_EVERY = 5


@dataclass
class FitJob:
    """Everything a fit needs, read from the stage."""

    stage_path: Path
    scene: SceneData
    observations: Observations
    contacts: list
    effects: dict
    settings: FitSettings
    device: str = "cpu"
    start: dict | None = None            # resume: {"youngs", "poisson", "trajectories"}
    source: str = "extracted"            # where the contacts came from: extracted | groundTruth | caller
    resumed_from: str = ""               # "" | "v<N>" | "checkpoint" | "warm:v<N>" (effects changed)
    history: list = field(default_factory=list)   # a resumed checkpoint's loss history
    problem: FitProblem | None = None    # built by run_fit (kept for the last pass after a late stop)
    starts: int = 1                      # fits from this many starts, the best kept (fit/batched.py)
    alt_start: dict | None = None        # a warm start's second start (`warm_path` "both": the measured hand paths),
                                         # the lower final loss of the two kept (`run_fit`)
    preload_choice: dict | None = None   # where the stage left it open: the fit's decision (fit/preload_choice.py)


@dataclass
class FitOutcome:
    result: FitResult
    version: int
    layer: str
    contacts: list = field(default_factory=list)
    current: int | None = None           # the version current after this fit
    reason: str = ""                     # why the new version is (or is not) current
    snapshot: str = ""                   # <stem>.versions/v<N>.usdc
    stopped_by: str | None = None        # the signal that stopped the fit (SIGINT, SIGTERM)
    confidence_estimated: bool = True
    phases: dict = field(default_factory=dict)   # seconds around the fit: "prepare", "problem", "notes", "write" (#26)

    def summary(self) -> dict:
        """The JSON-able summary `fit --json` prints."""
        r = self.result
        fm = r.frame_metrics
        model = model_summary(r.model)
        return {"version": self.version, "layer": self.layer, "snapshot": self.snapshot,
                "current_version": self.current, "is_current": self.current == self.version,
                "current_reason": self.reason, "status": "interrupted" if r.interrupted else "complete",
                "stopped_by": self.stopped_by, "confidence_estimated": self.confidence_estimated,
                "iterations": len(r.loss_history),
                "final_loss": r.final_loss, "runtime_s": r.runtime_s, "device": r.device,
                "phases_s": {**self.phases, **((r.model or {}).get("phases_s") or {})},
                "iteration_s": (r.model or {}).get("iteration_s"),
                "interrupted": r.interrupted,
                "psnr": float(np.mean([min(f["psnr"], 100) for f in fm])),
                "psnr_masked": float(np.nanmean([min(f["psnr_masked"], 100) for f in fm])),
                "ssim": float(np.mean([f["ssim"] for f in fm])), "iou": float(np.mean([f["iou"] for f in fm])),
                "youngs_modulus_pa": {"min": float(r.youngs.min()), "median": float(np.median(r.youngs)),
                                      "max": float(r.youngs.max())},
                "confidence_mean": float(r.confidence.mean()),
                "model": model,
                "identifiability": identifiability(model, float(r.confidence.mean())
                                                   if self.confidence_estimated else None, float(np.median(r.youngs))),
                # the fit's decision on the scan's preload where the stage left it open (fit/preload_choice.py)
                **({"preload": r.settings["preload"]} if isinstance((r.settings or {}).get("preload"), dict) else {}),
                **({"starts": r.model["starts"], "starts_chosen": r.model.get("starts_chosen"),
                    "starts_mode": r.model.get("starts_mode")} if (r.model or {}).get("starts") else {})}


def check_iterations(iterations) -> None:
    if iterations is None:
        return
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise InputError("--iterations", f"must be a whole number >= 1, got {iterations!r}")


def resume_start(stage_path, sd: SceneData, contacts) -> tuple[dict, str, dict | None]:
    """Where `--resume` goes on from: a killed fit's checkpoint, else the newest version's
    snapshot, else (a stage fitted before versions) the stage's current field. Returns (start,
    "checkpoint" | "v<N>", the checkpoint or None)."""
    lp = LayerPaths.of(stage_path)
    ck = load_checkpoint(lp.checkpoint)
    if ck is not None:
        want = fingerprint(sd, contacts)
        have = ck.get("fingerprint") or {}
        if (have.get("particles"), have.get("frames")) != (want["particles"], want["frames"]):
            raise InputError(lp.checkpoint, f"fit checkpoint of {have.get('particles')} particles and "
                             f"{have.get('frames')} frames does not match the stage ({want['particles']}, "
                             f"{want['frames']}): delete it to start afresh")
        if len(ck["start"]["youngs"]) != want["particles"]:
            raise InputError(lp.checkpoint, "fit checkpoint's material field does not match the stage's particles")
        return ck["start"], "checkpoint", ck
    if not sd.reports:
        raise InputError(stage_path, "nothing to resume: the stage has no fit yet")
    newest = sd.reports[-1]
    if newest.get("snapshot"):
        return read_version_start(stage_path, newest["version"]), f"v{newest['version']}", None
    start = {"youngs": sd.youngs_modulus, "poisson": sd.poisson_ratio,
             "trajectories": {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}}
    return start, f"v{sd.current_version or newest['version']}", None


def warm_start(stage_path, sd: SceneData) -> tuple[dict, str, tuple, tuple] | None:
    """Where a refit after `effects add / remove` starts: the current version's E field, nu and
    trajectories, and the fitted values of the effects it already had. None when the stage's
    effects are the ones the current version was fitted with (or it has none). Returns (start,
    "v<N>", effects added, effects removed)."""
    from ..sim.effects import EFFECT_NAMES

    rep = sd.current_report
    if rep is None or rep.get("status") == "interrupted":
        return None
    had, now = set(rep.get("effects") or []), set(sd.effects)
    nuisance = nuisance_effects(rep)
    had -= nuisance       # a damping fitted as a nuisance (fit --nuisance-damping) is not one the user switched on
    if had == now:
        return None
    if rep.get("snapshot"):
        start = read_version_start(stage_path, int(rep["version"]))
    else:   # a stage fitted before versions: the field it shows
        start = {"youngs": sd.youngs_modulus, "poisson": sd.poisson_ratio,
                 "trajectories": {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}}
    prev = rep.get("effect_parameters") or {}
    start["effects"] = {e: dict(prev[e]) for e in (now & had) | (now & nuisance) if e in prev}
    added = tuple(e for e in EFFECT_NAMES if e in now - had)
    removed = tuple(e for e in EFFECT_NAMES if e in had - now)
    return start, f"v{rep['version']}", added, removed


def check_starts(starts) -> None:
    from ..fit.batched import START_FACTORS

    if isinstance(starts, bool) or not isinstance(starts, (int, np.integer)) or not 1 <= starts <= len(START_FACTORS):
        raise InputError("--starts", f"must be a whole number from 1 to {len(START_FACTORS)}, got {starts!r}")


def prepare_fit(stage_path, *, iterations=None, joint=True, contact_from=None, contacts=None,
                hand_masks=None, device="cpu", seed=0, resume=False, log=print, settings_overrides=None,
                yes=True, warm=True, progress=True, starts=1, warm_path: str = "both") -> FitJob:
    """Read what a fit of the stage needs. `contact_from`: a synth capture's gt/ (contacts, supports,
    T0 and hand masks from the truth); `contacts`: the caller's `ContactSet`s (with `hand_masks`, an
    optional (T, H, W) override of the stage's); neither: the stage's contacts, extracted first
    when it has none. `resume`: go on from a killed fit's checkpoint or the newest version
    (`iterations` None: the checkpoint's remaining iterations, else the default). `warm`: when the
    stage's effects differ from the current version's (`effects add / remove`), start from that
    version (`warm_start`; `iterations` None: WARM_ITERATIONS) and search the start of the effects
    just added; the effects with `fit = true` are fitted by either schedule. With
    `settings_overrides={"track_weight": W}` (W > 0) the video's point tracks are measured (cached
    next to the stage, as the report's) and count in the loss (`fit_tracks`). `starts` > 1: the
    bumps schedule from that many starts, the best kept (`fit.batched.fit_starts`; batched on a GPU,
    one by one on the CPU)."""
    check_iterations(iterations)
    check_starts(starts)
    if settings_overrides and "track_weight" in settings_overrides:
        tw = settings_overrides["track_weight"]
        if isinstance(tw, bool) or not isinstance(tw, (int, float)) or not tw >= 0:
            raise InputError("--track-weight", f"must be a number >= 0, got {tw!r}")
    stage_path = Path(stage_path)
    sd = read_scene(stage_path)
    # what can be refused is refused before extraction writes anything
    if resume and not sd.reports and not LayerPaths.of(stage_path).checkpoint.exists():
        raise InputError(stage_path, "nothing to resume: the stage has no fit yet")
    if warm_path not in ("fitted", "measured", "both"):
        raise InputError("--warm-path", f"must be fitted, measured or both, got {warm_path!r}")
    warm_from = None if (resume or not warm) else warm_start(stage_path, sd)
    default_its = WARM_ITERATIONS if warm_from is not None else DEFAULT_ITERATIONS
    fit_effects = tuple(e for e, p in sd.effects.items() if p.get("fit", True))
    # the start of an effect is searched when it is new: every fitted one on a fresh fit, the added ones on a warm start
    search = tuple(e for e in (warm_from[2] if warm_from is not None else fit_effects) if e in fit_effects
                   and not (warm_from is not None and e in warm_from[0].get("effects", {})))   # a nuisance's c: kept
    settings = FitSettings(iterations=iterations or default_its, joint=joint, seed=seed, fit_effects=fit_effects,
                           search_effects=() if resume else search)
    if settings_overrides:
        settings = dataclasses.replace(settings, **settings_overrides)
    effects = stage_effects(sd)
    if "damping" in effects:      # the user's damping: fitted as theirs (the flag adds nothing, recorded False)
        settings.nuisance_damping = False
    if settings.nuisance_damping:
        # a global damping fitted with E as a nuisance (#24): on for this fit only, its start searched; the
        # stage's effects are not touched (the report lists it: warm_start does not count it as the user's)
        effects["damping"] = {"coefficient": 0.0}
        settings.fit_effects = tuple(settings.fit_effects) + ("damping",)
        if not resume:
            settings.search_effects = tuple(settings.search_effects) + ("damping",)
    if starts > 1 and settings.schedule != "bumps":
        raise InputError("--starts", f"runs the bumps schedule's fit from several starts; the {settings.schedule} "
                         "schedule searches its own starts")
    # on the CPU the starts run one by one (on a GPU, batched, they cost about one: not counted)
    cost = settings if starts <= 1 or str(device).startswith("cuda") else \
        dataclasses.replace(settings, iterations=settings.iterations * int(starts))
    check_cost(sd, cost, device, yes=yes, stage_path=stage_path, resumed=resume or warm_from is not None)
    # past the refusals: the simulator's kernels compile on a second thread while extraction runs (#26)
    preload(device)
    obs = load_observations(sd, with_hand_masks=False)
    source = "extracted"
    if contacts is not None:
        source = "caller"
        obs.hand_masks = load_observations(sd).hand_masks if hand_masks is None else hand_masks
    elif contact_from is not None:
        contacts = true_contacts(sd, contact_from)
        obs.hand_masks = true_hand_masks(contact_from, sd.n_frames)
        source = "groundTruth"
    else:
        contacts = stage_contacts(sd)
        if not contacts:
            from .extract import extract as run_extract

            log("no contact sets on the stage: running extraction first")
            run_extract(stage_path, log=log, device=device)
            sd = read_scene(stage_path)
            contacts = stage_contacts(sd)
        obs = load_observations(sd)
    start, resumed_from, history, alt = None, "", [], None
    carried = None       # the scan's preload as the fit this one continues decided it, where the stage says nothing
    said = sd.settings.preload
    if resume:
        start, resumed_from, ck = resume_start(stage_path, sd, contacts)
        sd.settings.preload = decided_preload(sd, ck, sd.reports[-1] if sd.reports and ck is None else None)
        if ck is not None:
            history = list(ck.get("history") or [])
            if iterations is None:
                iterations = max(int(ck.get("budget") or DEFAULT_ITERATIONS) - int(ck.get("iteration") or 0), 1)
            log(f"resuming from the checkpoint of a stopped fit (iteration {ck.get('iteration')} of "
                f"{ck.get('budget')}, written {ck.get('created')}): {iterations} iterations more")
        else:
            log(f"resuming from {resumed_from}")
    elif warm_from is not None:
        start, ver, added, removed = warm_from
        resumed_from = f"warm:{ver}"
        sd.settings.preload = decided_preload(sd, None, sd.current_report)
        if warm_path in ("measured", "both") and added:
            # the previous version's path may have soaked up the effect just added (diagnose's trajectory check):
            # the hand paths start again from the measured ones, the field and the other effects warm
            measured = {k: v for k, v in start.items() if k != "trajectories"}
            if warm_path == "measured":
                start = measured
                log("warm start: the hand paths from the measured ones (--warm-path measured)")
            else:
                alt = measured
                log("warm start: twice, from the previous paths and from the measured ones; the lower final loss kept "
                    "(--warm-path both)")
        change = ", ".join([f"+{e}" for e in added] + [f"-{e}" for e in removed])
        log(f"effects changed since {ver} ({change}): warm start from {ver}'s field and trajectory, "
            f"{iterations or default_its} iterations (--fresh: a fit from scratch)")
    if said is None and sd.settings.preload is not None:
        carried = {"preload": sd.settings.preload, "unsure": None, "loss": {}, "E": {},
                   "reason": f"as the fit it continues ({resumed_from}) took the scan"}
    if iterations is not None:
        settings.iterations = int(iterations)
    if settings.track_weight > 0:
        obs.tracks = fit_tracks(sd, obs, device=device, log=log, progress=progress)
    if starts > 1 and start is not None:
        log(f"--starts {starts}: a {'resumed' if resume else 'warm-started'} fit goes on from one field; one start")
        starts = 1
    return FitJob(stage_path, sd, obs, list(contacts), effects, settings, device, start, source,
                  resumed_from, history, starts=int(starts), alt_start=alt, preload_choice=carried)


def preload(device) -> None:
    """On the CPU, the simulator's Warp modules loaded (or compiled) on a thread while the stage is
    read (`sim.kernels.preload`), so the first launches of `FitProblem` find them ready; nothing on CUDA."""
    preload_kernels(device)


def fit_tracks(sd: SceneData, obs: Observations, *, device="cpu", log=print, progress=True):
    """The video's point tracks for the fit's track term: the report's (`adapters.measured_tracks`:
    DIS flow from the Gaussians the video shows at frame 0, forward-backward checked, lost on the
    hand; cached in `<stem>.report/tracks.npz`). InputError when the video gives too few."""
    from .adapters import measured_tracks

    bar = None
    if progress:
        from tqdm import tqdm

        bar = lambda it: tqdm(it, desc="tracks", unit="frame", leave=False, dynamic_ncols=True)  # noqa: E731
    tr = measured_tracks(sd, obs, device=device, progress=bar)
    n0 = int(np.asarray(tr.valid[0], bool).sum())
    if n0 < 3:
        raise InputError(sd.path, f"--track-weight: only {n0} point tracks start on the object at frame 0 "
                         "(too little texture, or the object is not where the stage puts it)")
    held = float(np.asarray(tr.valid[1:], bool).sum(1).mean() / n0) if len(tr.valid) > 1 else 1.0
    log(f"tracks: {n0} points on the object at frame 0, {100 * held:.0f}% of them valid per later frame on average")
    return tr


def check_cost(sd: SceneData, settings: FitSettings, device: str, *, yes: bool, stage_path, resumed: bool = False):
    """The fit's estimated wall time (app/budget.py's cost model); InputError (one line, with the
    cost) for a fit that would take hours, unless `yes`."""
    return budget.check_fit_cost(int(settings.iterations), len(sd.particles_positions),
                                 int(np.prod(sd.settings.grid_resolution)), sd.settings.substeps, sd.n_frames,
                                 device, yes=yes, stage=str(stage_path),
                                 search_evals=0 if resumed else settings.search_evals,
                                 confidence_probes=settings.confidence_probes)


def make_problem(job: FitJob, contacts=None) -> FitProblem:
    """The job's FitProblem (its contacts, or `contacts`); bad contacts are the stage's fault."""
    try:
        return FitProblem(job.scene, job.observations, job.contacts if contacts is None else contacts,
                          effects=job.effects, device=job.device)
    except ValueError as exc:
        raise InputError(job.stage_path, str(exc)) from None


def run_fit(job: FitJob, *, progress=True, log=print, on_iteration=None) -> FitResult:
    """Run the optimiser on a job (the first fit of a guessed support sizes it first); the job's
    contacts become the ones the result was fitted with. `on_iteration`: the optimiser's callback."""
    uniform_e = None
    s = job.settings
    if (s.select_supports and job.source == "extracted" and job.start is None and not job.scene.reports
            and any(c.sized_by_fit for c in job.contacts)):
        # the first fit of a guessed support (no still region was in view) sizes it by what it
        # renders (a refit keeps the size the fit layer recorded)
        contacts, prob, uniform_e, tried = select_supports(lambda cs: make_problem(job, cs), job.contacts,
                                                           job.scene.particles_positions,
                                                           job.scene.settings.particle_spacing, s, log=log)
        chosen = sum(len(c.indices) for c in contacts if c.type == "fixed")
        if chosen != tried[0][1]:
            log(f"supports: {chosen} particles held ({tried[0][1]} as extracted): the lowest loss of "
                f"{len(tried)} sizes")
        job.contacts = contacts
    else:
        prob = make_problem(job)
    job.problem = prob
    choice = None
    if job.scene.settings.preload is None and job.start is None:
        # the stage does not say whether the scan carries its weight: the frames decide (fit/preload_choice.py)
        from ..fit.preload_choice import choose_preload

        choice = choose_preload(prob, s.search_evals, log=log)
        job.scene.settings.preload = choice["preload"]     # the twins, the confidence, the layer written: as chosen
        job.preload_choice = choice
        if s.schedule == "bumps":     # its start search is the choice's (the same probes): not run again
            uniform_e = choice["uniform_e"]
    result = _optimise_job(job, prob, uniform_e, progress=progress, log=log, on_iteration=on_iteration)
    if choice is not None and choice.get("probes") and not (result.model or {}).get("uniform_probes"):
        result.model = {**(result.model or {}), "uniform_probes": choice["probes"]}   # the start search's
    return record_preload(job, result)


def record_preload(job: FitJob, result: FitResult) -> FitResult:
    """The fit's decision on the scan's preload in its settings (the report; the fit layer authors
    physinteract:preload from it, usd/fit_io.py), where it made one."""
    c = job.preload_choice
    if c is not None:
        result.settings["preload"] = {k: c.get(k) for k in ("preload", "unsure", "loss", "E", "reason")}
    return result


def decided_preload(sd: SceneData, ck: dict | None, report: dict | None):
    """A resumed or warm-started fit goes on as the fit it continues took the scan (its checkpoint's or its
    version's decision) where the stage itself leaves it open; None where that fit made none."""
    if sd.settings.preload is not None:
        return sd.settings.preload
    if ck is not None and (ck.get("fingerprint") or {}).get("preload") is not None:
        return bool(ck["fingerprint"]["preload"])
    rec = ((report or {}).get("settings") or {}).get("preload")
    return bool(rec["preload"]) if isinstance(rec, dict) and "preload" in rec else None


def _optimise_job(job: FitJob, prob, uniform_e, *, progress=True, log=print, on_iteration=None) -> FitResult:
    s = job.settings
    if job.starts > 1 and job.start is None:
        from ..fit.batched import fit_starts

        return fit_starts(prob, s, job.starts, progress=progress, log=log, on_iteration=on_iteration,
                          uniform_e=uniform_e)
    if job.start is not None and job.alt_start is not None:
        return _two_warm_starts(job, prob, progress=progress, log=log, on_iteration=on_iteration)
    return optimise(prob, s, progress=progress, log=log, start=job.start, uniform_e=uniform_e,
                    on_iteration=on_iteration)


def _two_warm_starts(job: FitJob, prob, *, progress=True, log=print, on_iteration=None) -> FitResult:
    """A warm refit after `effects add` from the previous version's hand paths and from the measured ones
    (`warm_path` "both"), the lower final loss kept (the fit's own objective: on foam_bar's 16 hidden-effect
    cases the kept one had the higher masked PSNR in all 16; docs/benchmarks/diagnose_named.md, 20th
    session); its confidence estimated once, on the kept iterate."""
    from ..fit.substep import kept_rung

    s = job.settings
    quiet = dataclasses.replace(s, confidence_probes=0)
    runs = []
    for name, st in (("fitted", job.start), ("measured", job.alt_start)):
        if runs and stopping.requested():       # a stop during the first run: keep it, skip the second
            break
        with kept_rung(prob):      # each run from the substep's rung the warm start found (its hysteresis)
            r = optimise(prob, quiet, progress=progress, log=log, start=st, on_iteration=on_iteration)
        runs.append((float(r.final_loss), name, r))
        log(f"warm start from the {name} hand paths: final loss {r.final_loss:.6g}")
    loss, name, best = min(runs, key=lambda t: t[0])
    best.settings["warm_path"] = {"kept": name, "final_loss": {n: lo for lo, n, _ in runs}}
    log(f"kept the refit from the {name} hand paths (final loss {loss:.6g})")
    if s.confidence_probes > 0 and not stopping.requested():
        start = {"youngs": best.youngs, "poisson": best.poisson, "trajectories": best.trajectories,
                 "effects": {e: dict(p) for e, p in (best.effect_parameters or {}).items()}}
        conf = optimise(prob, dataclasses.replace(s, iterations=0, search_effects=()), progress=False, log=None,
                        start=start)
        best.confidence, best.confidence_gaussian = conf.confidence, conf.confidence_gaussian
        best.settings["confidence_probes"] = conf.settings.get("confidence_probes", s.confidence_probes)
    else:
        best.settings["confidence_probes"] = 0
    return best


def interaction_notes(job: FitJob, result: FitResult) -> list[str]:
    """What the fit's residual says about the interaction (`fit.interaction_check`, #23): a residual
    largest around the grasp or release frames, or at the contact, named with the override to try."""
    from ..fit.interaction_check import check_fit

    try:
        chk = check_fit(job.problem, result, job.contacts)
    except Exception as exc:  # noqa: BLE001 - a check never costs the fit
        return [f"interaction check skipped ({type(exc).__name__}: {exc})"]
    if chk is None:
        return []
    return chk["notes"] or ["interaction check: the residual is not largest around the grasp or release "
                            "frames, nor at the contact"]


def ground_notes(job: FitJob, result: FitResult) -> list[str]:
    """A note when the fitted motion rolls or tips on the ground (`fit.ground_roll`: the grid nodes' ground, the
    default, brakes a roll, so the E of such a clip is likely biased; #24). None with the ground at the particles
    (PHYSINTERACT_GROUND=penalty: `simulation.GROUND_CONTACT`), which lets a ball roll on."""
    from .. import simulation
    from ..fit.ground_roll import roll_note

    if simulation.GROUND_CONTACT == "penalty":
        return []
    sim = getattr(job.problem, "sim", None)
    ground = (getattr(sim, "effects", None) or {}).get("ground")
    if ground is None or result.positions is None or not len(result.positions):
        return []
    height = (result.effect_parameters or {}).get("ground", {}).get("height", ground.get("height", 0.0))
    try:
        note = roll_note(result.positions, float(height), float(sim.grid.dx))
    except Exception as exc:  # noqa: BLE001 - a check never costs the fit
        return [f"ground roll check skipped ({type(exc).__name__}: {exc})"]
    return [note] if note else []


def _finish_from(job: FitJob, tracker: FitTracker, log) -> FitResult | None:
    """A stop that landed outside the optimiser's loop (in its last pass or its confidence
    estimate): the tracker's best iterate, through the optimiser's last pass alone."""
    start = tracker.start()
    if start is None or job.problem is None:
        return None
    log("stopped after the iterations: writing the best iterate without its confidence")
    s = dataclasses.replace(job.settings, iterations=0, confidence_probes=0)
    r = optimise(job.problem, s, progress=False, log=None, start=start)
    r.loss_history = list(tracker.history)
    r.interrupted = not (tracker.loop_done or stopping.is_finishing())   # (a converged loop ends early)
    return r


def fit(stage_path, *, iterations=None, joint=True, contact_from=None, contacts=None, hand_masks=None,
        device="cpu", seed=0, resume=False, progress=True, log=print, settings_overrides=None, keep_best=True,
        checkpoint_every=CHECKPOINT_EVERY, yes=True, warm=True, starts=1, warm_path: str = "both") -> FitOutcome:
    """Fit the stage's material field and trajectory to its video; write it as a new version
    (scene.fit.usdc and `<stem>.versions/v<N>.usdc`). `warm_path`: where a warm start after `effects add`
    takes the hand paths from: "both" (default: from the previous version's and from the measured ones, the
    lower final loss kept, `_two_warm_starts`; twice the refit's cost), "fitted" or "measured" (#22). `keep_best`: the new version becomes current
    only if its loss is below the current one's; `checkpoint_every`: iterations between
    checkpoints (0: none); `yes`: go on even when the cost model says the fit takes hours; `warm`: a
    refit after the stage's effects changed starts from the current version (`prepare_fit`);
    `iterations` None: DEFAULT_ITERATIONS, or WARM_ITERATIONS for such a warm start. `starts` > 1:
    that many fits from different starts, the lowest final loss kept, every start's loss in the
    version's material model ("starts"; `fit.batched.fit_starts`).
    SIGINT / SIGTERM stop it cleanly (the best iterate is written, `outcome.stopped_by` says so);
    a second signal quits without writing (the checkpoint stays)."""
    check_iterations(iterations)
    if checkpoint_every is None or int(checkpoint_every) < 0:
        raise InputError("--checkpoint-every", f"must be >= 0, got {checkpoint_every!r}")
    cpu_threads(device)
    t_prep = time.perf_counter()
    job = prepare_fit(stage_path, iterations=iterations, joint=joint, contact_from=contact_from, contacts=contacts,
                      hand_masks=hand_masks, device=device, seed=seed, resume=resume, log=log,
                      settings_overrides=settings_overrides, yes=yes, warm=warm, progress=progress, starts=starts,
                      warm_path=warm_path)
    lp = LayerPaths.of(job.stage_path)
    phases = {"prepare": round(time.perf_counter() - t_prep, 3)}   # reading the stage, the contacts, the settings
    probes = int(job.settings.confidence_probes)
    names = [c.name for c in job.contacts]   # replaced by the simulation's slot names once built
    tracker = FitTracker(lp.checkpoint if checkpoint_every else None, fingerprint(job.scene, job.contacts),
                         int(job.settings.iterations), names, every=int(checkpoint_every or 0),
                         history=job.history, resumed_from=job.resumed_from)

    def on_iteration(it, loss, mat, trajs):
        if job.problem is not None and tracker.names is names:
            tracker.names = job.problem.sim.slot_names()
        tracker.fingerprint["preload"] = job.scene.settings.preload    # a resume starts the scan the same way
        tracker(it, loss, mat, trajs)

    def on_stop():  # in the signal handler: a stopped fit skips its confidence estimate
        job.settings.confidence_probes = 0

    with stopping.graceful(on_stop=on_stop):
        late = False
        t_run = time.perf_counter()
        try:
            result = run_fit(job, progress=progress, log=log, on_iteration=on_iteration)
            # building the problem (simulation, renderer, observations) and what else ran outside the fit's clock
            phases["problem"] = round(max(time.perf_counter() - t_run - float(result.runtime_s), 0.0), 3)
        except stopping.StopRequested as stop:
            result, late = _finish_from(job, tracker, log), True
            if result is None:
                log(f"{stop.signal}: stopped before the first iteration; nothing written")
                raise KeyboardInterrupt from None
            record_preload(job, result)
        stopped_by = stopping.requested()
        if not late and not stopped_by:
            t_notes = time.perf_counter()
            for line in interaction_notes(job, result) + ground_notes(job, result):
                log(line)
            phases["notes"] = round(time.perf_counter() - t_notes, 3)
        conf_ok = probes > 0 and not late and int(result.settings.get("confidence_probes", 0)) > 0
        result.settings["confidence_probes"] = probes   # what was asked; confidenceEstimated says what ran
        if job.history:   # resumed from a checkpoint: the version holds the whole fit's history
            result.loss_history = list(job.history) + list(result.loss_history)
        t_write = time.perf_counter()
        info = write_fit_layer(job.stage_path, job.scene, result, job.contacts, keep_best=keep_best,
                               effect_parameters=result.effect_parameters,
                               confidence_estimated=conf_ok, resumed_from=job.resumed_from)
        remove_checkpoint(lp.checkpoint)
        phases["write"] = round(time.perf_counter() - t_write, 3)
    job.settings.confidence_probes = probes
    return FitOutcome(result, info["version"], info["layer"], job.contacts, current=info["current"],
                      reason=info["reason"], snapshot=info["snapshot"], stopped_by=stopped_by,
                      confidence_estimated=conf_ok, phases=phases)
