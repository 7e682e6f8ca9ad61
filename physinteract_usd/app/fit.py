"""`fit`: the joint fit of the material field and the interaction trajectory to the stage's video,
written into the stage's fit layer as a new model version.

The steps, each usable on its own (benchmarks and experiments swap a part):
1. `prepare_fit`: read the stage, its observations, its contacts (running extraction when it has
   none; or the ground truth's with `contact_from`; or the caller's `contacts`), effects, settings
   and the resumed start -> a `FitJob`;
2. `run_fit`: size a guessed support on the first fit, then the optimiser (`fit.fit`) -> FitResult;
3. `write_fit_layer` (usd.fit_io) -> the version written.
`fit` runs the three and returns a `FitOutcome`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..devices import cpu_threads
from ..errors import InputError
from ..fit import FitProblem, FitResult, FitSettings
from ..fit import fit as optimise
from ..fit.optimize import select_supports
from ..fit.problem import Observations
from ..scene import SceneData
from ..usd.fit_io import write_fit_layer
from .adapters import load_observations, read_scene, stage_contacts, stage_effects, true_contacts, true_hand_masks


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


@dataclass
class FitOutcome:
    result: FitResult
    version: int
    layer: str
    contacts: list = field(default_factory=list)

    def summary(self) -> dict:
        """The JSON-able summary `fit --json` prints."""
        r = self.result
        fm = r.frame_metrics
        return {"version": self.version, "layer": self.layer, "iterations": len(r.loss_history),
                "final_loss": r.final_loss, "runtime_s": r.runtime_s, "device": r.device,
                "interrupted": r.interrupted,
                "psnr": float(np.mean([min(f["psnr"], 100) for f in fm])),
                "psnr_masked": float(np.nanmean([min(f["psnr_masked"], 100) for f in fm])),
                "ssim": float(np.mean([f["ssim"] for f in fm])), "iou": float(np.mean([f["iou"] for f in fm])),
                "youngs_modulus_pa": {"min": float(r.youngs.min()), "median": float(np.median(r.youngs)),
                                      "max": float(r.youngs.max())},
                "confidence_mean": float(r.confidence.mean())}


def prepare_fit(stage_path, *, iterations=60, joint=True, contact_from=None, contacts=None, hand_masks=None,
                device="cpu", seed=0, resume=False, log=print, settings_overrides=None) -> FitJob:
    """Read what a fit of the stage needs. `contact_from`: a synth capture's gt/ (contacts, supports,
    T0 and hand masks from the truth); `contacts`: the caller's `ContactSet`s (with `hand_masks`, an
    optional (T, H, W) override of the stage's); neither: the stage's contacts, extracted first
    when it has none."""
    stage_path = Path(stage_path)
    sd = read_scene(stage_path)
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
    settings = FitSettings(iterations=iterations, joint=joint, seed=seed)
    if settings_overrides:
        settings = dataclasses.replace(settings, **settings_overrides)
    start = None
    if resume:
        if not sd.reports:
            raise InputError(stage_path, "nothing to resume: the stage has no fit yet")
        start = {"youngs": sd.youngs_modulus, "poisson": sd.poisson_ratio,
                 "trajectories": {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}}
    return FitJob(stage_path, sd, obs, list(contacts), stage_effects(sd), settings, device, start, source)


def make_problem(job: FitJob, contacts=None) -> FitProblem:
    """The job's FitProblem (its contacts, or `contacts`); bad contacts are the stage's fault."""
    try:
        return FitProblem(job.scene, job.observations, job.contacts if contacts is None else contacts,
                          effects=job.effects, device=job.device)
    except ValueError as exc:
        raise InputError(job.stage_path, str(exc)) from None


def run_fit(job: FitJob, *, progress=True, log=print) -> FitResult:
    """Run the optimiser on a job (the first fit of a guessed support sizes it first); the job's
    contacts become the ones the result was fitted with."""
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
    return optimise(prob, s, progress=progress, log=log, start=job.start, uniform_e=uniform_e)


def fit(stage_path, *, iterations=60, joint=True, contact_from=None, contacts=None, hand_masks=None, device="cpu",
        seed=0, resume=False, progress=True, log=print, settings_overrides=None) -> FitOutcome:
    """Fit the stage's material field and trajectory to its video; write scene.fit.usdc."""
    cpu_threads(device)
    job = prepare_fit(stage_path, iterations=iterations, joint=joint, contact_from=contact_from, contacts=contacts,
                      hand_masks=hand_masks, device=device, seed=seed, resume=resume, log=log,
                      settings_overrides=settings_overrides)
    result = run_fit(job, progress=progress, log=log)
    info = write_fit_layer(job.stage_path, job.scene, result, job.contacts)
    return FitOutcome(result, info["version"], info["layer"], job.contacts)
