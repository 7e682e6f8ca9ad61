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
from .core import PHYSICAL, CandidateResult, Diagnosis
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
        r1 = res(x, F)
    except SimulationError as exc:
        cr.note = f"refit failed: {exc}"
        cr.accepted = False
        return None
    m = _frame_mask(res, val) if val else np.ones(len(r0), bool)
    # the drop beyond what the base parameters alone would give (their linear step), as predicted
    J = diag._J
    a0, *_ = np.linalg.lstsq(J, -r0, rcond=None)
    b0 = r0 + J @ a0
    cr.realized_loss_drop = loss(b0) - loss(r1)
    v0, v1 = loss(r0[m]), loss(r1[m])
    cr.accepted = bool(v1 < v0)
    cr.estimate = {**eff.get(cr.effect, {})}
    cr.note = (f"refit ({iterations} iterations, held-back frames {val}): held-back loss {v0:.3e} -> {v1:.3e}; "
               f"loss {loss(r0):.3e} -> {loss(r1):.3e} ({loss(b0):.3e} with the base's own step alone)"
               + ("" if cr.accepted else ": not accepted"))
    return {"E": lad.mat.youngs().detach(), "nu": lad.mat.poisson().detach(),
            "trajectories": [t.detach() for t in lad.trajs], "effects": eff}


def judge_probe(diag: Diagnosis, cr: CandidateResult, holdout_every: int = 4) -> None:
    """A non-physical cause (or `heterogeneity`): its best probe taken for real, the base
    parameters re-adjusted by their linear step; realised drop on all frames, accepted when the
    held-back frames' loss falls too."""
    from .core import realised_gauss_newton

    ctx = diag._ctx
    prob, res, r0, J = ctx["prob"], ctx["res"], ctx["r0"], diag._J
    if cr.best < 0:
        return
    p = cr.probes[cr.best]
    if cr.effect in ("heterogeneity", "camera:time_offset", "camera:depth_scale"):
        if cr.effect == "heterogeneity":
            d = realised_gauss_newton(diag, cr)
            cr.realized_loss_drop = d
            cr.accepted = None if d is None else bool(d > 0)
            return
        r1 = r0 + p.column * cr.step           # render-only / gravity: the linear step itself
    else:
        r1 = r0 + p.column                      # the probe itself (amplitude 1)
    val = held_back_frames(prob.T, holdout_every, res, p.column)
    a0, *_ = np.linalg.lstsq(J, -r0, rcond=None)
    a1, *_ = np.linalg.lstsq(J, -r1, rcond=None)
    b0, b1 = r0 + J @ a0, r1 + J @ a1
    cr.realized_loss_drop = loss(b0) - loss(b1)
    m = _frame_mask(res, val) if val else np.ones(len(r0), bool)
    cr.accepted = bool(loss(b1[m]) < loss(b0[m]))


__all__ = ["refit_effect", "judge_probe", "held_back_frames"]
