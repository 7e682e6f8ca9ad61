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

import time
from pathlib import Path

import numpy as np

from .jsonsafe import json_safe
from ..diagnose import CANDIDATES, PHYSICAL, BaseState, DiagnoseSettings, conclude, describe, diagnose_problem
from ..diagnose.refit import judge_probe, refit_effect
from ..errors import InputError
from .adapters import effects_with_fitted, load_observations, read_scene, stage_contacts


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


def region_labels(E: np.ndarray, max_regions: int = 8) -> np.ndarray | None:
    """Regions of a piecewise-constant field (its distinct values), None for a smooth field."""
    vals, inv = np.unique(np.round(np.log(np.maximum(E, 1e-30)), 6), return_inverse=True)
    return inv.astype(np.int64) if len(vals) <= max_regions else None


def parse_candidates(spec) -> tuple:
    if spec is None:
        return CANDIDATES
    names = tuple(s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip())
    bad = [n for n in names if n not in CANDIDATES]
    if bad:
        raise InputError("--candidates", f"unknown candidate {bad[0]!r}; known: {', '.join(CANDIDATES)}")
    return names


def diagnose(stage_path, *, refit: int = 3, refit_iterations: int = 8, candidates=None, write_stage: bool = True,
             device: str = "cpu", dtype: str = "float32", seed: int = 0, max_pixels: int = 6000,
             progress: bool = True, log=print) -> dict:
    """Diagnose the stage's current fit (module doc); returns the JSON-able diagnosis."""
    import torch

    from ..fit.problem import FitProblem

    t0 = time.perf_counter()
    stage_path = Path(stage_path)
    if refit is None or isinstance(refit, bool) or int(refit) < 0:
        raise InputError("--refit", f"must be a whole number >= 0, got {refit!r}")
    if refit_iterations is None or int(refit_iterations) < 1:
        raise InputError("--refit-iterations", f"must be a whole number >= 1, got {refit_iterations!r}")
    cands = parse_candidates(candidates)
    sd = read_scene(stage_path)
    if not sd.reports or sd.current_report is None:
        raise InputError(stage_path, "has no fit to diagnose: run `physinteract-usd fit` first")
    version = int(sd.current_version or sd.current_report["version"])
    obs = load_observations(sd)
    fitted = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    contacts = [c.replace(trajectory=np.asarray(fitted[c.name])) if c.name in fitted and c.is_interaction else c
                for c in stage_contacts(sd)]
    present = effects_with_fitted(sd)
    skipped = [e for e in cands if e in present]
    cands = tuple(e for e in cands if e not in present)
    try:
        prob = FitProblem(sd, obs, contacts, effects=superset_effects(sd, present), device=device, dtype=dtype)
    except ValueError as exc:
        raise InputError(stage_path, str(exc)) from None
    st = sd.settings
    E = torch.as_tensor(np.clip(sd.youngs_modulus, st.youngs_min, st.youngs_max), dtype=prob.tdtype, device=prob.tdev)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, st.poisson_max), dtype=prob.tdtype, device=prob.tdev)
    base = BaseState(E, nu, superset_effects(sd, present), region_labels(sd.youngs_modulus))
    settings = DiagnoseSettings(candidates=cands, seed=seed, max_pixels=max_pixels)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = lambda it, desc: tqdm(it, desc=desc, unit="candidate", leave=False, dynamic_ncols=True)  # noqa: E731
    diag = diagnose_problem(prob, base, settings, log=log, progress=bar, evidence=describe)
    for e in skipped:
        diag.notes.append(f"{e} is already in the model (fitted): not a candidate")
    top = [c for c in diag.significant][: int(refit)]
    for cr in top:
        if cr.effect in PHYSICAL:
            log(f"refitting with {cr.effect} ({refit_iterations} iterations, warm-started)")
            refit_effect(diag, cr, iterations=int(refit_iterations), log=None)
        else:
            judge_probe(diag, cr)
    conclude(diag)
    for cr in diag.significant:       # the evidence again: the refit's estimate is the better number
        try:
            cr.evidence = describe(cr.effect, cr, diag._ctx)
        except Exception as exc:  # noqa: BLE001
            cr.evidence = f"(evidence unavailable: {exc})"
    diag.cost["seconds"] = time.perf_counter() - t0
    out = json_safe(diag.to_dict())
    out.update({"stage": str(stage_path), "version": version})
    if write_stage:
        from ..usd.diagnosis_io import write_diagnosis

        out["stage_layer"] = write_diagnosis(stage_path, sd.fps, sd.n_frames, version, out)
    return out
