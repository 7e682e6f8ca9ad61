"""Step 5 of the diagnosis: a short warm-started refit of a top candidate, accepted only if the
loss on held-back frames falls.

A physical effect is refitted with the fit's own ladder machinery (`fit.ladder._Ladder`: AdamW on
the regions' log E, the trajectory and the effect's log-parametrised parameters, the ladder's
held-back frames left out), warm-started at the fitted field and trajectory and at the probe's
value of the effect. A non-physical cause is judged on its probe taken for real (the changed
timing, contact, grasp or support, with the base parameters re-adjusted by their linear step).
Both report the drop of the diagnosis's loss (`residual.loss`) on all frames beyond what the base
parameters' own (linear) step gives, as the prediction is, and judge it on the held-back frames."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import SimulationError
from .core import PHYSICAL, CandidateResult, Diagnosis, _pad, prior_residual
from .residual import ImageResidual, loss

_POSITIVE = {"coefficient", "yieldStress", "friction", "modulus", "relaxationTime"}


def held_back_frames(T: int, every: int = 4, res: ImageResidual | None = None, column=None) -> list[int]:
    """Frames left out of the refit to judge it. With the candidate's column: every other frame
    among those where the candidate changes the model most (its column's energy above the median:
    frames it cannot change cannot judge it); else the ladder's every `every`-th frame."""
    from ..fit.ladder import _frames

    if res is None or column is None or T < 6:
        return _frames(T, every)[1]
    e = np.square(np.asarray(column)).reshape(res.shape).sum((1, 2, 3))
    order = [res.frames[i] for i in np.argsort(-e) if e[i] > 0]
    strong = sorted(order[: max(2, len(order) // 2)])
    return strong[1::2] if len(strong) > 1 else strong


def _frame_mask(res: ImageResidual, frames) -> np.ndarray:
    return np.isin(res.frame_of(), list(frames))


def refit_effect(diag: Diagnosis, cr: CandidateResult, *, iterations: int = 8, holdout_every: int = 4, log=None):
    """Refit `cr`'s physical effect (module doc). Fills cr.realized_loss_drop, cr.accepted and
    cr.estimate (the refitted parameters). Returns the refitted state {"E", "nu", "trajectories",
    "effects"} or None."""
    from ..fit.ladder import _Ladder
    from ..fit.optimize import FitSettings

    ctx = diag._ctx
    prob, base, res, r0 = ctx["prob"], ctx["base"], ctx["res"], ctx["r0"]
    if cr.effect not in PHYSICAL or cr.effect not in prob.effects:
        return None
    col = cr.probes[cr.best].column if cr.best >= 0 else None
    val = held_back_frames(prob.T, holdout_every, res, col)
    s = FitSettings(iterations=int(iterations), joint=True, fit_effects=(cr.effect,), holdout_every=holdout_every,
                    confidence_probes=0)
    lad = _Ladder(prob, s, log, progress=False)
    labels = base.labels if base.labels is not None else np.zeros(len(prob.x0), np.int64)
    E = base.E.detach().cpu().numpy()
    lad.labels = labels.astype(np.int64)
    lad.mat.set_regions(lad.labels)
    lad.mat.set_region_log_e(np.array([np.log(np.median(E[labels == r])) for r in range(int(labels.max()) + 1)]))
    nu0 = float(base.nu.median())
    with torch.no_grad():
        lad.mat.w_nu.copy_(torch.full_like(lad.mat.w_nu, float(math.log(nu0 / (lad.mat.nu_max - nu0)))))
    start = dict(cr.estimate)
    for p, raw in lad.effect_raw[cr.effect].items():
        v = start.get(p)
        if v is None or not math.isfinite(float(v)):
            continue
        v = float(v)
        if p in _POSITIVE:
            if v <= 0:
                continue
            v = math.log(v)
        else:
            v = v / prob.traj_scale
        with torch.no_grad():
            raw.copy_(torch.tensor(v, dtype=raw.dtype, device=raw.device))
    train = [k for k in range(1, prob.T) if k not in val]
    try:
        lad.optimise(int(iterations), train, fit_nu=False, fit_traj=True)
        eff = {e: {p: float(v.detach()) for p, v in ps.items()} for e, ps in (lad.effects() or {}).items()}
        full = {e: dict(p) for e, p in base.effects.items()}
        for e, ps in eff.items():
            full.setdefault(e, {}).update(ps)
        with torch.no_grad():
            x, F = prob.simulate(lad.mat.youngs().detach(), lad.mat.poisson().detach(),
                                 [t.detach() for t in lad.trajs], effects=full)
        run = ctx["run"]
        p1 = prior_residual(prob, base, [t.detach() for t in lad.trajs]) if len(run.p0) else np.zeros(0)
        sc = float(ctx["prior"].get("row_scale", 0.0))
        r1 = res(x, F)
        r1a = run.aug(r1, p1 * sc)
    except SimulationError as exc:
        cr.note = f"refit failed: {exc}"
        cr.accepted = False
        return None
    m = _frame_mask(res, val) if val else np.ones(len(r0), bool)
    # the drop beyond what the base parameters alone would give (their linear step), as predicted
    J, r0a = diag._J, ctx["r0a"]
    a0, *_ = np.linalg.lstsq(J, -r0a, rcond=None)
    b0 = r0a + J @ a0
    cr.realized_loss_drop = run.aloss(b0) - run.aloss(r1a)
    v0, v1 = loss(r0[m]), loss(r1[m])
    cr.accepted = bool(v1 < v0)
    cr.estimate = {**eff.get(cr.effect, {})}
    cr.note = (f"refit ({iterations} iterations, held-back frames {val}): held-back loss {v0:.3e} -> {v1:.3e}; "
               f"loss {loss(r0):.3e} -> {loss(r1):.3e} ({run.aloss(b0):.3e} with the base's own step alone)"
               + ("" if cr.accepted else ": not accepted"))
    return {"E": lad.mat.youngs().detach(), "nu": lad.mat.poisson().detach(),
            "trajectories": [t.detach() for t in lad.trajs], "effects": eff}


def judge_probe(diag: Diagnosis, cr: CandidateResult, holdout_every: int = 4) -> None:
    """A non-physical cause (or `heterogeneity`): its best probe taken for real, the base
    parameters re-adjusted by their linear step; realised drop on all frames, accepted when the
    held-back frames' loss falls too."""
    from .core import realised_gauss_newton

    ctx = diag._ctx
    prob, res, r0, J, run = ctx["prob"], ctx["res"], ctx["r0a"], diag._J, ctx["run"]
    if cr.best < 0:
        return
    p = cr.probes[cr.best]
    col = _pad(p.column, len(r0))
    if cr.effect in ("heterogeneity", "camera:time_offset", "camera:depth_scale"):
        if cr.effect == "heterogeneity":
            d = realised_gauss_newton(diag, cr)
            cr.realized_loss_drop = d
            cr.accepted = None if d is None else bool(d > 0)
            return
        r1 = r0 + col * cr.step                 # render-only / gravity: the linear step itself
    else:
        r1 = r0 + col                           # the probe itself (amplitude 1)
    val = held_back_frames(prob.T, holdout_every, res, p.column)
    a0, *_ = np.linalg.lstsq(J, -r0, rcond=None)
    a1, *_ = np.linalg.lstsq(J, -r1, rcond=None)
    b0, b1 = r0 + J @ a0, r1 + J @ a1
    cr.realized_loss_drop = run.aloss(b0) - run.aloss(b1)
    n = run.n_img or len(r0)
    m = _frame_mask(res, val) if val else np.ones(n, bool)
    cr.accepted = bool(loss(b1[:n][m]) < loss(b0[:n][m]))


__all__ = ["refit_effect", "judge_probe", "held_back_frames"]


def refit_base(prob, base, factor: float, *, iterations: int = 8, res: ImageResidual | None = None, log=None):
    """A short refit of the base model (no new effect; the E field's regions, the path kept) started
    at the base's E field x `factor` (per region, its median), so that a base fit stuck in a local
    minimum is not mistaken for missing physics. Returns {"factor", "E", "nu", "loss" (the
    diagnosis's loss, `residual.loss`), "fit_loss"}; loss inf when the simulation fails."""
    from ..fit.ladder import _Ladder
    from ..fit.optimize import FitSettings

    res = res or ImageResidual(prob)
    s = FitSettings(iterations=int(iterations), joint=False, holdout_every=0, confidence_probes=0)
    lad = _Ladder(prob, s, log, progress=False)
    labels = base.labels if base.labels is not None else np.zeros(len(prob.x0), np.int64)
    E = base.E.detach().cpu().numpy()
    lad.labels = labels.astype(np.int64)
    lad.mat.set_regions(lad.labels)
    st = prob.scene.settings
    le = [math.log(float(np.clip(factor * np.median(E[labels == r]), 1.001 * st.youngs_min, 0.999 * st.youngs_max)))
          for r in range(int(labels.max()) + 1)]
    lad.mat.set_region_log_e(np.array(le))
    nu0 = float(base.nu.median())
    with torch.no_grad():
        lad.mat.w_nu.copy_(torch.full_like(lad.mat.w_nu, float(math.log(nu0 / (lad.mat.nu_max - nu0)))))
    out = {"factor": float(factor), "E": None, "nu": None, "loss": math.inf, "fit_loss": math.inf}
    try:
        out["fit_loss"] = float(lad.optimise(int(iterations), list(range(1, prob.T)), fit_nu=False, fit_traj=False))
        E1, nu1 = lad.mat.youngs().detach(), lad.mat.poisson().detach()
        with torch.no_grad():
            x, F = prob.simulate(E1, nu1, None, effects=base.effects)
        out.update(E=E1, nu=nu1, loss=loss(res(x, F)))
    except SimulationError as exc:
        out["note"] = f"refit failed: {exc}"
    return out


__all__ += ["refit_base"]
