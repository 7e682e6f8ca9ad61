"""Model selection from simple to complex: the fit's "ladder" schedule.

1. One E for the whole object: a coarse sweep of log E over the allowed range (forward passes only;
   probes that go unstable or leave the grid are reported and skipped), a golden-section refinement
   around the best, and, where the sweep is flat (two minima within `flat_tolerance`), both are
   refined; then a short gradient polish of E and nu.
2. Regions, one split at a time (`fit.regions`): the score of every candidate split (from the
   motion: where dL/dlog E says "stiffer" against "softer"; and from the appearance: colour
   clusters) predicts its loss drop d^2 / (2 h); the best is tried, warm-started with its Newton
   step, and kept only if the loss on held-back frames (every `holdout_every`-th frame, never fitted
   while the regions are chosen) falls by more than `split_margin`: more freedom than the data pin
   down is refused. A rejected split ends the ladder.
3. A final joint polish of the kept regions and (unless `joint=False`) the trajectory on all frames.
4. Per-particle confidence and each region's interval from the curvature of the loss (Gauss-Newton,
   `optimize.confidence`): a region the video does not determine gets a wide interval, not a
   confident wrong number.

Held particles (a support holds them from the first frame) have no score; they join the region of
the nearest free particle.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ..errors import SimulationError
from . import regions as R
from .adamw import AdamW
from .effect_params import effect_parameters, effect_values, search_effects
from .material import MaterialField
from .optimize import FitResult, FitSettings, assemble_result, clean_gradients, confidence, cosine_lr, frame_metrics
from .problem import FitProblem
from .search import golden_section, no_finite_uniform_probe


def _frames(T: int, every: int) -> tuple[list[int], list[int]]:
    """(training frames, held-back frames): every `every`-th frame from frame 2 is held back."""
    val = [k for k in range(2, T) if every > 1 and (k - 2) % every == 0] if T >= 6 else []
    train = [k for k in range(1, T) if k not in val]
    return train, val


class _Ladder:
    def __init__(self, prob: FitProblem, s: FitSettings, log=None, progress: bool = True, on_iteration=None):
        self.prob, self.s, self.log = prob, s, log or (lambda *a: None)
        self.on_iteration = on_iteration
        st = prob.scene.settings
        self.feats = prob.particle_appearance() if s.appearance > 0 else None
        self.mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                                 device=prob.tdev, seed=s.seed)
        self.mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        self.trajs = [t.clone().requires_grad_(s.joint) for t in prob.initial_trajectories()]
        self.effect_raw = effect_parameters(prob, getattr(s, "fit_effects", ()))      # {effect: {param: unconstrained leaf tensor}}
        self.train, self.val = _frames(prob.T, s.holdout_every)
        self.history: list[float] = []
        self.labels = np.zeros(len(prob.x0), np.int64)
        self.held = prob.held_particles()
        self.graph = R.particle_graph(prob.x0, 1.6 * st.particle_spacing)
        self.min_size = max(8, int(s.region_min_share * len(prob.x0)))
        self.report: dict = {"schedule": "ladder", "held_back_frames": self.val, "splits": []}
        self.bar = None
        self.best = {"loss": float("inf")}
        if progress and s.iterations:
            from tqdm import tqdm

            self.bar = tqdm(total=int(s.iterations), desc="fit", unit="it", dynamic_ncols=True)
        self.used = 0

    # ------------------------------------------------------------------ losses
    def effects(self) -> dict | None:
        """The fitted effects' parameters (tensors; None when none is fitted)."""
        return effect_values(self.effect_raw, self.prob.traj_scale) if self.effect_raw else None

    def loss(self, frames, E=None, trajs=None, grad=False):
        mat, prob = self.mat, self.prob
        E = mat.youngs() if E is None else E
        nu = mat.poisson()
        tr = self.trajs if trajs is None else trajs
        ctx = torch.enable_grad() if grad else torch.no_grad()
        with ctx:
            out = prob.loss(E, nu if grad else nu.detach(), tr if tr else None, effects=self.effects(), frames=frames)
            return out["rec"] + (out["reg_traj"] if any(t.requires_grad for t in tr) else 0.0)

    def safe_loss(self, frames, E=None) -> float:
        try:
            v = float(self.loss(frames, E))
        except SimulationError:
            return float("inf")
        return v if math.isfinite(v) else float("inf")

    # ------------------------------------------------------------------ 1. uniform
    def uniform_start(self) -> float:
        s, mat = self.s, self.mat
        P = len(self.prob.x0)
        lo, hi = mat.lo + 0.02 * (mat.hi - mat.lo), mat.hi - 0.02 * (mat.hi - mat.lo)
        cache: dict[float, float] = {}

        def f(le):
            if le not in cache:
                E = torch.full((P,), math.exp(le), dtype=mat.dtype, device=mat.device)
                cache[le] = self.safe_loss(self.train, E)
                if math.isfinite(cache[le]):
                    self.log(f"uniform E {math.exp(le):.4g} Pa: loss {cache[le]:.5f}")
                else:
                    self.log(f"uniform E {math.exp(le):.4g} Pa: the simulation went unstable or left the grid: skipped")
            return cache[le]

        grid = np.linspace(lo, hi, max(int(s.sweep_points), 3))
        vals = np.array([f(le) for le in grid])
        if not np.isfinite(vals).any():
            raise no_finite_uniform_probe()
        # local minima of the sweep; where the loss is flat (two within flat_tolerance), refine both
        order = np.argsort(vals)
        best_v = vals[order[0]]
        mins = [i for i in range(len(grid)) if np.isfinite(vals[i])
                and (i == 0 or vals[i] <= vals[i - 1]) and (i == len(grid) - 1 or vals[i] <= vals[i + 1])]
        starts = [i for i in mins if vals[i] <= best_v * (1 + s.flat_tolerance)][:2]
        step = grid[1] - grid[0]
        for i in starts:
            golden_section(f, grid[i] - step, grid[i] + step, s.search_evals)
        le = min((k for k in cache if math.isfinite(cache[k])), key=cache.get)
        self.report["uniform_sweep"] = {f"{math.exp(k):.4g}": (round(v, 6) if math.isfinite(v) else None)
                                        for k, v in sorted(cache.items())}
        if len(starts) > 1:
            self.report["flat_start"] = [float(math.exp(grid[i])) for i in starts]
        return math.exp(le)

    # ------------------------------------------------------------------ optimisation
    def snapshot(self) -> dict:
        mat = self.mat
        return {"B": mat.B, "K": mat.K, "theta": mat.theta.detach().clone(), "w_nu": mat.w_nu.detach().clone(),
                "nu_basis": mat.nu_basis, "labels": self.labels.copy(),
                "trajs": [t.detach().clone() for t in self.trajs],
                "effects": {e: {p: v.detach().clone() for p, v in ps.items()} for e, ps in self.effect_raw.items()}}

    def restore(self, snap: dict) -> None:
        mat = self.mat
        mat.B, mat.K, mat.nu_basis = snap["B"], snap["K"], snap["nu_basis"]
        mat.theta = snap["theta"].clone().requires_grad_(True)
        mat.w_nu = snap["w_nu"].clone().requires_grad_(True)
        self.labels = snap["labels"].copy()
        for t, b in zip(self.trajs, snap["trajs"]):
            with torch.no_grad():
                t.copy_(b)
        for e, ps in snap.get("effects", {}).items():
            for p, v in ps.items():
                with torch.no_grad():
                    self.effect_raw[e][p].copy_(v)

    def optimise(self, n: int, frames, *, fit_nu: bool, fit_traj: bool, lr: float | None = None) -> float:
        """`n` AdamW steps (cosine-annealed) on the regions' log E (and nu, the trajectory); keeps the
        best iterate of these steps (by the loss on `frames`). Returns its loss."""
        s, mat = self.s, self.mat
        n = int(min(n, max(int(s.iterations) - self.used, 0)))
        groups = [{"params": [mat.theta], "lr": lr or s.lr_material}]
        if fit_nu:
            groups.append({"params": [mat.w_nu], "lr": s.lr_poisson})
        if fit_traj and self.trajs:
            for t in self.trajs:
                t.requires_grad_(True)
            groups.append({"params": self.trajs, "lr": s.lr_trajectory})
        eff = [v for ps in self.effect_raw.values() for v in ps.values()]
        if eff:
            groups.append({"params": eff, "lr": s.lr_effects})
        opt = AdamW(groups, weight_decay=s.weight_decay)
        base = [g["lr"] for g in opt.param_groups]
        best_v, best = float("inf"), self.snapshot()
        for j in range(n):
            cosine_lr(opt, base, j, n)
            opt.zero_grad(set_to_none=True)
            try:
                total = self.loss(frames, grad=True)
            except SimulationError as exc:
                self.log(f"iteration {self.used}: {exc}; halving the step")
                for g in opt.param_groups:
                    g["lr"] *= 0.5
                self.restore(best)
                self.used += 1
                continue
            lv = float(total.detach())
            self.history.append(lv)
            if lv < best_v:
                best_v, best = lv, self.snapshot()
            total.backward()
            clean_gradients(opt, self.trajs)
            opt.step()
            self.used += 1
            if self.on_iteration is not None:
                self.on_iteration(self.used, lv, mat, self.trajs)
            if self.bar is not None:
                self.bar.set_postfix(loss=f"{lv:.4f}", regions=mat.K, E=f"{float(mat.youngs().median()):.3g}")
                self.bar.update(1)
        self.restore(best)
        for t in self.trajs:
            t.requires_grad_(False)
        return best_v

    # ------------------------------------------------------------------ 2. splits
    def score(self, frames) -> np.ndarray:
        """dL / dlog E_p at the current field (zero on held particles)."""
        logE = torch.log(self.mat.youngs().detach()).requires_grad_(True)
        total = self.loss(frames, E=torch.exp(logE), grad=True)
        g, = torch.autograd.grad(total, logE)
        out = g.detach().cpu().numpy().astype(np.float64)
        out[self.held] = 0.0
        return out

    def candidates(self, g: np.ndarray) -> list[dict]:
        out = []
        free_labels = np.where(self.held, -1, self.labels)
        for r in range(self.mat.K):
            for kind, parts in (("motion", R.score_parts(g, free_labels, r, self.graph, self.min_size)),
                                ("appearance", R.appearance_parts(self.feats, free_labels, r, self.graph,
                                                                  self.min_size, seed=self.s.seed))):
                for part in parts:
                    v = R.split_direction(free_labels, r, part)
                    d = float(g @ v)
                    out.append({"region": r, "kind": kind, "part": part, "v": v, "d": d,
                                "z": abs(d) / max(float(np.linalg.norm(v)), 1e-12)})
        # the same part found twice (motion and appearance agree) is tried once
        seen, uniq = set(), []
        for c in sorted(out, key=lambda c: -c["z"]):
            key = (c["region"], len(c["part"]), int(c["part"][:5].sum()))
            if key not in seen:
                seen.add(key)
                uniq.append(c)
        return uniq

    def predicted_drop(self, c: dict, frames, L0: float, delta: float = 0.15) -> float:
        """d^2 / (2 h), h the loss's curvature along the split's direction (two forward passes)."""
        E0 = self.mat.youngs().detach()
        v = torch.as_tensor(c["v"], dtype=E0.dtype, device=E0.device)
        lp = self.safe_loss(frames, E0 * torch.exp(delta * v))
        lm = self.safe_loss(frames, E0 * torch.exp(-delta * v))
        if not (math.isfinite(lp) and math.isfinite(lm)):
            return 0.0
        h = (lp + lm - 2 * L0) / delta ** 2
        c["h"] = h
        # the drop of the better of the two probes when the curvature is not positive
        return c["d"] ** 2 / (2 * h) if h > 0 else max(L0 - min(lp, lm), 0.0)

    def split(self, c: dict) -> None:
        """Apply a split with its Newton step (clamped to a factor 3 in E)."""
        log_e = self.mat.region_log_e()
        new = R.relabel_split(self.labels, c["part"])
        self.labels = R.attach_held(new, self.held, self.prob.x0)
        self.mat.set_regions(self.labels)
        step = -c["d"] / c["h"] if c.get("h", 0) > 0 else 0.0
        step = float(np.clip(step, -math.log(3.0), math.log(3.0)))
        share = len(c["part"]) / max(int((self.labels == c["region"]).sum()) + len(c["part"]), 1)
        vals = np.append(log_e, log_e[c["region"]])
        vals[-1] += step * (1 - share)
        vals[c["region"]] -= step * share
        self.mat.set_region_log_e(np.clip(vals, self.mat.lo + 1e-3, self.mat.hi - 1e-3))

    # ------------------------------------------------------------------ the whole schedule
    def run(self, start: dict | None = None, uniform_e: float | None = None) -> tuple:
        s, mat = self.s, self.mat
        budget = int(s.iterations)
        n_uniform = max(2, int(round(s.uniform_share * budget)))
        n_split = max(2, int(round(s.split_share * budget)))
        n_final = max(2, int(round(s.final_share * budget)))
        interrupted = False
        e0 = None
        try:
            if start is not None:
                e0 = float(np.exp(np.mean(np.log(start["youngs"]))))
                labels = np.asarray(start.get("regions")) if start.get("regions") is not None else None
                if labels is not None and len(labels) == len(self.prob.x0):
                    self.labels = labels.astype(np.int64)
                    mat.set_regions(self.labels)
                    mat.set_region_log_e(np.array([np.log(np.median(start["youngs"][self.labels == r]))
                                                   for r in range(mat.K)]))
                else:
                    mat.set_uniform(e0)
                for i, name in enumerate(self.prob.sim.slot_names()):
                    if name in start.get("trajectories", {}):
                        with torch.no_grad():
                            self.trajs[i].copy_(torch.as_tensor(start["trajectories"][name], dtype=self.prob.tdtype))
                self.report["resumed"] = True
                if self.effect_raw and s.search_effects:   # effects just switched on: their start first
                    st = self.prob.scene.settings
                    self.report["effect_search"] = search_effects(
                        lambda: self.loss(list(range(1, self.prob.T))), self.effect_raw, tuple(s.search_effects),
                        (st.youngs_min, st.youngs_max), self.prob.traj_scale, points=s.effect_search_points,
                        log=self.log)
            else:
                e0 = uniform_e if uniform_e is not None else self.uniform_start()
                mat.set_uniform(e0)
                self.optimise(n_uniform, self.train, fit_nu=True, fit_traj=False)
                self.report["uniform_e"] = float(np.exp(mat.region_log_e()[0]))
                L_val = self.safe_loss(self.val) if self.val else None
                for _ in range(int(s.max_regions) - 1):
                    if budget - self.used < n_split + n_final:
                        break
                    L0 = self.safe_loss(self.train)
                    g = self.score(self.train)
                    cands = self.candidates(g)[: int(s.split_candidates)]
                    if not cands:
                        break
                    for c in cands:
                        c["predicted"] = self.predicted_drop(c, self.train, L0)
                    c = max(cands, key=lambda c: c["predicted"])
                    entry = {"region": int(c["region"]), "kind": c["kind"], "particles": int(len(c["part"])),
                             "predicted_drop": float(c["predicted"]), "loss": L0}
                    if c["predicted"] < s.split_min_drop * L0:
                        entry["kept"] = False
                        entry["why"] = "predicted drop below the threshold"
                        self.report["splits"].append(entry)
                        break
                    snap = self.snapshot()
                    self.split(c)
                    L1 = self.optimise(n_split, self.train, fit_nu=False, fit_traj=False)
                    entry["realised_drop"] = float(L0 - L1)
                    if L_val is not None:
                        V1 = self.safe_loss(self.val)
                        entry["held_back_loss"] = [L_val, V1]
                        keep = V1 < L_val * (1 - s.split_margin)
                    else:
                        keep = L1 < L0 * (1 - s.split_margin)
                    entry["kept"] = bool(keep)
                    self.report["splits"].append(entry)
                    self.log(f"split region {c['region']} ({c['kind']}, {len(c['part'])} particles): predicted drop "
                             f"{c['predicted']:.2e}, realised {L0 - L1:.2e}"
                             + (f", held-back loss {L_val:.5f} -> {V1:.5f}" if L_val is not None else "")
                             + (": kept" if keep else ": refused"))
                    if not keep:
                        self.restore(snap)
                        break
                    L_val = V1 if L_val is not None else None
            # final joint polish on all frames
            n_left = max(budget - self.used, 0)
            self.optimise(n_left if n_left else n_final, list(range(1, self.prob.T)), fit_nu=False,
                          fit_traj=s.joint and bool(self.trajs), lr=0.5 * s.lr_material)
        except KeyboardInterrupt:
            interrupted = True
            self.log("interrupted: keeping the best iterate so far")
        finally:
            if self.bar is not None:
                self.bar.close()
        return (e0 if e0 is not None else float(np.exp(np.mean(mat.region_log_e())))), interrupted


def fit_ladder(prob: FitProblem, s: FitSettings, *, progress=True, log=None, start=None, uniform_e=None,
               on_iteration=None) -> FitResult:
    """The "ladder" schedule (module doc). `on_iteration(it, loss, mat, trajs)` after every step."""
    t0 = time.perf_counter()
    torch.manual_seed(s.seed)
    np.random.seed(s.seed)
    lad = _Ladder(prob, s, log, progress, on_iteration)
    if start is not None and start.get("effects"):   # a warm start: the previous version's effect values
        lad.effect_raw = effect_parameters(prob, s.fit_effects, start["effects"])
    e_uniform, interrupted = lad.run(start, uniform_e)
    mat = lad.mat
    E, nu = mat.youngs().detach(), mat.poisson().detach()
    trajs = [t.detach() for t in lad.trajs]
    effects = lad.effects()
    with torch.no_grad():
        out = prob.loss(E, nu, trajs if trajs else None, effects=effects, frames=range(1, prob.T), keep_renders=True)
        final_loss = float(out["rec"] + out["reg_traj"])
        x, F = out["x"], out["F"]
        renders = {0: {n: v.detach() for n, v in prob.render_frame(0, x[0], F[0]).items()}, **out["renders"]}
    fitted_effects = {e: {p: float(v.detach()) for p, v in ps.items()} for e, ps in (effects or {}).items()}
    metrics = frame_metrics(prob, renders)
    conf = np.ones(len(prob.x0))
    model = dict(lad.report)
    model["regions"] = int(mat.K)
    if s.confidence_probes > 0 and not interrupted:
        conf, sigma = confidence(prob, mat, trajs, s.confidence_probes, seed=s.seed, return_sigma=True,
                                  effects=effects, covariance=s.confidence_covariance)
        log_e = mat.region_log_e()
        model["region_e"] = [float(np.exp(v)) for v in log_e]
        model["region_particles"] = [int((lad.labels == r).sum()) for r in range(mat.K)]
        # each region's 95% interval from the curvature (its particles share one sigma)
        model["region_interval"] = []
        for r in range(mat.K):
            sg = float(np.median(sigma[lad.labels == r])) if np.any(lad.labels == r) else float("inf")
            model["region_interval"].append([float(np.exp(log_e[r] - 1.96 * sg)), float(np.exp(log_e[r] + 1.96 * sg))])
    return assemble_result(prob, s, E, nu, conf, trajs, x, F, metrics, lad.feats, lad.history, final_loss, t0,
                           interrupted, e_uniform, regions=lad.labels.copy(), model=model,
                           effect_parameters=fitted_effects)
