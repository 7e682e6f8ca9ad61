"""Several fits of one scene from different starts, in lockstep: the bumps schedule (`optimize.py`)
run for B starts at once, each iteration ONE tiled rollout (`sim/batch.py`: B copies of the scene
side by side on one grid, sharing every kernel launch) forward and backward for all of them.

Each start (`Start`: the uniform start E x a factor, the basis centres' seed) is a copy with its
own material field, trajectories, AdamW state, level schedule and convergence stop; the loss
backpropagated is the sum of the copies' losses, so each copy's gradient is its own. A copy that
converged keeps its best iterate and leaves the batch (the rollout shrinks); a copy whose
simulation went unstable or left its own box is reported and dropped (it keeps the best iterate it
had), not turned into inf for all. The copies' renders and loss terms run batched too: every
(copy, frame) image of an iteration in one rasterizer pass and one loss call (`copies_rec`).

    results = fit_bumps_batched(prob, settings, default_starts(4, seed=0), uniform_e=e)
    r = fit_starts(prob, settings, 4)          # the best start, every start's loss in r.model["starts"]

Why: on a GPU a small scene's substep is bound by launch latency, so B copies cost about one
(docs/benchmarks/gpu.md, "Several probes in one launch"); processes on one GPU serialise. On the
CPU the copies' arithmetic runs one after another and tiling does not pay: `fit_starts` runs the
starts one by one there (`fit_bumps` each).

The starts (`START_FACTORS`): x1, then one adaptive-substep rung lower each (x 1/sqrt(2), 1/2,
1/(2 sqrt(2)), ...; `sim.cfl.RUNG_RATIO`): no start is stiffer than x1, so a tiled batch begins at
the x1 start's substep, the one fit's (a start at x2 sat two rungs up and held every copy at 1.41x
the substeps: docs/benchmarks/gpu.md). As the fields move, the shared substep follows the stiffest
copy's field (`Simulation.simulate_batch` takes the rung of the largest E of all copies, every call).

Limits: all copies take the substep of the largest E among them (a soft copy's rollout is a little
finer in time than its own fit's would be); the starts spread below the searched E only (a field
stiffer than the best uniform E somewhere is still reached from x1, as one fit reaches it); the
effects' parameters are shared by the copies of a
tiled rollout, so a fit that fits effects runs its starts one by one; a resumed or warm-started
fit has one start (the field it goes on from).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from .. import stopping
from ..errors import SimulationError
from ..sim.cfl import RUNG_RATIO
from .adamw import AdamW
from .converge import improved, lr_scale, plateaued
from .material import MaterialField, neighbour_pairs, pair_weights
from .optimize import (FitResult, FitSettings, _level_params, _restore_in_place, _seed, _split, assemble_result,
                       clean_gradients, fit_bumps, frame_metrics, golden_uniform_search)
from .phases import Phases
from .problem import FitProblem


def rung_factors(n: int) -> tuple:
    """x1 and then one substep rung (`RUNG_RATIO`) lower each: 1, 1/sqrt(2), 1/2, ... (n of them).
    Every factor is <= 1, so every start's rung (`sim.cfl.rung`), hence its substep count, is at most
    the x1 start's."""
    return tuple(RUNG_RATIO ** -k for k in range(int(n)))


# The starts' factors on the uniform start E (the golden-section search's), in order: `--starts N`
# takes the first N; each start also takes its own seed (settings.seed + its index) for the bumps'
# centres. Inside the x1 start's substep rung: `rung_factors` (was x 1, 0.5, 2, 0.25, ...: the x2
# start raised every copy's substep count by 1.41x).
START_FACTORS = rung_factors(8)


@dataclass(frozen=True)
class Start:
    factor: float = 1.0     # the start's uniform E = the searched uniform E x this (clipped to the range)
    seed: int = 0           # the basis centres' seed (MaterialField)


def default_starts(n: int, seed: int = 0) -> list[Start]:
    """The first `n` starts: START_FACTORS' factors, seeds seed, seed + 1, ..."""
    n = int(n)
    if not 1 <= n <= len(START_FACTORS):
        raise ValueError(f"starts must be 1..{len(START_FACTORS)}, got {n}")
    return [Start(START_FACTORS[i], int(seed) + i) for i in range(n)]


def start_e(e_uniform: float, factor: float, e_range: tuple) -> float:
    lo, hi = float(e_range[0]), float(e_range[1])
    return float(np.clip(e_uniform * factor, lo * 1.001, hi * 0.999))


def batching_pays(prob: FitProblem, settings: FitSettings) -> bool:
    """Whether `fit_starts` runs its starts as tiled copies: on a GPU, for a fit whose effects are
    not fitted (the copies of a tiled rollout share the effects' parameters)."""
    return str(prob.tdev).startswith("cuda") and not settings.fit_effects


# ------------------------------------------------------------------------------- one copy
class _Copy:
    """One start's state in the lockstep loop: fit_bumps' parameterisation, levels, AdamW, best
    iterate and convergence stop (fit_bumps without resume and fitted effects)."""

    def __init__(self, prob: FitProblem, s: FitSettings, start: Start, e0: float, feats, pairs, pair_w,
                 lam_smooth: float):
        st = prob.scene.settings
        self.prob, self.s, self.start = prob, dataclasses.replace(s, seed=start.seed), start
        self.mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                                 device=prob.tdev, seed=start.seed, width=s.basis_width, features=feats,
                                 appearance=s.appearance, centre_mask=~prob.held_particles())
        self.mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        self.e0 = e0
        self.mat.set_uniform(e0)
        self.trajs = [t.clone().requires_grad_(s.joint) for t in prob.initial_trajectories()]
        self.pairs, self.pair_w, self.lam = pairs, pair_w, lam_smooth
        self.levels = tuple(int(k) for k in s.levels)
        self.per_level = _split(max(int(s.iterations), 0), tuple(s.level_share), len(self.levels))
        self.history: list[float] = []
        self.best = {"loss": float("inf")}
        self.status = "running"       # running | converged | unstable (dropped) | interrupted
        self.note = ""
        self.li = -1
        self._next_level()

    # the schedule ---------------------------------------------------------------------------
    def _next_level(self) -> None:
        s, mat, best = self.s, self.mat, self.best
        self.li += 1
        while self.li < len(self.levels) and self.per_level[self.li] <= 0:
            self.li += 1
        if self.li >= len(self.levels):
            self.status = "converged" if self.status == "running" else self.status
            return
        li, k = self.li, self.levels[self.li]
        if self.history:
            if "theta" in best:       # refine from the best iterate so far
                mat.B, mat.nu_basis = best["B"], best["nu_basis"]
                with torch.no_grad():
                    mat.theta = best["theta"].clone().requires_grad_(True)
                    mat.w_nu = best["w_nu"].clone().requires_grad_(True)
                self.trajs = [t.clone().requires_grad_(s.joint) for t in best["trajs"]]
            mat.refine(k, refine_nu=False)
        elif k != mat.K:
            mat.refine(k, refine_nu=False)
        groups = [{"params": [mat.theta], "lr": s.lr_material}]
        if li < s.fit_poisson_levels:
            groups.append({"params": [mat.w_nu], "lr": s.lr_poisson})
        if s.joint and self.trajs and li >= len(self.levels) - s.trajectory_levels:
            groups.append({"params": self.trajs, "lr": s.lr_trajectory})
        self.opt = AdamW(groups, weight_decay=s.weight_decay)
        self.base = [g["lr"] for g in self.opt.param_groups]
        self.n_it, self.j, self.stop_at, self.tail = self.per_level[li], 0, self.per_level[li], None
        self.level_losses: list[float] = []
        self.level_best = None

    @property
    def active(self) -> bool:
        return self.status == "running"

    def inputs(self):
        """Set the iteration's learning rates; (E, nu, trajectories) with gradients."""
        scale = lr_scale(self.j, self.n_it, self.tail)
        self.scale = scale
        for g, b0 in zip(self.opt.param_groups, self.base):
            g["lr"] = b0 * scale
        self.opt.zero_grad(set_to_none=True)
        return self.mat.youngs(), self.mat.poisson(), self.trajs

    def total(self, out: dict):
        """The iteration's loss (the problem's reconstruction + trajectory prior + smoothness)."""
        mat = self.mat
        reg = self.lam * mat.smoothness(self.pairs, self.pair_w) if len(self.pairs) and mat.K > 1 else 0.0
        return out["rec"] + out["reg_traj"] + reg

    def record(self, lv: float, sim) -> None:
        self.history.append(lv)
        if not self.level_losses or lv < min(self.level_losses):
            self.level_best = _level_params(self.mat, self.trajs, None)
        self.level_losses.append(lv)
        if lv < self.best["loss"]:
            m = self.mat
            self.best.update(loss=lv, sim=sim, theta=m.theta.detach().clone(), w_nu=m.w_nu.detach().clone(),
                             B=m.B, nu_basis=m.nu_basis, trajs=[t.detach().clone() for t in self.trajs])

    def step(self) -> None:
        """The optimiser's step after the backward, then the level's convergence stop."""
        s = self.s
        clean_gradients(self.opt, self.trajs)
        self.opt.step()
        j = self.j
        self.j += 1
        if self.tail is None and plateaued(self.level_losses, s.plateau_patience, s.plateau_tol):
            n_tail = s.plateau_tail if improved(self.level_losses, s.plateau_tol) else 0
            self.tail, self.stop_at = (j + 1, self.scale, n_tail), min(self.n_it, j + 1 + n_tail)
            _restore_in_place(self.mat, self.trajs, self.level_best, {})
            for st_ in self.opt.state.values():
                if "exp_avg" in st_:
                    st_["exp_avg"].zero_()
        if self.j >= self.stop_at or self.j >= self.n_it:
            self._next_level()

    def drop(self, why: str, status: str = "unstable") -> None:
        self.status, self.note = status, why

    def restore_best(self) -> None:
        best, mat = self.best, self.mat
        if "theta" not in best:
            return
        mat.B, mat.nu_basis = best["B"], best["nu_basis"]
        mat.K = mat.B.shape[1]
        with torch.no_grad():
            mat.theta = best["theta"].clone().requires_grad_(True)
            mat.w_nu = best["w_nu"].clone().requires_grad_(True)
        for t, b in zip(self.trajs, best["trajs"]):
            with torch.no_grad():
                t.copy_(b)


# The copies' renders and loss terms: every (copy, frame) image of an iteration in one rasterizer
# pass and one batched loss (`FitProblem.frames_rec`: `render.render_batch`,
# `render.reconstruction_loss_batch`) instead of one render and one loss per copy and frame (B x (T - 1)
# of each). False: `FitProblem.loss` per copy (the measurement's "before"; equal to 1e-6,
# tests/test_fit_batched.py).
BATCH_RENDERS = True


def copies_rec(prob: FitProblem, x, F, copies, frames=None):
    """(len(copies),) reconstruction losses of the copies `copies` of a batch's states x (B, T, P, 3),
    F (B, T, P, 3, 3), all their frames' renders and loss terms batched (`FitProblem.frames_rec`)."""
    return prob.frames_rec(x, F, list(copies), frames)[0]


def batch_losses(prob: FitProblem, E, nu, trajectories=None):
    """The problem's loss of B fields in one tiled rollout: E, nu (B, P); `trajectories` one (B, T, 3)
    tensor per slot, or None. Returns ([the `FitProblem.loss` dict of each copy, None for a copy
    whose simulation went unstable or left its box], bad (B,) bool). Differentiable: the sum of
    the copies' totals backpropagates each copy's own gradient through one backward. The copies'
    renders and loss terms run batched (`copies_rec`) unless BATCH_RENDERS is off."""
    x, F, bad = prob.sim.simulate_batch(E, nu, trajectories)
    good = [b for b in range(len(bad)) if not bad[b]]
    recs = copies_rec(prob, x, F, good) if BATCH_RENDERS and good else None
    outs = []
    for b in range(len(bad)):
        if bad[b]:
            outs.append(None)
            continue
        tr = None if trajectories is None else [t[b] for t in trajectories]
        if recs is None:
            outs.append(prob.loss(E[b], nu[b], tr, simulated=(x[b], F[b])))
            continue
        reg = prob.trajectory_prior(tr) if tr is not None and prob.weights.trajectory > 0 else 0.0
        outs.append({"rec": recs[good.index(b)], "reg_traj": reg, "x": x[b], "F": F[b], "renders": {}})
    return outs, np.asarray(bad, bool)


# ---------------------------------------------------------------------------- the batch
def _losses_or_dropped(prob, E, nu, trajs):
    """`batch_losses`, and why a copy marked bad was: a SimulationError left after simulate_batch's
    copy-by-copy retry marks every copy of the rollout."""
    try:
        outs, bad = batch_losses(prob, E, nu, trajs)
    except SimulationError as exc:
        return [None] * len(E), np.ones(len(E), bool), str(exc)
    return outs, bad, "its simulation went unstable or left its own box"


def fit_bumps_batched(prob: FitProblem, settings: FitSettings | None = None, starts: list[Start] | None = None, *,
                      uniform_e: float | None = None, progress: bool = True, log=None,
                      on_iteration=None) -> list[FitResult]:
    """The bumps schedule from several starts in lockstep (module doc); one FitResult per start, in
    order, each without its confidence (ones; `fit_starts` estimates the chosen one's) and with
    `model["start"]` = {"factor", "seed", "uniform_e", "status", "iterations", "note"}. `uniform_e`:
    the searched uniform E (searched here when None). `on_iteration(it, loss, mat, trajs)` is called
    for the first start while it runs (the app's checkpoint follows it: a resumed batched fit goes on
    from that start's iterate, as one fit)."""
    s = settings or FitSettings()
    if s.fit_effects:
        raise ValueError("fit_bumps_batched: the copies of a tiled rollout share the effects' parameters; "
                         "fit the starts one by one (fit_starts does) when effects are fitted")
    starts = list(starts or default_starts(2, s.seed))
    _seed(s.seed)
    t0 = time.perf_counter()
    st = prob.scene.settings
    feats = prob.particle_appearance() if s.appearance > 0 else None
    probes: dict = {}
    skipped: list = []
    if uniform_e is None:
        mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                            device=prob.tdev, seed=s.seed, width=s.basis_width, features=feats,
                            appearance=s.appearance, centre_mask=~prob.held_particles())
        mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        uniform_e = golden_uniform_search(prob, mat, s.search_evals, log, skipped=skipped, seen=probes)
    pairs_np = neighbour_pairs(prob.x0, 1.6 * st.particle_spacing)
    pairs = torch.as_tensor(pairs_np, device=prob.tdev)
    pair_w = torch.as_tensor(pair_weights(pairs_np, feats, s.appearance), dtype=prob.tdtype, device=prob.tdev)
    lam = prob.weights.smooth if feats is not None else prob.weights.smooth_plain
    copies = [_Copy(prob, s, sp, start_e(uniform_e, sp.factor, (st.youngs_min, st.youngs_max)), feats, pairs,
                    pair_w, lam) for sp in starts]
    budget = max(int(s.iterations), 0)
    bar = None
    if progress and budget:
        from tqdm import tqdm

        bar = tqdm(total=budget, desc=f"fit x{len(copies)}", unit="it", dynamic_ncols=True)
    it = 0
    interrupted = False
    try:
        while any(c.active for c in copies):
            run = [c for c in copies if c.active]
            ins = [c.inputs() for c in run]
            E = torch.stack([i[0] for i in ins])
            nu = torch.stack([i[1] for i in ins])
            trajs = [torch.stack([i[2][k] for i in ins]) for k in range(len(ins[0][2]))] or None
            outs, bad, why = _losses_or_dropped(prob, E, nu, trajs)
            total = 0.0
            for c, out, b in zip(run, outs, bad):
                if b:
                    c.drop(f"dropped at iteration {len(c.history)}: {why}")
                    if log:
                        log(f"start x{c.start.factor:g} (seed {c.start.seed}): {c.note}")
                    continue
                tot = c.total(out)
                lv = float(tot.detach())
                if not math.isfinite(lv):
                    c.drop(f"dropped at iteration {len(c.history)}: its loss is not finite")
                    continue
                c.record(lv, (out["x"].detach(), out["F"].detach()))
                total = total + tot
            if torch.is_tensor(total):
                total.backward()
            for c in run:
                if c.active:
                    c.step()
            it += 1
            if bar is not None:
                best = min((c.best["loss"] for c in copies), default=math.inf)
                bar.set_postfix(best=f"{best:.4f}", running=sum(c.active for c in copies))
                bar.update(1)
            c0 = copies[0]      # the checkpoint follows the first start while it runs
            if on_iteration is not None and c0 in run and c0.status != "unstable" and c0.history:
                on_iteration(len(c0.history), c0.history[-1], c0.mat, c0.trajs)
    except KeyboardInterrupt:
        interrupted = True
        for c in copies:
            if c.active:
                c.drop("stopped", status="interrupted")
        if log:
            log("interrupted: keeping each start's best iterate so far")
    finally:
        if bar is not None:
            bar.close()
    stopping.finishing()
    results = []
    for c in copies:
        results.append(_finish_copy(prob, c, feats, t0, interrupted, uniform_e, probes, skipped))
    return results


def _finish_copy(prob, c: _Copy, feats, t0, interrupted, e_uniform, probes, skipped) -> FitResult:
    """A copy's last pass: its best iterate's renders (from the kept simulation when there is one),
    metrics and animation, its confidence left at ones."""
    c.restore_best()
    mat, s = c.mat, c.s
    E, nu = mat.youngs().detach(), mat.poisson().detach()
    trajs = [t.detach() for t in c.trajs]
    sim = c.best.get("sim")
    final_loss = float("inf")
    with torch.no_grad():
        try:
            out = prob.loss(E, nu, trajs or None, frames=range(1, prob.T), keep_renders=True, simulated=sim)
        except SimulationError:
            out = None
        if out is not None:
            reg = c.lam * mat.smoothness(c.pairs, c.pair_w) if len(c.pairs) and mat.K > 1 else 0.0
            final_loss = float(out["rec"] + out["reg_traj"] + reg)
            x, F = out["x"], out["F"]
            renders = {0: {n: v.detach() for n, v in prob.render_frame(0, x[0], F[0]).items()}, **out["renders"]}
        else:     # never simulated stably: the rest shape, an inf loss
            T, P = prob.T, len(prob.x0)
            x = torch.as_tensor(np.repeat(prob.x0[None], T, 0), dtype=prob.tdtype, device=prob.tdev)
            F = torch.eye(3, dtype=prob.tdtype, device=prob.tdev).expand(T, P, 3, 3).clone()
            renders = {k: {n: v.detach() for n, v in prob.render_frame(k, x[k], F[k]).items()} for k in range(T)}
    metrics = frame_metrics(prob, renders)
    model = {"start": {"factor": c.start.factor, "seed": c.start.seed, "uniform_e": c.e0, "status": c.status,
                       "iterations": len(c.history), **({"note": c.note} if c.note else {})}}
    if probes:
        model["uniform_probes"] = probes
    if skipped:
        model["uniform_skipped"] = sorted(skipped)
    r = assemble_result(prob, dataclasses.replace(s, confidence_probes=0), E, nu, np.ones(len(prob.x0)), trajs,
                        x, F, metrics, feats, c.history, final_loss, t0, interrupted or c.status == "interrupted",
                        e_uniform, model=model)
    return r


# ------------------------------------------------------------------- short region refits
def refit_regions_batched(prob: FitProblem, labels: np.ndarray, log_e_starts, nu0: float, iterations: int, *,
                          lr: float | None = None, log=None) -> list[dict]:
    """B short refits of a region-constant E field (one log E per region of `labels`), the paths
    kept at T0, nu fixed at `nu0`: the ladder's `optimise` step (AdamW on the regions' log E, a
    cosine learning rate, the best iterate kept; what `diagnose.refit.refit_base` runs for one
    start) for the starts `log_e_starts` (B arrays of per-region log E) in lockstep, one tiled
    rollout forward+backward per iteration. A start whose simulation goes unstable or leaves its
    box is dropped (its best iterate so far kept; "note" says so). Returns per start {"E", "nu"
    (tensors; None when no iterate simulated), "fit_loss", "iterations"[, "note"]}."""
    from .optimize import cosine_lr

    st = prob.scene.settings
    s = FitSettings()
    labels = np.asarray(labels, np.int64)
    mats, opts, bases, best = [], [], [], []
    for le in log_e_starts:
        mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                            device=prob.tdev, seed=s.seed)
        mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        mat.set_regions(labels)
        mat.set_region_log_e(np.asarray(le, np.float64))
        with torch.no_grad():
            mat.w_nu.copy_(torch.full_like(mat.w_nu, float(math.log(nu0 / (mat.nu_max - nu0)))))
        opt = AdamW([{"params": [mat.theta], "lr": lr or s.lr_material}], weight_decay=s.weight_decay)
        mats.append(mat)
        opts.append(opt)
        bases.append([g["lr"] for g in opt.param_groups])
        best.append({"loss": math.inf, "theta": mat.theta.detach().clone(), "n": 0})
    alive = [True] * len(mats)
    notes = [""] * len(mats)
    n = int(iterations)
    for j in range(n):
        run = [i for i in range(len(mats)) if alive[i]]
        if not run:
            break
        for i in run:
            cosine_lr(opts[i], bases[i], j, n)
            opts[i].zero_grad(set_to_none=True)
        E = torch.stack([mats[i].youngs() for i in run])
        nu = torch.stack([mats[i].poisson().detach() for i in run])
        outs, bad, why = _losses_or_dropped(prob, E, nu, None)
        total = 0.0
        for i, out, b in zip(run, outs, bad):
            lv = math.inf if b else float(out["rec"].detach())
            if not math.isfinite(lv):
                alive[i] = False
                notes[i] = f"dropped at iteration {j}: {why if b else 'its loss is not finite'}"
                if log:
                    log(f"refit start {i}: {notes[i]}")
                continue
            best[i]["n"] = j + 1
            if lv < best[i]["loss"]:
                best[i].update(loss=lv, theta=mats[i].theta.detach().clone())
            total = total + out["rec"]
        if torch.is_tensor(total):
            total.backward()
        for i in run:
            if alive[i]:
                opts[i].step()
    out = []
    for i, mat in enumerate(mats):
        ok = math.isfinite(best[i]["loss"])
        with torch.no_grad():
            mat.theta = best[i]["theta"].clone().requires_grad_(True)
            E1, nu1 = mat.youngs().detach(), mat.poisson().detach()
        d = {"E": E1 if ok else None, "nu": nu1 if ok else None, "fit_loss": best[i]["loss"],
             "iterations": best[i]["n"]}
        if notes[i]:
            d["note"] = notes[i]
        out.append(d)
    return out


# ------------------------------------------------------------------------- the app's entry
def fit_starts(prob: FitProblem, settings: FitSettings | None = None, n_starts: int = 2, *, batched: bool | None = None,
               progress: bool = True, log=None, on_iteration=None, uniform_e: float | None = None) -> FitResult:
    """The bumps schedule from `n_starts` starts (`default_starts`: x 1, 0.71, 0.5, ... of the searched
    uniform E), the best kept by its training
    loss (its final loss; the bumps schedule holds no frames back). `batched` None: as tiled copies
    in lockstep where that pays (`batching_pays`: on a GPU, effects not fitted), else one by one
    (`fit_bumps` each, from the same searched uniform E). The chosen start's confidence is
    estimated afterwards (`settings.confidence_probes`, read then: a stop skips it) by fit_bumps'
    last pass at its own substep; its `model["starts"]` lists every start ({"factor", "seed",
    "uniform_e", "final_loss", "iterations", "status"}), `model["starts_chosen"]` the chosen index,
    `model["starts_mode"]` "batched" or "sequential"."""
    s = settings or FitSettings()
    t0 = time.perf_counter()
    clock = Phases()        # model["phases_s"]: the search, the starts' fits, the chosen one's confidence (#26)
    starts = default_starts(n_starts, s.seed)
    st = prob.scene.settings
    batched = batching_pays(prob, s) if batched is None else bool(batched)
    if s.fit_effects:
        batched = False
    probes: dict = {}
    skipped: list = []
    if uniform_e is None:
        feats = prob.particle_appearance() if s.appearance > 0 else None
        mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                            device=prob.tdev, seed=s.seed, width=s.basis_width, features=feats,
                            appearance=s.appearance, centre_mask=~prob.held_particles())
        mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        with clock("start_search"):
            uniform_e = golden_uniform_search(prob, mat, s.search_evals, log, skipped=skipped, seen=probes)
    t_fits = time.perf_counter()
    if log:
        log(f"{len(starts)} starts ({'batched: one tiled rollout per iteration' if batched else 'one by one'}) "
            f"from the uniform E {uniform_e:.4g} Pa x " + ", ".join(f"{sp.factor:g}" for sp in starts))
    no_conf = dataclasses.replace(s, confidence_probes=0)
    if batched:
        results = fit_bumps_batched(prob, no_conf, starts, uniform_e=uniform_e, progress=progress, log=log,
                                    on_iteration=on_iteration)
    else:
        results = []
        for i, sp in enumerate(starts):
            r = fit_bumps(prob, dataclasses.replace(no_conf, seed=sp.seed), progress=progress, log=log,
                          on_iteration=on_iteration if i == 0 else None,
                          uniform_e=start_e(uniform_e, sp.factor, (st.youngs_min, st.youngs_max)))
            r.model["start"] = {"factor": sp.factor, "seed": sp.seed, "uniform_e": r.uniform_start,
                                "status": "interrupted" if r.interrupted else "converged",
                                "iterations": len(r.loss_history)}
            results.append(r)
            if r.interrupted:       # a stop ends the starts too
                break
    table = []
    for r in results:
        d = dict(r.model.get("start", {}))
        d["final_loss"] = r.final_loss if math.isfinite(r.final_loss) else None
        table.append(d)
    finite = [i for i, r in enumerate(results) if math.isfinite(r.final_loss)]
    if not finite:
        raise SimulationError("no start of the fit simulated stably", frame=0,
                              advice="check the contacts and the E range (every start went unstable)")
    clock.add("iterations", time.perf_counter() - t_fits)      # every start's fit, with its final pass
    k = min(finite, key=lambda i: results[i].final_loss)
    win = results[k]
    interrupted = any(r.interrupted for r in results)
    if log:
        log("starts: " + ", ".join(f"x{d['factor']:g} {d['final_loss']:.5f}" if d["final_loss"] is not None
                                   else f"x{d['factor']:g} dropped" for d in table)
            + f"; kept x{starts[k].factor:g}")
    t_conf = time.perf_counter()
    if s.confidence_probes > 0 and not interrupted:
        # the chosen start's confidence (fit_bumps' last pass from its iterate, at its own substep)
        fin = fit_bumps(prob, dataclasses.replace(s, seed=starts[k].seed, iterations=0), progress=False, log=None,
                        start={"youngs": win.youngs, "poisson": win.poisson, "trajectories": win.trajectories})
        win.confidence, win.confidence_gaussian = fin.confidence, fin.confidence_gaussian
        win.settings["confidence_probes"] = s.confidence_probes
    clock.add("confidence", time.perf_counter() - t_conf)
    model = {k_: v for k_, v in win.model.items() if k_ != "start"}
    model.update(starts=table, starts_chosen=k, starts_mode="batched" if batched else "sequential",
                 phases_s=dict(clock.seconds))
    if probes:
        model["uniform_probes"] = probes
    if skipped:
        model["uniform_skipped"] = sorted(skipped)
    win.model = model
    win.uniform_start = float(uniform_e)
    win.runtime_s = time.perf_counter() - t0
    win.settings["starts"] = len(starts)
    win.interrupted = interrupted
    return win


__all__ = ["Start", "START_FACTORS", "rung_factors", "default_starts", "batch_losses", "copies_rec", "fit_bumps_batched",
           "fit_starts", "batching_pays", "refit_regions_batched", "BATCH_RENDERS"]
