"""Step 7 of the diagnosis: a short warm-started refit of a top candidate, accepted only if the
loss on held-back frames falls beyond the frames' own spread (a paired test over blocks).

A physical effect is refitted with the fit's own ladder machinery (`fit.ladder._Ladder`: AdamW on
log E, the trajectory and the effect's log-parametrised parameters, the held-back frames left out),
started exactly at the base (`warm_start`: its E field, nu and fitted path) with the effect at its
score estimate, the base's own parameters moved gently (`BASE_LR_SCALE`); the control is the base
refitted alike (`refit_null`). Two folds (`held_back_folds`): each model is refitted once without
each half of the frames the candidate changes most, and the paired test pools both halves. A
non-physical cause is judged on its probe taken for real (the changed timing, contact, grasp or
support, with the base parameters re-adjusted by their linear step). Both report the drop of the
diagnosis's loss (`residual.loss`) on all frames beyond what the base parameters' own (linear)
step gives, as the prediction is, and judge it on the held-back frames."""

from __future__ import annotations

import contextlib
import math
import numbers
import types

import numpy as np
import torch

from ..errors import SimulationError
from .core import PHYSICAL, CandidateResult, Diagnosis, _pad, prior_residual
from .residual import ImageResidual, loss

_POSITIVE = {"coefficient", "yieldStress", "friction", "modulus", "relaxationTime"}


def _strong_frames(res: ImageResidual, column) -> list[int]:
    """The frames where a column changes the model most (its energy above the median)."""
    e = np.square(np.asarray(column)).reshape(res.shape).sum((1, 2, 3))
    order = [res.frames[i] for i in np.argsort(-e) if e[i] > 0]
    return sorted(order[: max(2, len(order) // 2)])


def held_back_frames(T: int, every: int = 4, res: ImageResidual | None = None, column=None) -> list[int]:
    """Frames left out of the refit to judge it. With the candidate's column: every other frame
    among those where the candidate changes the model most (its column's energy above the median:
    frames it cannot change cannot judge it); else the ladder's every `every`-th frame."""
    from ..fit.ladder import _frames

    if res is None or column is None or T < 6:
        return _frames(T, every)[1]
    strong = _strong_frames(res, column)
    return strong[1::2] if len(strong) > 1 else strong


def held_back_folds(T: int, every: int = 4, res: ImageResidual | None = None, column=None, folds: int = 2
                    ) -> list[list[int]]:
    """The held-back frames of `folds` refits (cross-fitting): fold 1 is `held_back_frames` (every other
    frame among the candidate's strong ones), fold 2 the strong frames fold 1 trains on, so that
    every frame the candidate changes most judges it once (twice the held-back blocks of one fold).
    Without a column (or with fewer than two strong frames), one fold."""
    one = held_back_frames(T, every, res, column)
    if folds < 2 or res is None or column is None or T < 6:
        return [one]
    strong = _strong_frames(res, column)
    two = strong[0::2]
    return [one, two] if one and two and len(strong) > 1 else [one]


def as_folds(frames) -> list[list[int]] | None:
    """A list of held-back frames (one fold) or a list of such lists (folds) -> a list of folds."""
    if frames is None:
        return None
    frames = list(frames)
    if frames and isinstance(frames[0], (list, tuple)):
        return [list(f) for f in frames]
    return [frames]


def _frame_mask(res: ImageResidual, frames) -> np.ndarray:
    return np.isin(res.frame_of(), list(frames))


def held_back_test(diag: Diagnosis, r_ref, r_new=None, m=None) -> dict:
    """`score.paired_drop` of held-back elements of two image residuals, over the diagnosis's blocks (a
    few frames x an image tile, as its score tests): the drop of the held-back loss from `r_ref` to
    `r_new`, its standard error and the one-sided p-value. `r_ref` may instead be a list of (r_ref,
    r_new, m) triples, one per fold (each fold's refits trained without its held-back frames `m`):
    their held-back elements are pooled (a block's elements from two folds are summed into the one
    block: blocks stay independent)."""
    from . import score as S

    ctx = diag._ctx
    s = ctx.get("settings")
    blocks = ctx.get("blocks")
    if blocks is None:                                   # a diagnosis made without them: one block a frame
        blocks = ctx["res"].frame_of().astype(np.int64)
        nb = int(blocks.max()) + 1
    else:
        nb = int(ctx["n_blocks"])
    triples = r_ref if r_new is None else [(r_ref, r_new, m)]
    a = np.concatenate([np.asarray(t[0])[t[2]] for t in triples])
    b = np.concatenate([np.asarray(t[1])[t[2]] for t in triples])
    bl = np.concatenate([blocks[t[2]] for t in triples])
    return S.paired_drop(a, b, bl, nb, n_flips=getattr(s, "n_flips", 4000), seed=getattr(s, "seed", 0))


def _alpha(diag: Diagnosis) -> float:
    return float(getattr(diag._ctx.get("settings"), "alpha", 0.05))


def _accept(diag: Diagnosis, cr: CandidateResult, refs: dict, held: list) -> None:
    """Acceptance on the held-back frames: a one-sided paired test (`held_back_test`, pooled over the
    folds) against each model without the candidate: `refs` {name: [per fold: its image residual]},
    `held` [per fold: (mask of the held-back elements, the candidate's image residual)]; accepted
    when every p-value is below alpha (an intersection-union test: below the base's and the
    control's at level alpha). The drop and its standard error are reported against the reference
    with the lower held-back loss."""
    tests = [(name, held_back_test(diag, [(rr[i], r1, m) for i, (m, r1) in enumerate(held)]))
             for name, rr in refs.items()]
    # the lower reference: the smallest drop (the held-back loss to beat is the lower one)
    low = min(tests, key=lambda t: t[1]["drop"])
    p = max(t[1]["p"] for t in tests)
    cr.held_back_drop, cr.held_back_se, cr.held_back_p = low[1]["drop"], low[1]["se"], p
    cr.accepted = bool(p < _alpha(diag) and low[1]["drop"] > 0)
    cr._held = held


WARM = "field"   # how a refit starts (`warm_start`): "field" (the base's own E field, exactly) or "regions"
                 # (before 2026-11-26: each region's median E, which flattened a smooth field to one value)


def warm_start(lad, base, how: str = "field") -> None:
    """Start a refit's ladder (`fit.ladder._Ladder`) at the base: its E and nu.

    "field": a piecewise-constant base (`base.labels`) gets one log E per region (exact); any other
    field is nested (`MaterialField.set_base`): log E = the base's own per particle, plus one offset
    the refit moves (the score test's base column for such a field: the whole field's scale), so the
    refit starts exactly where the base is and keeps its shape. "regions": each region's median E
    (a smooth field becomes uniform: the refit starts far from the base, and 8 iterations do not get
    back; docs/benchmarks/diagnose_named.md, 2026-11-26 (10th))."""
    labels = base.labels if base.labels is not None else np.zeros(len(base.E), np.int64)
    E = base.E.detach().cpu().numpy().astype(np.float64)
    lad.labels = labels.astype(np.int64)
    if how == "field" and base.labels is None and float(np.ptp(np.log(E))) > 1e-9:
        lad.mat.set_basis(1)
        lad.mat.set_base(E)
    else:
        lad.mat.set_regions(lad.labels)
        lad.mat.set_region_log_e(np.array([np.log(np.median(E[labels == r])) for r in range(int(labels.max()) + 1)]))
    nu = base.nu.detach().cpu().numpy().astype(np.float64)
    if how == "field" and float(np.ptp(nu)) > 1e-9:
        lad.mat.set_values(lad.mat.youngs().detach().cpu().numpy(), nu)      # nu's basis: one value, least squares
    else:
        nu0 = float(np.median(nu))
        with torch.no_grad():
            lad.mat.w_nu.copy_(torch.full_like(lad.mat.w_nu, float(math.log(nu0 / (lad.mat.nu_max - nu0)))))


BASE_LR_SCALE = 0.0   # the refits move the base's own parameters (E, the path) at this x the fit's learning rates
                      # (the effect's at the fit's). 0: the base held, only the effect's parameters fitted on the
                      # training frames, and the control is the base itself (no refit). On foam_bar (CPU, grid 16;
                      # docs/benchmarks/diagnose_named.md, 2026-11-26 (10th)) at the fit's rates 8 iterations from the
                      # converged base raised the control's held-back loss by 9-24% (trained without the frames the
                      # candidate changes most, the base moves toward the others), at 0.2x still by 1.4-27%; held,
                      # plasticity@1's held-back gain was the same (p 0.002) and viscoelasticity@1's rose from
                      # 1e-6 (p 0.48) to 8.9e-5 (p 0.07)


def _refit(diag: Diagnosis, effect: str | None, start: dict, val: list, iterations: int, holdout_every: int, log,
           warm: str | None = None, base_lr_scale: float | None = None):
    """A short warm-started refit of the base (`warm_start`: its E field and nu; the trajectory from the
    fitted path) with `effect`'s parameters too (None: the base alone, the control every candidate's
    refit is judged against), on the frames not in `val`. Returns (image residual, augmented
    residual, state) or raises SimulationError."""
    from ..fit.ladder import _Ladder
    from ..fit.optimize import FitSettings

    ctx = diag._ctx
    prob, base = ctx["prob"], ctx["base"]
    effs = tuple(effect) if isinstance(effect, (tuple, list)) else ((effect,) if effect else ())
    if len(effs) > 1:                   # several effects at once (`refit_joint`): `start` is {effect: {param: v}}
        starts = {e: dict(start.get(e) or {}) for e in effs}
    else:
        starts = {e: start for e in effs}
    s = FitSettings(iterations=int(iterations), joint=True, fit_effects=effs,
                    holdout_every=holdout_every, confidence_probes=0)
    lrs = BASE_LR_SCALE if base_lr_scale is None else float(base_lr_scale)
    if lrs != 1.0:      # the base's own parameters (E, the path) moved more gently than the effect's
        s.lr_material, s.lr_trajectory = s.lr_material * lrs, s.lr_trajectory * lrs
    lad = _Ladder(prob, s, log, progress=False)
    warm_start(lad, base, warm or WARM)
    for e_, p, raw in [(e_, p, raw) for e_ in effs for p, raw in lad.effect_raw.get(e_, {}).items()]:
        v = starts[e_].get(p)
        if not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
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
    state = {"E": lad.mat.youngs().detach(), "nu": lad.mat.poisson().detach(),
             "trajectories": [t.detach() for t in lad.trajs], "effects": eff, "full_effects": full,
             "history": list(lad.history)}
    state["bound"] = rung_for(diag, state["E"])
    r1, r1a = residual_at(diag, state, state["bound"])
    return r1, r1a, state


def rung_for(diag: Diagnosis, E) -> float | None:
    """The adaptive substep's stiffness bound a refitted field is judged at: the base's own (the one
    its residual was taken at) unless the field is stiffer than that rung allows (then its own)."""
    sim = getattr(diag._ctx["prob"], "sim", None)
    b0 = diag._ctx.get("e_bound")
    if b0 is None or sim is None or not getattr(sim, "adaptive", False):
        return None
    return float(max(b0, sim.bound_for(float(E.max()))))


def residual_at(diag: Diagnosis, state: dict | None, bound: float | None):
    """(image residual, augmented residual) of a state {"E", "nu", "trajectories", "full_effects"}
    (None: the base) simulated at the substep of stiffness `bound` (`fit.select.pinned_substep`):
    models compared on held-back frames are simulated at one substep (a different time step alone
    changes the loss by ~2%, as much as the candidates differ). The base at its own bound is the
    diagnosis's own residual (no forward)."""
    from ..fit.select import pinned_substep

    ctx = diag._ctx
    prob, base, res, run = ctx["prob"], ctx["base"], ctx["res"], ctx["run"]
    if state is None:
        if bound is None or bound == ctx.get("e_bound"):
            return ctx["r0"], ctx["r0a"]
        cache = ctx.setdefault("base_at", {})
        if bound not in cache:
            with torch.no_grad(), pinned_substep(prob, bound):
                x, F = prob.simulate(base.E, base.nu, None, effects=base.effects)
            cache[bound] = (res(x, F), ctx["r0a"][len(ctx["r0"]):])
        r, p = cache[bound]
        return r, run.aug(r, p)
    trajs = state["trajectories"]
    with torch.no_grad(), pinned_substep(prob, bound):
        x, F = prob.simulate(state["E"], state["nu"], trajs, effects=state["full_effects"])
    p1 = prior_residual(prob, base, trajs) if len(run.p0) else np.zeros(0)
    sc = float(ctx["prior"].get("row_scale", 0.0))
    r1 = res(x, F)
    return r1, run.aug(r1, p1 * sc)


def refit_null(diag: Diagnosis, val: list, *, iterations: int = 8, holdout_every: int = 4, log=None) -> dict | None:
    """The control of the candidates' refits: the base refitted alike (the same iterations, the same
    held-back frames `val`: one list, or one list per fold, `as_folds`), with no new effect. A few
    iterations from the fit move E and the path too, and lower the held-back loss by themselves where
    the base was not quite converged (or raise it): a candidate counts only for what it adds beyond
    that. Returns {"frames" (fold 1's), "folds": [{"frames", "state", "residual", "held_back_loss"}],
    "held_back_loss" (over every fold's held-back frames), "loss", "aloss", "residual" (fold 1's)}, or
    None when the simulation fails."""
    ctx = diag._ctx
    res, run = ctx["res"], ctx["run"]
    out = []
    for f in as_folds(val) or [[]]:
        if BASE_LR_SCALE == 0:      # the base's parameters held: the control is the base itself
            (r1, r1a), st = residual_at(diag, None, ctx.get("e_bound")), None
        else:
            try:
                r1, r1a, st = _refit(diag, None, {}, f, iterations, holdout_every, log)
            except SimulationError:
                return None
        m = _frame_mask(res, f) if f else np.ones(len(r1), bool)
        out.append({"frames": list(f), "state": st, "residual": r1, "aloss": run.aloss(r1a),
                    "held_back_loss": loss(r1[m]), "mask": m})
    allm = np.concatenate([o["residual"][o["mask"]] for o in out])
    return {"frames": out[0]["frames"], "folds": out, "held_back_loss": loss(allm), "loss": loss(out[0]["residual"]),
            "aloss": out[0]["aloss"], "residual": out[0]["residual"]}


def group_frames(diag: Diagnosis, crs: list, holdout_every: int = 4, folds: int = 1) -> list:
    """Held-back frames shared by candidates compared with each other (a confusable pair): every other
    frame among those where the candidates together (each column normalised) change the model most.
    `folds` 2: a list of the two folds' frames (`held_back_folds`)."""
    ctx = diag._ctx
    res, prob = ctx["res"], ctx["prob"]
    cols = [np.asarray(c.probes[c.best].column) for c in crs if c.best >= 0 and c.probes]
    e = 0.0
    for col in cols:
        col = col[: res.n]
        nrm = float(np.sum(np.square(col)))
        if nrm > 0:
            e = e + np.square(col) / nrm
    column = np.sqrt(e) if cols and np.ndim(e) else None
    if folds > 1:
        return held_back_folds(prob.T, holdout_every, res, column, folds)
    return held_back_frames(prob.T, holdout_every, res, column)


def refit_effect(diag: Diagnosis, cr: CandidateResult, *, iterations: int = 8, holdout_every: int = 4, log=None,
                 frames: list | None = None, null: dict | None = None, folds: int = 1):
    """Refit `cr`'s physical effect (module doc). Fills cr.realized_loss_drop, cr.accepted,
    cr.held_back_drop and cr.estimate (the refitted parameters). `frames`: the held-back frames, one
    list or one per fold (`as_folds`; default: from the candidate's own column, `folds` of them);
    `null`: the base refitted alike on those frames (`refit_null`): the held-back loss to beat is the
    lower of the base's and that one's, each compared at the candidate's substep. With several folds
    the candidate is refitted once per fold and the paired test pools every fold's held-back blocks.
    Returns fold 1's refitted state {"E", "nu", "trajectories", "effects"} or None."""
    ctx = diag._ctx
    prob, res, r0 = ctx["prob"], ctx["res"], ctx["r0"]
    if cr.effect not in PHYSICAL or cr.effect not in prob.effects:
        return None
    col = cr.probes[cr.best].column if cr.best >= 0 else None
    fl = as_folds(frames) or held_back_folds(prob.T, holdout_every, res, col, folds)
    nf = null.get("folds") if null is not None else None
    if nf is not None and [o["frames"] for o in nf] != fl:
        nf = None                                   # a control made on other frames cannot judge these
    start = dict(cr.estimate)
    held, refs, states, r1as = [], {"base": []}, [], []
    for i, val in enumerate(fl):
        try:
            r1, r1a, state = _refit(diag, cr.effect, start, val, iterations, holdout_every, log)
        except SimulationError as exc:
            cr.note = f"refit failed: {exc}"
            cr.accepted = False
            return None
        b = state["bound"]
        m = _frame_mask(res, val) if val else np.ones(len(r0), bool)
        held.append((m, r1))
        refs["base"].append(residual_at(diag, None, b)[0])
        if nf is not None:
            cs = nf[i]["state"]
            refs.setdefault("control", []).append(
                residual_at(diag, None, b)[0] if cs is None else
                nf[i]["residual"] if cs.get("bound") == b else residual_at(diag, cs, b)[0])
        states.append(state)
        r1as.append(r1a)
    run = ctx["run"]
    # the drop beyond what the base parameters alone would give (their linear step), as predicted
    J, r0a = diag._J, ctx["r0a"]
    a0, *_ = np.linalg.lstsq(J, -r0a, rcond=None)
    b0 = r0a + J @ a0
    cr.realized_loss_drop = float(np.mean([run.aloss(b0) - run.aloss(ra) for ra in r1as]))
    # the loss to beat: the best model without the candidate, the base as it is or refitted alike (a
    # refit on the training frames can also raise the held-back loss: then the base itself is the bar)
    _accept(diag, cr, refs, held)
    est = {}
    for p_ in states[0]["effects"].get(cr.effect, {}):
        vs = [float(st["effects"][cr.effect][p_]) for st in states]
        est[p_] = float(np.exp(np.mean(np.log(vs)))) if p_ in _POSITIVE and min(vs) > 0 else float(np.mean(vs))
    cr.estimate = est
    cr._states = states
    hb = lambda rr: loss(np.concatenate([r[m] for r, (m, _) in zip(rr, held)]))  # noqa: E731
    v1 = loss(np.concatenate([r1[m] for m, r1 in held]))
    ref = "the base's" if nf is None else f"the base refitted alike: {hb(refs['control']):.3e}"
    where = (f"held-back frames {fl[0]}" if len(fl) == 1 else
             f"{len(fl)} folds, held-back frames " + " and ".join(str(f) for f in fl))
    cr.note = (f"refit ({iterations} iterations from the base's field and path, the effect from its estimate; "
               f"{where}): held-back loss {hb(refs['base']):.3e} -> {v1:.3e} ({ref}); drop {cr.held_back_drop:.3g} "
               f"+- {cr.held_back_se:.2g} (paired test over blocks, p = {cr.held_back_p:.3g}); loss {loss(r0):.3e} -> "
               f"{loss(held[0][1]):.3e} ({run.aloss(b0):.3e} with the base's own step alone)"
               + ("" if cr.accepted else ": not accepted (the held-back drop is within the frames' own spread)"
                  if cr.held_back_drop > 0 else ": not accepted"))
    return states[0]


def _same_folds(a: list, b: list) -> bool:
    return len(a) == len(b) and all(np.array_equal(x[0], y[0]) for x, y in zip(a, b))


# The confusable pairs of physical effects the nested comparison (`nested_pair`) separates when both are
# accepted on the same held-back frames (issue #22: "damping vs ground friction", damping vs viscoelasticity).
NESTED_PAIRS = (frozenset(("damping", "ground")), frozenset(("damping", "viscoelasticity")))
# A physical effect and the interaction cause that mimics it, told apart the same way (`nested_with_interaction`): a
# release off by a frame or two takes energy out of the swing as damping does (the tests' tiny bar released 2 frames
# late: damping passes the held-back test too, p 0.00025; nested, the release is needed and damping is not).
INTERACTION_PAIRS = (frozenset(("damping", "interaction:timing")), frozenset(("viscoelasticity", "interaction:timing")),
                     frozenset(("damping", "interaction:support")))


def refit_joint(diag: Diagnosis, crs: list, frames: list, *, iterations: int = 8, holdout_every: int = 4, log=None
                ) -> dict | None:
    """The candidates `crs` (physical effects) refitted together, each started at its own refitted
    estimate, on the held-back `frames` (one list per fold, as each was refitted alone). Returns
    {"effects", "held": [per fold (mask, image residual)], "states", "estimate": {effect: {param}}} or
    None when the simulation fails."""
    ctx = diag._ctx
    res = ctx["res"]
    from ..workers import fork_map

    effs = tuple(c.effect for c in crs)
    start = {c.effect: dict(c.estimate) for c in crs}
    folds = as_folds(frames)

    def one(val):
        r1, _, state = _refit(diag, effs, start, val, iterations, holdout_every, log)
        return r1, state

    try:        # the folds are independent: on the CPU each in its own process where there are the cores
        got = fork_map(one, folds, device=ctx["prob"].tdev)
    except SimulationError:
        return None
    held = [(_frame_mask(res, val) if val else np.ones(len(r1), bool), r1) for val, (r1, _) in zip(folds, got)]
    states = [state for _, state in got]
    return {"effects": effs, "held": held, "states": states,
            "estimate": {e: dict(states[0]["effects"].get(e, {})) for e in effs}}


def per_frame_loss(diag: Diagnosis, held: list) -> dict:
    """{frame: the loss (mean square over its elements) of a model's held-back residual}, folds pooled
    (each frame is held back in one fold)."""
    fr = diag._ctx["res"].frame_of()
    out = {}
    for m, r in held:
        for k in sorted(set(fr[m].tolist())):
            mk = m & (fr == k)
            out[int(k)] = float(np.mean(np.square(np.asarray(r)[mk])))
    return out


def nested_pair(diag: Diagnosis, a: CandidateResult, b: CandidateResult, *, iterations: int = 8,
                holdout_every: int = 4, log=None) -> dict | None:
    """Two candidates of a confusable pair, both accepted on the same held-back frames (`a` the one
    named, `b` its rival), told apart by a nested comparison: refitted together (one more refit a fold,
    `refit_joint`), each judged by what it adds given the other: the paired held-back test (`held_back_test`,
    pooled over the folds) from the other one's model alone to the pair's. The effect the data needs is the
    one whose removal costs held-back loss; its rival, whose removal costs nothing once the first is in, only
    mimicked it. Returns {"pair", "adds": {effect: {"drop", "se", "p", "share"}}, "winner", "decided",
    "why", "per_frame": {model: {frame: held-back loss}}, "estimate"}; `winner` is `a` or `b`'s effect, or None
    (not told apart: both add, or neither does); None when the joint refit failed or the folds differ."""
    ha, hb_ = getattr(a, "_held", None), getattr(b, "_held", None)
    if ha is None or hb_ is None or not _same_folds(ha, hb_):
        return None
    folds = [sorted(set(diag._ctx["res"].frame_of()[m].tolist())) for m, _ in ha]
    j = refit_joint(diag, [a, b], folds, iterations=iterations, holdout_every=holdout_every, log=log)
    if j is None:
        return None
    out = judge_nested(diag, a, b, j["held"], effects=j["effects"])
    out.update(estimate=j["estimate"], _joint=j)
    return out


@contextlib.contextmanager
def _under_contacts(prob, contacts):
    """The diagnosis's problem simulating under other `contacts` for a while (`nested_with_interaction`): its
    simulation swapped for a twin under them (`Simulation.forward_twin`; differentiable), restored on exit."""
    saved = (prob.sim, prob.contacts, prob.control)
    prob.sim = prob.sim.forward_twin(contacts)
    prob.contacts, prob.control = prob.sim.contacts, prob.sim.control
    try:
        yield prob
    finally:
        prob.sim, prob.contacts, prob.control = saved


def _readjusted(diag: Diagnosis, ra: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """An augmented residual `ra` plus the base parameters' linear re-adjustment fitted without the held-back
    elements `mask` (as `judge_probe` re-adjusts an interaction probe): its image part."""
    n = diag._ctx["run"].n_img or len(mask)
    return _with_step(diag._J, ra, np.concatenate([~mask, np.ones(len(ra) - n, bool)]))[:n]


def nested_with_interaction(diag: Diagnosis, phys: CandidateResult, inter: CandidateResult, *, iterations: int = 8,
                            holdout_every: int = 4, log=None) -> dict | None:
    """A physical effect and an interaction cause that mimics it (damping and a grasp frame moved: both take energy
    out of the swing), both accepted on the same held-back frames, told apart as a confusable pair of physical
    effects is (`nested_pair`): the effect refitted under the interaction's change (its best probe's contacts,
    `core.probe_contacts`), and each judged by what it adds given the other. The interaction is judged as a probe
    with the base's linear re-adjustment (`judge_probe`), a physical effect by a refit that holds the base: here the
    effect's model and the pair's get the same re-adjustment, so each side of the drop-one test is re-adjusted
    alike. Returns `judge_nested`'s dict (`winner` the effect or the cause, None when not told apart) or None when
    it does not apply (no rebuilt contacts, other folds, the simulation failed)."""
    from .core import probe_contacts

    hp, hi = getattr(phys, "_held", None), getattr(inter, "_held", None)
    if hp is None or hi is None or not _same_folds(hp, hi):
        return None
    ctx = diag._ctx
    prob, res, run = ctx["prob"], ctx["res"], ctx["run"]
    cs = probe_contacts(prob, inter)
    if cs is None:
        return None
    folds = [sorted(set(res.frame_of()[m].tolist())) for m, _ in hp]
    start = dict(phys.estimate or {})
    from ..workers import fork_map

    def one(val):
        with _under_contacts(prob, cs):
            _, r1a, state = _refit(diag, phys.effect, start, val, iterations, holdout_every, log)
        return r1a, state

    try:
        got = fork_map(one, folds, device=prob.tdev)
    except SimulationError:
        return None
    joint = [(m, _readjusted(diag, r1a, m)) for (m, _), (r1a, _) in zip(hp, got)]
    phys_adj = types.SimpleNamespace(effect=phys.effect,
                                     _held=[(m, _readjusted(diag, run.aug(np.asarray(r)), m)) for m, r in hp])
    out = judge_nested(diag, phys_adj, inter, joint, effects=(phys.effect, inter.effect))
    out["estimate"] = {phys.effect: dict(got[0][1]["effects"].get(phys.effect, {}))}
    out["why"] = (f"{phys.effect} refitted under {inter.effect}'s change ({inter.probes[inter.best].label}), the base "
                  f"re-adjusted alike in every model; " + out["why"])
    return out


def lowest_points_mask(diag: Diagnosis, band: float | None = None, radius_px: float = 1.5) -> np.ndarray:
    """(n,) bool over the image residual's elements: the pixels (of the residual's subsampled grid) within
    `radius_px` strided pixels of the base model's lowest particles projected into each frame, the particles
    within `band` of that frame's lowest point (default half `core.ground_reach`: what a plane below the
    body can touch). Where a ground acts and damping does not single out."""
    from .core import ground_reach

    ctx = diag._ctx
    prob, res, x = ctx["prob"], ctx["res"], ctx["x"]
    x = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
    band = 0.5 * ground_reach(prob) if band is None else float(band)
    nf, h, w, _ = res.shape
    s = res.stride
    out = np.zeros((nf, h, w), bool)
    for i, k in enumerate(res.frames):
        y = x[k][:, 1]
        low = x[k][y <= y.min() + band]
        uv, z = prob.cameras[k].project(low)
        uv = uv[z > 0]
        if not len(uv):
            continue
        ci = (uv[:, 0] - (s // 2 + 0.5)) / s          # strided column / row of each projected particle
        ri = (uv[:, 1] - (s // 2 + 0.5)) / s
        rr, cc = np.mgrid[0:h, 0:w]
        for a, b in zip(ri, ci):
            out[i] |= (rr - a) ** 2 + (cc - b) ** 2 <= radius_px ** 2
    return np.broadcast_to(out[..., None], (nf, h, w, 4)).ravel()


def bottom_signature(diag: Diagnosis, damping: CandidateResult, ground: CandidateResult, *,
                     mask: np.ndarray | None = None) -> dict | None:
    """The ground's signature against damping (issue #22): a plane stops the lowest points at one height while
    the rest of the body moves; damping slows every motion everywhere. On the held-back elements at the base
    model's lowest points (`lowest_points_mask`) and on the rest, the paired test (`held_back_test`, folds
    pooled) from damping's refitted model to the ground's: `bottom` > 0 with p < alpha is the ground's
    signature (its model fits the lowest points better than damping's, which cannot single them out). Returns
    {"bottom": {"drop", "se", "p", "elements"}, "rest": {...}, "ground_signature": bool, "why"} or None."""
    hd, hg = getattr(damping, "_held", None), getattr(ground, "_held", None)
    if hd is None or hg is None or not _same_folds(hd, hg):
        return None
    low = lowest_points_mask(diag) if mask is None else np.asarray(mask, bool)
    out = {}
    for name, sel in (("bottom", low), ("rest", ~low)):
        trip = [(a[1], b[1], a[0] & sel) for a, b in zip(hd, hg)]
        n = int(sum(t[2].sum() for t in trip))
        if n == 0:
            return None
        t = held_back_test(diag, trip)
        out[name] = {"drop": float(t["drop"]), "se": float(t["se"]), "p": float(t["p"]), "elements": n}
    b, r = out["bottom"], out["rest"]
    out["ground_signature"] = bool(b["p"] < _alpha(diag) and b["drop"] > 0)
    out["why"] = (f"at the lowest points (the pixels of the particles within half a plane's reach of the lowest, "
                  f"{b['elements']} held-back values) the ground's model leaves {b['drop']:.3g} +- {b['se']:.2g} less "
                  f"than damping's (p = {b['p']:.2g}); over the rest of the body {r['drop']:.3g} +- {r['se']:.2g} "
                  f"(p = {r['p']:.2g})" + (": the lowest points stop where a floor holds them (the ground's signature)"
                                           if out["ground_signature"] else ": no floor's signature at the lowest points"))
    return out


def judge_nested(diag: Diagnosis, a: CandidateResult, b: CandidateResult, joint: list, effects=None) -> dict:
    """The nested comparison's decision (`nested_pair`) from `a`'s and `b`'s held-back residuals (their
    `_held`, on the same folds) and the pair's (`joint`: per fold (mask, image residual)): what each adds
    given the other, by the paired held-back test from the other's model alone to the pair's; the one needed
    (p < alpha, drop > 0) while the other is not is the `winner`."""
    ha, hb_ = a._held, b._held
    alpha = _alpha(diag)
    base = [diag._ctx["r0"]] * len(ha)
    L_base = loss(np.concatenate([np.asarray(r)[m] for r, (m, _) in zip(base, ha)]))
    adds = {}
    for me, other in ((a, b), (b, a)):
        # what `me` adds given `other`: from other's held-back residual to the pair's
        t = held_back_test(diag, [(ho[1], hj[1], ho[0]) for ho, hj in zip(other._held, joint)])
        adds[me.effect] = {"drop": float(t["drop"]), "se": float(t["se"]), "p": float(t["p"]),
                           "share": float(t["drop"]) / L_base if L_base > 0 else 0.0,
                           "needed": bool(t["p"] < alpha and t["drop"] > 0)}
    na, nb = adds[a.effect]["needed"], adds[b.effect]["needed"]
    winner = a.effect if na and not nb else b.effect if nb and not na else None
    pct = lambda e: f"{100 * adds[e]['share']:.1f}% (p = {adds[e]['p']:.2g})"  # noqa: E731
    why = (f"refitted together (drop-one on the same held-back frames): removing {a.effect} given {b.effect} "
           f"costs {pct(a.effect)} of the held-back loss, removing {b.effect} given {a.effect} {pct(b.effect)}")
    L_j = loss(np.concatenate([np.asarray(r)[m] for m, r in joint]))
    L_1 = min(loss(np.concatenate([np.asarray(r)[m] for m, r in h])) for h in (ha, hb_))
    if L_j > L_1:
        why += (" (the pair's refit ends above the better one alone: its few iterations from the two estimates did not "
                "reach it; read the removal costs as bounds)")
    if winner is None:
        why += (": both needed" if na and nb else ": neither needed given the other (not told apart by nesting)")
    else:
        loser = b.effect if winner == a.effect else a.effect
        why += f": {winner} is needed, {loser} only mimics it"
    per_frame = {"base": per_frame_loss(diag, [(m, r) for r, (m, _) in zip(base, ha)]),
                 a.effect: per_frame_loss(diag, ha), b.effect: per_frame_loss(diag, hb_),
                 "+".join(effects or (a.effect, b.effect)): per_frame_loss(diag, joint)}
    return {"pair": [a.effect, b.effect], "adds": adds, "winner": winner, "decided": winner is not None,
            "why": why, "per_frame": per_frame}


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
        if c is cr or getattr(c, "_held", None) is None or held is None or not _same_folds(c._held, held):
            continue
        # from cr's held-back residual to c's, pooled over the folds
        t = held_back_test(diag, [(h[1], g[1], h[0]) for h, g in zip(held, c._held)])
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


def _with_step(J: np.ndarray, r: np.ndarray, train: np.ndarray) -> np.ndarray:
    """The residual `r` with the base columns' linear step fitted on the rows `train` only (r itself without columns)."""
    return r + J @ _train_lstsq(J, r, train) if J.size else np.asarray(r)


def _train_lstsq(A: np.ndarray, y: np.ndarray, train: np.ndarray) -> np.ndarray:
    """Least squares of `y` on the columns of `A` over the rows `train` only."""
    if A.size == 0:
        return np.zeros(A.shape[1] if A.ndim == 2 else 0)
    a, *_ = np.linalg.lstsq(A[train], -y[train], rcond=None)
    return a


def judge_probe(diag: Diagnosis, cr: CandidateResult, holdout_every: int = 4, frames: list | None = None) -> None:
    """A non-physical cause (or `heterogeneity`), judged as a physical one is (cross-fitted): per fold
    its amplitude (a continuous probe: the Gauss-Newton step; `heterogeneity` then simulated for
    real, the field moved by that step; a discrete probe is taken whole) and the base parameters'
    re-adjustment (their linear step) are fitted on the training rows only (every image element not
    in that fold's held-back frames, and the trajectory prior's rows), the base re-adjusted alike
    without the candidate and the base as it is are the references (it must beat both), and the paired
    test pools the folds' held-back blocks (`_accept`). Before 2026-11-26 the step and the re-adjustment
    were fitted on all frames, the held-back ones included, so the held-back test was not one. `realized_loss_drop`: the drop on
    all frames beyond the base's own linear step (fold 1's amplitude)."""
    ctx = diag._ctx
    prob, res, r0, J, run = ctx["prob"], ctx["res"], ctx["r0a"], diag._J, ctx["run"]
    if cr.best < 0:
        return
    p = cr.probes[cr.best]
    col = _pad(p.column, len(r0))
    fl = as_folds(frames) or [held_back_frames(prob.T, holdout_every, res, p.column)]
    n = run.n_img or len(r0)
    # the references: the base re-adjusted alike (its linear step fitted on the same training rows) and the base as it
    # is. The linear step can raise the held-back loss (a linearised re-adjustment fitted on half the frames): a probe
    # carrying the same step then "gains" on it by undoing part of it, though it leaves the held-back frames worse than
    # the base as it is (the README walkthrough at grid 24: a grasp moved 1 -> 2 accepted at p 0.0015 with its
    # held-back residual 2.5e-4 above damping's, which was itself below the base's). A candidate must beat both, as a
    # refitted effect must beat the base as it is and refitted alike (`refit_effect`).
    held, refs, real = [], {"base": [], "as_is": []}, None
    for f in fl:
        m = _frame_mask(res, f) if f else np.ones(n, bool)
        train = np.concatenate([~m, np.ones(len(r0) - n, bool)]) if f else np.ones(len(r0), bool)
        b0 = _with_step(J, r0, train)
        if p.discrete or cr.effect not in ("heterogeneity", "camera:time_offset", "camera:depth_scale"):
            r1 = r0 + col                           # the probe itself (amplitude 1)
        else:
            pf = p
            if cr.effect == "heterogeneity" and f:
                # the split direction chosen again without the held-back frames (the score test's was chosen
                # from the residual's gradient on all frames: a selection the held-back test would not undo)
                from .core import _heterogeneity_probes

                again = _heterogeneity_probes(run, r0[:n], ctx["settings"], weight=(~m).astype(np.float64))
                pf = again[0] if again else p
            cf = _pad(pf.column, len(r0))
            A = np.column_stack([J, cf]) if J.size else cf[:, None]
            t = float(_train_lstsq(A, r0, train)[-1])
            if pf.sign and t * pf.sign < 0:
                t = 0.0
            if cr.effect == "heterogeneity":        # the field moved by that step, simulated
                v = torch.as_tensor(pf.meta["direction"], dtype=run.base.E.dtype, device=run.base.E.device)
                try:
                    r1 = run.aug(run.r(E=run.base.E * torch.exp(t * v)))
                except SimulationError as exc:
                    cr.note = f"judged: the step failed ({exc})"
                    cr.accepted = False
                    return
            else:
                r1 = r0 + cf * t                    # render-only / gravity: the linear step itself
        b1 = _with_step(J, r1, train)
        if real is None:
            every = np.ones(len(r0), bool)
            real = run.aloss(_with_step(J, r0, every)) - run.aloss(_with_step(J, r1, every))
        held.append((m, b1[:n]))
        refs["base"].append(b0[:n])
        refs["as_is"].append(np.asarray(r0[:n]))
    cr.realized_loss_drop = real
    _accept(diag, cr, refs, held)
    s = ctx.get("settings")
    if cr.effect == "heterogeneity" and getattr(s, "heterogeneity_priced", False):
        priced = price_heterogeneity(diag, held, refs["base"])
        cr.priced = priced
        if cr.accepted and not priced["keep"]:
            cr.accepted = False
        cr.held_back_p = max(float(cr.held_back_p), float(priced["p_time"]))
        cr.note = f"priced: {priced['why']}" + ("; " + cr.note if cr.note else "")
    cr.note = (f"judged on held-back frames ({' and '.join(str(f) for f in fl)}; its amplitude and the base's "
               f"re-adjustment fitted without them): drop {cr.held_back_drop:.3g} +- {cr.held_back_se:.2g}, p = "
               f"{cr.held_back_p:.3g}" + ("" if cr.accepted else ": not accepted") + ("; " + cr.note if cr.note else ""))


def price_heterogeneity(diag: Diagnosis, held: list, refs: list) -> dict:
    """`heterogeneity` judged as the fit's own model selection judges a richer field (`fit.select.select_rule`,
    docs/diagnose.md): over the held-back frames (the folds pooled) the mean per-frame drop of the loss must
    exceed `FitSettings.select_penalty` x its added coefficients (one: a part's E) x the base's held-back loss,
    and the candidate must be better on most held-back frames (a sign test); and the paired test on time
    blocks (one a frame, no image tiles: a wrong field is coherent over the image, so the tiles are not
    independent evidence of it) at alpha. `held`: per fold (mask, the candidate's residual); `refs`: per fold
    the base re-adjusted alike. Returns {"keep", "p_time", "select", "why"}."""
    from ..fit.optimize import FitSettings
    from ..fit.select import select_rule
    from . import score as S

    res = diag._ctx["res"]
    fr = res.frame_of()
    u, f, a, b, bl = [], [], [], [], []
    for (m, r1), r0 in zip(held, refs):
        for k in sorted(set(fr[m].tolist())):
            mk = m & (fr == k)
            u.append(float(np.mean(np.square(r0[mk]))))
            f.append(float(np.mean(np.square(r1[mk]))))
            a.append(r0[mk])
            b.append(r1[mk])
            bl.append(np.full(int(mk.sum()), len(u) - 1, np.int64))
    if not u:
        return {"keep": False, "p_time": 1.0, "select": None, "why": "no held-back frame"}
    sel = select_rule(u, f, 1, FitSettings())
    st = diag._ctx.get("settings")
    t = S.paired_drop(np.concatenate(a), np.concatenate(b), np.concatenate(bl), len(u),
                      n_flips=getattr(st, "n_flips", 4000), seed=getattr(st, "seed", 0))
    keep = bool(sel["keep_field"] and t["p"] < _alpha(diag) and t["drop"] > 0)
    why = (f"{sel['why']}; on time blocks ({len(u)} frames) drop {t['drop']:.3g} +- {t['se']:.2g}, p = {t['p']:.3g}"
           + ("" if keep else ": not kept"))
    return {"keep": keep, "p_time": float(t["p"]), "select": sel, "why": why}


def judge_on_rest(diag: Diagnosis, cr: CandidateResult) -> None:
    """A camera cause tested on the frames before the first grasp (`DiagnoseSettings.camera_rest`,
    `core.test_on_rows`): no refit judges it on moving frames (where the rendering's and the discretisation's
    own errors lean along its probe, docs/diagnose.md); its score test on the rest frames, given the selected
    candidates, is its held-back evidence (p at alpha, then Holm's correction with the others). The drop and
    its standard error are the linear step's on those frames (base re-adjusted on them alone), for the record."""
    from . import score as S

    ctx = diag._ctx
    rows = ctx.get("rest_rows")
    r0, J = ctx["r0a"], diag._J
    if cr.best < 0 or rows is None or not rows.any():
        cr.accepted = False
        return
    idx = np.where(rows[: len(r0)])[0]
    col = _pad(cr.probes[cr.best].column, len(r0))[idx]
    rr, Jr = r0[idx], J[idx]
    a0, *_ = np.linalg.lstsq(Jr, -rr, rcond=None) if Jr.size else (np.zeros(0),)
    b0 = rr + (Jr @ a0 if Jr.size else 0.0)
    A = np.column_stack([Jr, col]) if Jr.size else col[:, None]
    a1, *_ = np.linalg.lstsq(A, -rr, rcond=None)
    b1 = rr + A @ a1
    blocks = np.asarray(ctx["blocks"])[idx] if ctx.get("blocks") is not None else np.zeros(len(idx), np.int64)
    lab, inv = np.unique(blocks, return_inverse=True)
    t = S.paired_drop(b0, b1, inv.astype(np.int64), len(lab))
    n = ctx["run"].n_img or len(r0)
    cr.held_back_drop = float(t["drop"]) * len(idx) / n
    cr.held_back_se = float(t["se"]) * len(idx) / n
    cr.held_back_p = float(cr.p_value)
    cr.accepted = bool(cr.p_value < _alpha(diag) and cr.drop > 0)
    cr.note = (f"judged on the frames before the first grasp (score test p = {cr.p_value:.3g}; the linear step's "
               f"drop there {cr.held_back_drop:.3g} +- {cr.held_back_se:.2g})" + ("" if cr.accepted else ": not accepted")
               + ("; " + cr.note if cr.note else ""))


__all__ = ["refit_effect", "refit_null", "judge_probe", "judge_on_rest", "price_heterogeneity", "held_back_frames", "held_back_folds", "as_folds", "group_frames",
           "held_back_test", "warm_start", "residual_at", "rung_for",
           "compare_rivals", "nested_pair", "nested_with_interaction", "judge_nested", "bottom_signature", "lowest_points_mask", "refit_joint", "per_frame_loss", "NESTED_PAIRS", "INTERACTION_PAIRS"]


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
