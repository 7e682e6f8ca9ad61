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


def held_back_test(diag: Diagnosis, r_ref: np.ndarray, r_new: np.ndarray, m: np.ndarray) -> dict:
    """`score.paired_drop` of the held-back elements `m` of two image residuals, over the diagnosis's
    blocks (a few frames x an image tile, as its score tests): the drop of the held-back loss from
    `r_ref` to `r_new`, its standard error and the one-sided p-value."""
    from . import score as S

    ctx = diag._ctx
    s = ctx.get("settings")
    blocks = ctx.get("blocks")
    if blocks is None:                                   # a diagnosis made without them: one block a frame
        blocks = ctx["res"].frame_of().astype(np.int64)
        nb = int(blocks.max()) + 1
    else:
        nb = int(ctx["n_blocks"])
    return S.paired_drop(r_ref[m], r_new[m], blocks[m], nb, n_flips=getattr(s, "n_flips", 4000),
                         seed=getattr(s, "seed", 0))


def _alpha(diag: Diagnosis) -> float:
    return float(getattr(diag._ctx.get("settings"), "alpha", 0.05))


def _accept(diag: Diagnosis, cr: CandidateResult, refs: list, r1: np.ndarray, m: np.ndarray) -> None:
    """Acceptance on the held-back frames: a one-sided paired test (`held_back_test`) against each
    model without the candidate in `refs` [(name, image residual)]; accepted when every p-value is
    below alpha (an intersection-union test: below the base's and the control's at level alpha). The
    drop and its standard error are reported against the reference with the lower held-back loss."""
    tests = [(name, held_back_test(diag, r, r1, m)) for name, r in refs]
    # the lower reference: the smallest drop (the held-back loss to beat is the lower one)
    low = min(tests, key=lambda t: t[1]["drop"])
    p = max(t[1]["p"] for t in tests)
    cr.held_back_drop, cr.held_back_se, cr.held_back_p = low[1]["drop"], low[1]["se"], p
    cr.accepted = bool(p < _alpha(diag) and low[1]["drop"] > 0)
    cr._held = (m, r1)


def _refit(diag: Diagnosis, effect: str | None, start: dict, val: list, iterations: int, holdout_every: int, log):
    """A short warm-started refit of the base (regions' log E, the trajectory) with `effect`'s
    parameters too (None: the base alone, the control every candidate's refit is judged against),
    on the frames not in `val`. Returns (image residual, augmented residual, state) or raises
    SimulationError."""
    from ..fit.ladder import _Ladder
    from ..fit.optimize import FitSettings

    ctx = diag._ctx
    prob, base, res = ctx["prob"], ctx["base"], ctx["res"]
    s = FitSettings(iterations=int(iterations), joint=True, fit_effects=(effect,) if effect else (),
                    holdout_every=holdout_every, confidence_probes=0)
    lad = _Ladder(prob, s, log, progress=False)
    labels = base.labels if base.labels is not None else np.zeros(len(prob.x0), np.int64)
    E = base.E.detach().cpu().numpy()
    lad.labels = labels.astype(np.int64)
    lad.mat.set_regions(lad.labels)
    lad.mat.set_region_log_e(np.array([np.log(np.median(E[labels == r])) for r in range(int(labels.max()) + 1)]))
    nu0 = float(base.nu.median())
    with torch.no_grad():
        lad.mat.w_nu.copy_(torch.full_like(lad.mat.w_nu, float(math.log(nu0 / (lad.mat.nu_max - nu0)))))
    for p, raw in (lad.effect_raw.get(effect, {}) if effect else {}).items():
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
    lad.optimise(int(iterations), train, fit_nu=False, fit_traj=True)
    eff = {e: {p: float(v.detach()) for p, v in ps.items()} for e, ps in (lad.effects() or {}).items()}
    full = {e: dict(p) for e, p in base.effects.items()}
    for e, ps in eff.items():
        full.setdefault(e, {}).update(ps)
    trajs = [t.detach() for t in lad.trajs]
    with torch.no_grad():
        x, F = prob.simulate(lad.mat.youngs().detach(), lad.mat.poisson().detach(), trajs, effects=full)
    run = ctx["run"]
    p1 = prior_residual(prob, base, trajs) if len(run.p0) else np.zeros(0)
    sc = float(ctx["prior"].get("row_scale", 0.0))
    r1 = res(x, F)
    state = {"E": lad.mat.youngs().detach(), "nu": lad.mat.poisson().detach(), "trajectories": trajs, "effects": eff}
    return r1, run.aug(r1, p1 * sc), state


def refit_null(diag: Diagnosis, val: list, *, iterations: int = 8, holdout_every: int = 4, log=None) -> dict | None:
    """The control of the candidates' refits: the base refitted alike (the same iterations, the same
    held-back frames `val`), with no new effect. A few iterations from the fit move E and the path
    too, and lower the held-back loss by themselves where the base was not quite converged: a
    candidate counts only for what it adds beyond that. Returns {"frames", "held_back_loss",
    "loss", "aloss"} or None when the simulation fails."""
    ctx = diag._ctx
    res, run = ctx["res"], ctx["run"]
    try:
        r1, r1a, _ = _refit(diag, None, {}, val, iterations, holdout_every, log)
    except SimulationError:
        return None
    m = _frame_mask(res, val) if val else np.ones(len(r1), bool)
    return {"frames": list(val), "held_back_loss": loss(r1[m]), "loss": loss(r1), "aloss": run.aloss(r1a),
            "residual": r1}


def group_frames(diag: Diagnosis, crs: list, holdout_every: int = 4) -> list[int]:
    """Held-back frames shared by candidates compared with each other (a confusable pair): every other
    frame among those where the candidates together (each column normalised) change the model most."""
    ctx = diag._ctx
    res, prob = ctx["res"], ctx["prob"]
    cols = [np.asarray(c.probes[c.best].column) for c in crs if c.best >= 0 and c.probes]
    if not cols:
        return held_back_frames(prob.T, holdout_every)
    e = 0.0
    for col in cols:
        col = col[: res.n]
        nrm = float(np.sum(np.square(col)))
        if nrm > 0:
            e = e + np.square(col) / nrm
    return held_back_frames(prob.T, holdout_every, res, np.sqrt(e) if np.ndim(e) else None)


def refit_effect(diag: Diagnosis, cr: CandidateResult, *, iterations: int = 8, holdout_every: int = 4, log=None,
                 frames: list | None = None, null: dict | None = None):
    """Refit `cr`'s physical effect (module doc). Fills cr.realized_loss_drop, cr.accepted,
    cr.held_back_drop and cr.estimate (the refitted parameters). `frames`: the held-back frames
    (default: from the candidate's own column); `null`: the base refitted alike on those frames
    (`refit_null`): the held-back loss to beat is the lower of the base's and that one's. Returns the refitted
    state {"E", "nu", "trajectories", "effects"} or None."""
    ctx = diag._ctx
    prob, res, r0 = ctx["prob"], ctx["res"], ctx["r0"]
    if cr.effect not in PHYSICAL or cr.effect not in prob.effects:
        return None
    col = cr.probes[cr.best].column if cr.best >= 0 else None
    val = list(frames) if frames is not None else held_back_frames(prob.T, holdout_every, res, col)
    try:
        r1, r1a, state = _refit(diag, cr.effect, dict(cr.estimate), val, iterations, holdout_every, log)
    except SimulationError as exc:
        cr.note = f"refit failed: {exc}"
        cr.accepted = False
        return None
    run = ctx["run"]
    m = _frame_mask(res, val) if val else np.ones(len(r0), bool)
    # the drop beyond what the base parameters alone would give (their linear step), as predicted
    J, r0a = diag._J, ctx["r0a"]
    a0, *_ = np.linalg.lstsq(J, -r0a, rcond=None)
    b0 = r0a + J @ a0
    cr.realized_loss_drop = run.aloss(b0) - run.aloss(r1a)
    # the loss to beat: the best model without the candidate, the base as it is or refitted alike (a
    # refit on the training frames can also raise the held-back loss: then the base itself is the bar)
    v1 = loss(r1[m])
    refs = [("base", r0)] + ([] if null is None or null.get("residual") is None else [("control", null["residual"])])
    _accept(diag, cr, refs, r1, m)
    cr.estimate = {**state["effects"].get(cr.effect, {})}
    ref = "the base's" if null is None else f"the base refitted alike: {float(null['held_back_loss']):.3e}"
    cr.note = (f"refit ({iterations} iterations, held-back frames {val}): held-back loss {loss(r0[m]):.3e} -> "
               f"{v1:.3e} ({ref}); drop {cr.held_back_drop:.3g} +- {cr.held_back_se:.2g} (paired test over "
               f"blocks, p = {cr.held_back_p:.3g}); loss {loss(r0):.3e} -> {loss(r1):.3e} ({run.aloss(b0):.3e} "
               "with the base's own step alone)"
               + ("" if cr.accepted else ": not accepted (the held-back drop is within the frames' own spread)"
                  if cr.held_back_drop > 0 else ": not accepted"))
    return state


def compare_rivals(diag: Diagnosis, cr: CandidateResult, group: list):
    """Which of a confusable group (`cr`, the selected one, and its rivals, refitted on the same
    held-back frames) explains the held-back frames: an accepted rival replaces an accepted `cr`
    only when its held-back residual is below `cr`'s by a paired test at alpha (`held_back_test`:
    not by a difference within the frames' own spread); when `cr` was not accepted, the accepted
    rival with the largest held-back drop. Each rival's test against `cr` goes in its `rival_test`
    ({"against", "drop", "se", "p"}). Returns the winner (`cr` when none)."""
    ok = [c for c in group if c.accepted and getattr(c, "_held", None) is not None]
    held = getattr(cr, "_held", None)
    a = _alpha(diag)
    best, bt = None, None
    for c in group:
        if c is cr or getattr(c, "_held", None) is None or held is None or not np.array_equal(c._held[0], held[0]):
            continue
        t = held_back_test(diag, held[1], c._held[1], held[0])    # from cr's held-back residual to c's
        c.rival_test = {"against": cr.effect, "drop": t["drop"], "se": t["se"], "p": t["p"]}
        told = t["p"] < a and t["drop"] > 0
        c.note = (f"against {cr.effect} on the same held-back frames: {t['drop']:.3g} +- {t['se']:.2g} lower "
                  f"(p = {t['p']:.3g}): " + ("better" if told else "not told apart" if abs(t["drop"]) < 2 * t["se"]
                                             else "worse") + "; " + c.note)
        if c.accepted and told and (bt is None or t["drop"] > bt["drop"]):
            best, bt = c, t
    if cr.accepted:
        return best or cr
    return max(ok, key=lambda c: c.held_back_drop) if ok else cr


def judge_probe(diag: Diagnosis, cr: CandidateResult, holdout_every: int = 4, frames: list | None = None) -> None:
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
    val = list(frames) if frames is not None else held_back_frames(prob.T, holdout_every, res, p.column)
    a0, *_ = np.linalg.lstsq(J, -r0, rcond=None)
    a1, *_ = np.linalg.lstsq(J, -r1, rcond=None)
    b0, b1 = r0 + J @ a0, r1 + J @ a1
    cr.realized_loss_drop = run.aloss(b0) - run.aloss(b1)
    n = run.n_img or len(r0)
    m = _frame_mask(res, val) if val else np.ones(n, bool)
    _accept(diag, cr, [("base", b0[:n])], b1[:n], m)


__all__ = ["refit_effect", "refit_null", "judge_probe", "held_back_frames", "group_frames", "held_back_test",
           "compare_rivals"]


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
