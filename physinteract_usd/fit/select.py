"""Model selection from simple to complex by held-back frames: the fit's "select" schedule.

1. One E for the whole object (`uniform_stage`): a dense log-spaced sweep of uniform E over the
   allowed range (forward passes only, on the training frames), then a golden-section refinement
   inside the bracket of each of the best local minima (up to `select_minima`: after the release the
   loss is multimodal in E, one oscillation period against the next, and a coarse sweep can land in
   the wrong well). The curve's shape (flat / single / multimodal) and, per kept minimum, the
   curvature of the loss in log E and the interval where the loss rises by `select_interval_rise`
   of its value are reported.
2. The "uniform" model: uniform E (and nu and the trajectory) polished from the best minimum by
   the optimiser on one basis function (`optimize.fit_bumps`, levels (1,)), training frames only.
3. The "parts" model (`select_parts`): candidate partitions of the object by appearance (colour
   clusters of the particles' local colours) and by motion (where the uniform model's score
   dL/dlog E says stiffer against softer), cut into connected parts of a reasonable size
   (`fit.regions`); each part's E by a coordinate sweep over the whole range (forward passes only,
   batched on a GPU) from the uniform model's E, the best candidate also from the uniform stage's
   other minima (a part's loss can be needle-like and multimodal in E: a field started in the
   uniform optimum's well stays there), then a Nelder-Mead simplex over all the best candidate's
   part E together (`part_refine`: the parts' loss is a narrow valley across the axes, where the
   one-part-at-a-time search stalls), then an AdamW polish of the part E, one nu and the
   trajectory (`fit_parts`), training frames only.
   The "field" model: the bumps field (the finest level of `levels`) nested on the simpler model
   kept (uniform or parts; `select_field_nested`): log E = that model's per-particle log E, held
   fixed, plus a bumps offset that starts at zero (`MaterialField.set_base`), so the field starts
   at the kept model's loss, keeps its part boundaries, and its best iterate is never worse on the
   training frames; training frames only. (Before: the kept model projected onto the bumps, which
   cannot represent parts' sharp boundaries: on hemp_rope that field started, and ended, above the
   parts' held-back loss.)
   Where parts were kept, also the field from the uniform model (`select_field_from_uniform`: the
   plain bumps field, what the default schedule fits), n more iterations: the parts may be the
   wrong partition, and a field nested on them keeps their wrong boundaries (hemp_rope on an H200:
   the field on its motion parts MA 0.405 against bumps' 0.801). It is kept over the model chosen
   by the steps below only if it pays for its coefficients beyond that model's by the same test.
4. Selection on the held-back frames, simple to complex (uniform -> parts -> field): every
   `select_holdout_every`-th frame from frame 2, but never the first frame after a release, which
   carries most of the free motion's evidence (no model ever fits them; interleaved rather than a
   time split, so both halves see the grasp, the lift and the release alike, and the trajectory at
   a held-back frame is still pinned by the frames after it). A step is kept only if, over the
   held-back frames, its loss falls by more than its added freedom predicts: the mean per-frame
   drop d must exceed `select_penalty` x (added coefficients) x the simpler model's held-back loss
   (a BIC-like price per parameter), and the richer model must be better on most held-back frames
   (a sign test: one frame that the simpler model misses badly, the one after the release, does not
   carry the choice alone; a paired t-test was tried first and refused a two-part bar's field whose
   held-back loss fell 2.5x, because that frame dominated the variance). A tie keeps the simpler
   model.
5. The chosen model polished on all frames (`select_final_share` of the iterations) with its
   confidence (`optimize.confidence`).

The result's `model` says which model was chosen and why: the uniform stage's curve, minima and
intervals, the parts candidates (their sweeps, each part's E and interval), each model's training
and held-back losses and each step's test. No USD here."""

from __future__ import annotations

import dataclasses
import math
import time
import types

import numpy as np
import torch

from ..errors import SimulationError
from .adamw import AdamW
from .effect_params import effect_parameters, effect_values, fitted_values
from .substep import kept_rung, pinned_substep  # noqa: F401  (re-exported: select.pinned_substep)
from .optimize import FitResult, FitSettings, _level_params, _restore_in_place, clean_gradients, cosine_lr, fit_bumps
from .problem import FitProblem
from .exposure import EXPOSURE_FLOOR, exposure_of_rollout, unconstrained_particles  # noqa: F401  (re-exported)
from .search import UniformProbe, golden_section, has_ground, no_finite_uniform_probe
# pure Python, in a module free of torch / warp so that `info` imports it in milliseconds (#26); re-exported here
from ..fit_summary import DETERMINED_RATIO, ROUGH_RATIO, identifiability, model_summary, sweep_interval  # noqa: F401


def holdout_frames(T: int, every: int, keep=()) -> tuple[list[int], list[int]]:
    """(training frames, held-back frames): every `every`-th frame from frame 2 is held back (none
    when `every` < 2 or the clip has fewer than 6 frames: too few to fit on what is left); a frame in
    `keep` (the first frame after a release: the start of the free motion, which carries most of
    what the video says about E) is fitted, the next frame held back in its place."""
    keep = set(int(k) for k in keep)
    val = []
    if T >= 6 and every > 1:
        for k in range(2, T, every):
            while k in keep or k in val:
                k += 1
            if k < T:
                val.append(k)
    return [k for k in range(1, T) if k not in val], val


class FrameView:
    """A FitProblem whose loss, unless told otherwise, counts only `frames` (the training frames);
    everything else is the problem's."""

    def __init__(self, prob: FitProblem, frames: list[int]):
        self._prob, self._frames = prob, list(frames)

    def __getattr__(self, name):
        return getattr(self._prob, name)

    def loss(self, *args, frames=None, **kw) -> dict:
        return self._prob.loss(*args, frames=self._frames if frames is None else frames, **kw)


def problem_holdout(prob, s) -> tuple[list[int], list[int]]:
    """`holdout_frames` for a fit problem and its settings: every `s.select_holdout_every`-th frame held back, the
    first frame after each contact's release kept for fitting."""
    after_release = [c.release_frame + 1 for c in getattr(prob, "contacts", None) or []
                     if getattr(c, "release_frame", None) is not None]
    return holdout_frames(prob.T, int(s.select_holdout_every), keep=after_release)


def _shape(vals: np.ndarray, minima: list[int], flat: float) -> str:
    fin = vals[np.isfinite(vals)]
    if len(fin) and (fin.max() - fin.min()) <= flat * max(fin.min(), 1e-12):
        return "flat"
    return "multimodal" if len(minima) > 1 else "single"


def _curvature(cache: dict, le: float, half_width: float) -> float:
    """d^2 L / d(log E)^2 at `le` from a parabola through the probes within `half_width` of it
    (nan with fewer than three)."""
    pts = sorted((k, v) for k, v in cache.items() if abs(k - le) <= half_width + 1e-12 and math.isfinite(v))
    if len(pts) < 3:
        return float("nan")
    x = np.array([p[0] for p in pts]) - le
    y = np.array([p[1] for p in pts])
    return float(2.0 * np.polyfit(x, y, 2)[0])


def _batched_sweep(prob, grid, nu_t, frames, swept: dict, skipped: list, log=None, when: str = "cuda"):
    """On a GPU, the sweep's probes as tiled copies in few rollouts (`FitProblem.losses_batch`: a
    small scene's substep is launch-bound there, so the whole sweep costs about one probe at the
    stiffest probe's substep); None elsewhere (on the CPU each copy costs its own arithmetic, at
    the stiffest probe's substep: slower than probing one by one) or when the scene cannot be
    tiled. The values go to `swept`, not to the refinement's cache: they were taken at a finer
    time step than the refinement's own probes, so the two are not mixed."""
    from ..sim.batch import TilingError

    if when == "never" or (when == "cuda" and not str(prob.tdev).startswith("cuda")):
        return None
    E = torch.exp(torch.as_tensor(np.asarray(grid), dtype=prob.tdtype, device=prob.tdev))[:, None]
    try:
        vals = prob.losses_batch(E.expand(len(grid), len(prob.x0)), nu_t, frames=frames)
    except TilingError:
        return None
    for le, v in zip(grid, vals):
        swept[float(le)] = float(v)
        if not math.isfinite(v):
            skipped.append(math.exp(float(le)))
            if log:
                log(f"uniform E {math.exp(float(le)):.4g} Pa: the simulation went unstable or left the grid: skipped")
        elif log:
            log(f"uniform E {math.exp(float(le)):.4g} Pa: loss {v:.5f} (batched sweep)")
    return np.asarray(vals, dtype=float)


def uniform_stage(prob, frames, s: FitSettings, nu: float, log=None, progress: bool = False) -> dict:
    """The uniform-E stage (module doc, 1.). Returns {"e", "loss", "shape", "minima": [{"e",
    "loss", "curvature", "interval"}], "sweep": {E: loss}, "skipped": [E]}."""
    st = prob.scene.settings
    lo, hi = math.log(st.youngs_min), math.log(st.youngs_max)
    a, b = lo + 0.01 * (hi - lo), hi - 0.01 * (hi - lo)
    P = len(prob.x0)
    nu_t = torch.full((P,), float(nu), dtype=prob.tdtype, device=prob.tdev)
    skipped: list[float] = []
    f = UniformProbe(lambda E: prob.loss(E, nu_t, frames=frames)["rec"], P, prob.tdtype, prob.tdev, log, skipped)
    cache = f.cache

    grid = np.linspace(a, b, max(int(s.select_sweep_points), 3))
    it = grid
    if progress:
        from tqdm import tqdm

        it = tqdm(grid, desc="uniform sweep", unit="E", dynamic_ncols=True, leave=False)
    swept: dict[float, float] = {}
    vals = _batched_sweep(prob, grid, nu_t, frames, swept, skipped, log, s.select_sweep_batch)
    if vals is None:
        vals = np.array([f(le) for le in it])
    if not np.isfinite(vals).any():
        raise no_finite_uniform_probe(f.errors, has_ground(prob))
    n = len(grid)
    minima = [i for i in range(n) if np.isfinite(vals[i]) and (i == 0 or vals[i] <= vals[i - 1])
              and (i == n - 1 or vals[i] <= vals[i + 1])]
    # the plateaus of a flat stretch count once (their first point)
    minima = [i for j, i in enumerate(minima) if j == 0 or i != minima[j - 1] + 1 or vals[i] != vals[i - 1]]
    shape = _shape(vals, minima, s.select_flat)
    best_v = float(np.nanmin(vals[np.isfinite(vals)]))
    keep = sorted(minima, key=lambda i: vals[i])
    keep = [i for i in keep if vals[i] <= best_v * (1.0 + s.select_minima_tolerance)][: max(int(s.select_minima), 1)]
    step = float(grid[1] - grid[0])
    out = []
    for i in keep:
        ra, rb = max(a, grid[i] - step), min(b, grid[i] + step)
        if swept:
            f(grid[i])        # the batched sweep's point, at the refinement's own substep
        golden_section(f, ra, rb, s.search_evals)
        inside = [k for k in cache if ra - 1e-12 <= k <= rb + 1e-12 and math.isfinite(cache[k])]
        le = min(inside, key=cache.get)
        h = _curvature(cache, le, step)
        rise = s.select_interval_rise * cache[le]
        half = math.sqrt(2.0 * rise / h) if h > 0 else float("inf")
        interval = [math.exp(max(le - half, lo)), math.exp(min(le + half, hi))] if math.isfinite(half) \
            else [math.exp(lo), math.exp(hi)]
        out.append({"e": math.exp(le), "loss": cache[le], "curvature": h, "interval": interval})
    out.sort(key=lambda m: m["loss"])
    return {"e": out[0]["e"], "loss": out[0]["loss"], "shape": shape, "minima": out, "rise": s.select_interval_rise,
            "sweep": {f"{math.exp(k):.5g}": (round(v, 7) if math.isfinite(v) else None)
                      for k, v in sorted({**swept, **cache}.items())},
            "skipped": sorted(skipped)}


# parts are kept only if their E differ by more than this ratio (about the MA tolerance's half-width
# in log, sqrt(1.2 / 0.8) = 1.22: parts whose E agree closer are one material to the product's accuracy)
PARTS_MIN_RATIO = 1.25


def grasped_particles(prob) -> np.ndarray:
    """(P,) True for particles a contact drives for part of the clip (a hand's grasp) that no support
    holds from the first frame: while held, their motion is the hand's, not their material's."""
    held = np.asarray(prob.held_particles(), bool)
    out = np.zeros(len(prob.x0), bool)
    for c in getattr(prob, "contacts", []) or []:
        out[np.asarray(c.indices, np.int64)] = True
    return out & ~held


def part_candidates(prob, s: FitSettings, score: np.ndarray | None, log=None, attach_grasped: bool = False,
                    section: float | None = None, unconstrained: np.ndarray | None = None) -> list[dict]:
    """Candidate partitions of the object into parts (`fit.regions`), each {"kind", "labels" (P,)
    0..m-1, "parts"}: by appearance (colour clusters of the particles' local colours, k by
    `regions.colour_clusters`' rule) and by motion (the uniform model's score dL/dlog E split at
    its median: regions that want to strain differently), each cut into connected parts of at
    least `region_min_share` of the particles (smaller pieces join their neighbour), at most
    `select_max_parts`. Held particles (the video cannot see their material) join the nearest free
    cluster before the cut. The same partition found twice is kept once. `attach_grasped`
    (benchmarks, #24): in the motion candidate, the particles a hand grasps (`grasped_particles`)
    join the nearest free cluster too, as held ones do, rather than cut a part of their own: their
    score is the hand's motion, not their material's (hemp_rope: a part at the hand fitted 1.6
    kPa, and another time 19.5 kPa, against a truth of 7.5). `section` (metres; benchmarks, #24): the
    motion score averaged over a ball of the object's thickness before the cut
    (`regions.motion_clusters`). `unconstrained` (P,) bool (benchmarks, #24): particles the clip
    barely strains (`strain_exposure` below a floor) join the nearest strained cluster in the motion
    candidate, as held ones do: the video cannot tell their material, so they get no part (and no E)
    of their own but their strained neighbours'."""
    from . import regions as R

    st = prob.scene.settings
    P = len(prob.x0)
    held = np.asarray(prob.held_particles(), bool)
    free = ~held
    graph = R.particle_graph(prob.x0, 1.6 * st.particle_spacing)
    min_size = max(8, int(s.region_min_share * P))
    clusters = []
    if s.appearance > 0:
        clusters.append(("appearance", R.colour_clusters(prob.particle_appearance(), free, seed=s.seed)))
    grasped = grasped_particles(prob) if attach_grasped else np.zeros(P, bool)
    if unconstrained is not None:
        grasped = grasped | (np.asarray(unconstrained, bool) & free)
    if score is not None and (free & ~grasped).sum() >= 4:
        clusters.append(("motion", R.motion_clusters(score, free & ~grasped, graph, points=np.asarray(prob.x0),
                                                     section=section)))
    out = []
    for kind, cl in clusters:
        if cl is None:
            continue
        # held particles join the nearest free cluster first: a part reaching into a support is
        # one piece through it
        cl = R.attach_held(cl, held | (grasped if kind == "motion" else False), prob.x0)
        lab = R.connected_parts(cl, graph, min_size, int(s.select_max_parts))
        if lab is None or (lab < 0).any():
            continue
        if any(R.same_partition(lab, c["labels"]) for c in out):
            if log:
                log(f"parts by {kind}: the same partition as by {', '.join(c['kind'] for c in out)}")
            continue
        out.append({"kind": kind, "labels": lab, "parts": int(lab.max()) + 1})
    return out


def shape_candidate(prob, s: FitSettings) -> dict | None:
    """The parts by shape (`regions.thickness_clusters`: thin against thick), cut as `part_candidates` cuts the colour
    clusters (held particles join the nearest free cluster; pieces smaller than `region_min_share` join their neighbour),
    then one part per class (thin, thick), as {"kind": "thickness", "labels", "parts": 2,
    "thickness_m": (thin, thick) medians}, or None where the object is of one thickness. #24: the parts start's prior
    where the colours are a pattern or one colour (`parts_start.PartsStart`)."""
    from . import regions as R

    st = prob.scene.settings
    P = len(prob.x0)
    held = np.asarray(prob.held_particles(), bool)
    x = np.asarray(prob.x0)
    graph = R.particle_graph(x, 1.6 * st.particle_spacing)
    cl, med = R.thickness_clusters(x, st.particle_spacing, ~held, graph)
    if cl is None:
        return None
    cl = R.attach_held(cl, held, x)
    lab = R.connected_parts(cl, graph, max(8, int(s.region_min_share * P)), int(s.select_max_parts))
    if lab is None or (lab < 0).any():
        return None
    # one part per class (thin, thick): the pieces of a class share one E, two coefficients however many fingers or
    # knots (a 4-part simplex does not converge in the CUDA cap's 20 probes; the bumps after it refine each piece)
    cls = np.array([np.bincount(cl[lab == j], minlength=2).argmax() for j in range(int(lab.max()) + 1)])
    lab = cls[lab]
    if len(np.unique(lab)) < 2:
        return None
    return {"kind": "thickness", "labels": lab.astype(np.int64), "parts": 2, "thickness_m": med}


def _result_inputs(prob, r: FitResult, s: FitSettings):
    """(to-tensor function, the result's trajectories, its effects' values) for simulating a fit result."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=prob.tdtype, device=prob.tdev)  # noqa: E731
    names = prob.sim.slot_names()
    trajs = [t(r.trajectories[n]) for n in names] if names else None
    eff = None
    if r.effect_parameters:
        eff = effect_values(effect_parameters(prob, s.fit_effects, r.effect_parameters), prob.traj_scale)
    return t, trajs, eff


def strain_exposure(prob, youngs, poisson, trajectories=None, effects=None, frames=None,
                    e_bound: float | None = None) -> np.ndarray | None:
    """Each particle's strain exposure over the clip: the mean square over `frames` (default: all
    but the rest frame) of its rotation-free strain, the norm of the Hencky strain log V (F = V R:
    a swing's rotation is no strain), from one rollout of the given material (no gradients). A
    particle that barely strains tells the video nothing about its E (a rope's free tip below the
    hand: its E moves the picture by less than the noise). None if the rollout fails."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=prob.tdtype, device=prob.tdev)  # noqa: E731
    with torch.no_grad(), pinned_substep(prob, e_bound):
        try:
            _, F = prob.simulate(t(youngs), t(poisson), trajectories, effects)
        except SimulationError:
            return None
    return exposure_of_rollout(F, list(range(1, prob.T)) if frames is None else list(frames))


def fill_unconstrained(prob, r: FitResult, s: FitSettings, floor: float | None = None, log=None) -> FitResult:
    """Identifiability as part of the result (#24): the particles the video does not constrain
    (`unconstrained_particles`, from the strain exposure of the fitted field's own rollout) get the
    E of the constrained material they are attached to, the harmonic fill of log E over the particle
    graph (`regions.harmonic_fill`), not the value the optimiser happened to leave there, and
    confidence 0 (the video says nothing about them). The result's E, per Gaussian too, and its
    confidence are replaced in place; `r.model["unconstrained"]` records the rule, the counts, how
    far the fill moved E and the reconstruction loss before and after (all frames, one substep:
    by the rule it barely changes). The animation stays the fitted field's."""
    from .optimize import gaussian_weights
    from .regions import harmonic_fill, particle_graph

    floor = EXPOSURE_FLOOR if floor is None else float(floor)
    t, trajs, eff = _result_inputs(prob, r, s)
    e_top = float(np.max(r.youngs))
    expo = strain_exposure(prob, r.youngs, r.poisson, trajs, eff, e_bound=e_top)
    rec: dict = {"floor": floor, "rule": "strain exposure (mean square rotation-free strain over the clip, the "
                 "fitted field's rollout) below floor x the free particles' median, or held by a support"}
    if expo is None:
        rec["why"] = "the fitted field's rollout failed: nothing marked"
        r.model = {**(r.model or {}), "unconstrained": rec}
        return r
    held = np.asarray(prob.held_particles(), bool)
    unc = unconstrained_particles(expo, held, floor)
    graph = particle_graph(np.asarray(prob.x0, np.float64), 1.6 * float(prob.scene.settings.particle_spacing))
    log_e0 = np.log(np.asarray(r.youngs, np.float64))
    log_e = harmonic_fill(log_e0, ~unc, graph)
    frames = list(range(1, prob.T))
    before = frame_losses(prob, r, s, frames, e_top)
    feats = prob.particle_appearance() if s.appearance > 0 else None
    w, idx = gaussian_weights(prob, feats)
    r.youngs = np.exp(log_e).astype(np.asarray(r.youngs).dtype)
    r.youngs_gaussian = np.exp((w * log_e[idx]).sum(1))
    conf = np.where(unc, 0.0, np.asarray(r.confidence, np.float64))
    r.confidence, r.confidence_gaussian = conf, np.clip((w * conf[idx]).sum(1), 0.0, 1.0)
    after = frame_losses(prob, r, s, frames, max(e_top, float(np.max(r.youngs))))
    moved = np.abs(log_e - log_e0)[unc]
    rec.update(particles=int(unc.sum()), of=int(len(unc)), held=int(held.sum()),
               barely_strained=int((unc & ~held).sum()), median_exposure=float(np.median(expo[~held])) if (~held).any()
               else None, fill="harmonic (log E) over the particle graph from the constrained particles",
               moved_median=float(np.exp(np.median(moved))) if len(moved) else 1.0,
               moved_max=float(np.exp(np.max(moved))) if len(moved) else 1.0,
               loss_before=float(np.mean(before)), loss_after=float(np.mean(after)))
    r.model = {**(r.model or {}), "unconstrained": rec}
    if log:
        log(f"unconstrained: {rec['particles']} of {rec['of']} particles ({rec['held']} held, "
            f"{rec['barely_strained']} strained < {floor:g} x the median): confidence 0, E from the material they are "
            f"attached to (moved {rec['moved_median']:.2f}x median, {rec['moved_max']:.2f}x at most; loss "
            f"{rec['loss_before']:.5f} -> {rec['loss_after']:.5f})")
    return r


# the guard's sign test (`guard_rule`): the field must be lower on so many held-back frames that a coin
# would do it this rarely (one-sided): 4 of 4 frames (p = 1/16); 3 of 4 (p = 5/16) is not "clearly"
GUARD_ALPHA = 0.1


def guard_rule(uniform_val: list[float], field_val: list[float], added: int, s: FitSettings) -> dict:
    """"Never below one number" (#24): the field is kept over the uniform model only if select's test
    keeps it (`select_rule`: the mean held-back drop above the price of its added coefficients) and
    it is lower on so many held-back frames that chance would do so at most `GUARD_ALPHA` of the
    time (a one-sided sign test: select's "most frames" chooses between models; the guard asks for
    clear evidence that a field beats one number). {"keep_field", "sign_p", ... select_rule's}."""
    r = select_rule(uniform_val, field_val, added, s)
    n = len(field_val)
    k = int(r.get("better_frames", 0))
    p = float(sum(math.comb(n, j) for j in range(k, n + 1)) / 2 ** n) if n else 1.0
    keep = bool(r["keep_field"] and p <= GUARD_ALPHA)
    why = r["why"] + (f"; sign test p = {p:.3g} {'<=' if p <= GUARD_ALPHA else '>'} {GUARD_ALPHA}" if n else "")
    return {**r, "keep_field": keep, "sign_p": p, "why": why}


class _Stages:
    """A schedule's stages run one after another: each stage's iterations numbered on from the
    stages before it (for `on_iteration`), their loss histories joined."""

    def __init__(self, on_iteration):
        self.on_iteration, self.used, self.history = on_iteration, 0, []

    def run(self, go):
        base, cb = self.used, self.on_iteration
        r = go(lambda it, *a: cb(base + it, *a) if cb is not None else None)
        self.used += len(r.loss_history)
        self.history.extend(r.loss_history)
        return r


def _stage_budgets(s: FitSettings) -> tuple[int, int, int]:
    """(all iterations N, the uniform model's, the final polish's) of select's and the guard's budget."""
    N = max(int(s.iterations), 0)
    n_final = int(round(s.select_final_share * N)) if N else 0
    n_uni = max(int(round(s.select_uniform_share * N)), 1) if N else 0
    return N, n_uni, n_final


def fit_guarded(prob: FitProblem, s: FitSettings, *, progress: bool = True, log=None, start: dict | None = None,
                on_iteration=None, uniform_e: float | None = None, candidates: dict | None = None) -> FitResult:
    """The bumps schedule with a guard (`FitSettings.uniform_guard`, #24): the bumps field (the
    default schedule, its whole budget) and the uniform model (select's: the bumps start search's E
    polished with nu and the trajectory, `select_uniform_share` of the iterations) both fitted on
    the training frames (`holdout_frames`, as select), judged on the held-back frames at one
    substep; the field is kept only if `guard_rule` says it is clearly better, else the uniform E is
    returned and the field recorded as the rejected candidate (`model["guard"]`). The kept model is
    then polished on all frames (`select_final_share`), with its confidence. A resumed fit, or a
    clip too short to hold frames back, is the plain bumps fit. `candidates`: receives both
    training-frame models (benchmarks)."""
    if start is not None:
        return fit_bumps(prob, s, progress=progress, log=log, start=start, on_iteration=on_iteration)
    say = log or (lambda *a: None)
    train, val = problem_holdout(prob, s)
    if not val:
        r = fit_bumps(prob, s, progress=progress, log=log, on_iteration=on_iteration, uniform_e=uniform_e)
        r.model = {**(r.model or {}), "guard": {"why": "no held-back frames (fewer than 6 frames): the field unjudged"}}
        return r
    view = FrameView(prob, train)
    N, n_uni, n_final = _stage_budgets(s)
    stages = _Stages(on_iteration)
    run = stages.run
    sb = dataclasses.replace(s, confidence_probes=0)
    rb = run(lambda cb: fit_bumps(view, sb, progress=progress, log=log, on_iteration=cb, uniform_e=uniform_e))
    if rb.interrupted:
        rb.model = {**(rb.model or {}), "guard": {"why": "interrupted before the held-back test"}}
        return rb
    su = dataclasses.replace(s, levels=(1,), level_share=(1.0,), iterations=n_uni, confidence_probes=0,
                             trajectory_levels=1, fit_poisson_levels=1, search_effects=())
    ru = run(lambda cb: fit_bumps(view, su, progress=progress, log=log, on_iteration=cb, uniform_e=rb.uniform_start))
    models = {"uniform": ru, "field": rb}
    if candidates is not None:
        candidates.update(models)
    e_top = max(float(np.max(m.youngs)) for m in models.values())
    every = sorted(set(train) | set(val))
    losses = {}
    for name, m in models.items():
        fl = dict(zip(every, frame_losses(prob, m, s, every, e_top)))
        losses[name] = {"training": float(np.mean([fl[k] for k in train])),
                        "held_back": float(np.mean([fl[k] for k in val])), "held_back_frames": [fl[k] for k in val],
                        "median_e": float(np.median(m.youngs))}
    k_field = int(max(s.levels))
    test = guard_rule(losses["uniform"]["held_back_frames"], losses["field"]["held_back_frames"], max(k_field - 1, 1), s)
    chosen = "field" if test["keep_field"] else "uniform"
    say(f"guard: {chosen} ({test['why']})")
    guard = {"chosen": chosen, "rejected": "uniform" if chosen == "field" else "field", "training_frames": train,
             "held_back_frames": val, "models": losses, "test": test, "judged_at_e": e_top}
    if ru.interrupted:
        chosen, guard["why"] = "field", "the uniform model was interrupted: the field unjudged"
    r0 = models[chosen]
    levels = (1,) if chosen == "uniform" else (k_field,)
    sc = dataclasses.replace(s, levels=levels, level_share=(1.0,), iterations=n_final, search_effects=(),
                             trajectory_levels=1, fit_poisson_levels=1 if chosen == "uniform" else s.fit_poisson_levels)
    r = run(lambda cb: fit_bumps(prob, sc, progress=progress, log=log, on_iteration=cb, start=start_of(r0)))
    r.loss_history = stages.history
    r.uniform_start = rb.uniform_start
    r.interrupted = r.interrupted or ru.interrupted
    r.settings = {**r.settings, **{k: v for k, v in dataclasses.asdict(s).items() if k not in ("levels", "level_share")},
                  "levels": list(s.levels), "level_share": list(s.level_share), "iterations": int(s.iterations)}
    model = {"schedule": "bumps", "chosen": chosen, "guard": guard}
    if (rb.model or {}).get("uniform_probes"):
        model["uniform_probes"] = rb.model["uniform_probes"]      # the start search's (training frames)
    r.model = {**{k: v for k, v in (r.model or {}).items() if k not in ("schedule", "uniform_probes")}, **model}
    return r


def start_of(r: FitResult) -> dict:
    """A fit result as another fit's start (`fit_bumps(start=...)`). Copies: on the CPU a fit started
    from these arrays optimises them in place (`torch.as_tensor` shares a numpy array's memory),
    which rewrote the trajectory of every model started from (uniform, parts) and made later
    candidates start from the last fit's trajectory."""
    return {"youngs": np.array(r.youngs), "poisson": np.array(r.poisson),
            "trajectories": {n: np.array(v) for n, v in (r.trajectories or {}).items()},
            "effects": r.effect_parameters}


# the motion score's section average (`regions.motion_clusters(section=...)`): a ball of this many
# object thicknesses (a ball centred on one face of a rod reaches across the section and about as far
# along it either way, so the two faces average nearly the same particles; on a rod whose score flips
# across the section at 5x its trend along the length, 1 thickness still cut 15% of the ends wrongly)
SECTION_BALL = 1.5


def object_thickness(prob) -> float | None:
    """The object's thinnest part (metres) from its particles at rest (`thickness.thinnest_part` on
    their occupancy at the particle spacing); None if it cannot be measured."""
    from ..thickness import occupancy, thinnest_part

    try:
        h = float(prob.scene.settings.particle_spacing)
        th = thinnest_part(occupancy(np.asarray(prob.x0, np.float64), h), h)
    except (ValueError, AttributeError):
        return None
    return float(th.thinnest) if math.isfinite(th.thinnest) and th.thinnest > 0 else None


def part_score(prob, r: FitResult, s: FitSettings, frames) -> np.ndarray | None:
    """dL/dlog E per particle at a fit result (training frames; one forward and backward pass; zero
    on held particles): where the material wants to be stiffer (negative) or softer."""
    t, trajs, eff = _result_inputs(prob, r, s)
    log_e = torch.log(t(r.youngs)).requires_grad_(True)
    try:
        with torch.enable_grad():
            out = prob.loss(torch.exp(log_e), t(r.poisson), trajs, eff, frames=frames)
            g, = torch.autograd.grad(out["rec"], log_e)
    except SimulationError:
        return None
    g = g.detach().cpu().numpy().astype(np.float64)
    g[np.asarray(prob.held_particles(), bool)] = 0.0
    return g if np.isfinite(g).all() else None


class PartProbe:
    """The reconstruction loss on `frames` of a piecewise-constant E (one log E per part), the
    nu, trajectories and effects held; no gradients, cached per log-E vector. A probe that goes
    unstable or leaves the grid is inf. `weights` (P, m) instead of `labels`: log E = weights @ le (a
    trend's two ends, fit/trend_start.py)."""

    def __init__(self, prob, frames, labels, nu, trajs, effects, batch: str = "cuda", weights=None):
        self.prob, self.frames = prob, list(frames)
        self.weights = None if weights is None else np.asarray(weights, np.float64)
        self.labels = (np.asarray(labels, np.int64) if weights is None
                       else np.argmax(self.weights, axis=1).astype(np.int64))
        self.nu, self.trajs, self.effects, self.batch = nu, trajs, effects, batch
        self.cache: dict[tuple, float] = {}
        self.given = 0      # values taken from elsewhere (`remember`), not run here

    def _E(self, le) -> torch.Tensor:
        le = np.asarray(le, np.float64)
        e = np.exp(self.weights @ le) if self.weights is not None else np.exp(le)[self.labels]
        return torch.as_tensor(e, dtype=self.prob.tdtype, device=self.prob.tdev)

    @staticmethod
    def key(le) -> tuple:
        return tuple(round(float(v), 10) for v in le)

    def remember(self, le, value: float) -> None:
        """Take `value` as this probe's loss at `le` (the same field's loss probed by another PartProbe on the
        same frames, e.g. the uniform E of every trend axis)."""
        self.cache[self.key(le)] = float(value)
        self.given += 1

    @property
    def forwards(self) -> int:
        """The forwards this probe ran (its cache less the values it was given)."""
        return len(self.cache) - self.given

    def __call__(self, le) -> float:
        key = self.key(le)
        if key not in self.cache:
            try:
                with torch.no_grad(), kept_rung(self.prob):   # a probe leaves the substep's rung as it found it
                    v = float(self.prob.loss(self._E(key), self.nu, self.trajs, self.effects, frames=self.frames)["rec"])
            except SimulationError:
                v = float("inf")
            self.cache[key] = v if math.isfinite(v) else float("inf")
        return self.cache[key]

    def many(self, les: list) -> list[float] | None:
        """Several probes as tiled copies in few rollouts on a GPU (`FitProblem.losses_batch`);
        None where that does not apply (the CPU, a scene that cannot be tiled). Their values are
        taken at the stiffest copy's substep, so they choose where to look, and the chosen point
        is probed on its own."""
        from ..sim.batch import TilingError

        if self.batch == "never" or (self.batch == "cuda" and not str(self.prob.tdev).startswith("cuda")):
            return None
        E = torch.stack([self._E(le) for le in les])
        try:
            vals = self.prob.losses_batch(E, self.nu, self.trajs, self.effects, frames=self.frames)
        except TilingError:
            return None
        return [float(v) for v in vals]


def part_sweep(f: PartProbe, start: np.ndarray, grid: np.ndarray, s: FitSettings) -> dict:
    """Coordinate search of each part's log E (forward passes only): in the first round, each
    part in turn (largest first) over the whole `grid` of log E, the others held, then a
    golden-section refinement in the best probe's bracket (`search_evals` probes); later rounds
    refine each part by a golden section (3 probes) within one grid step of where it is. Returns {"log_e", "loss", "lines": per
    part {log E: loss} of its last line}."""
    cur = np.asarray(start, np.float64).copy()
    lo, hi = float(grid[0]), float(grid[-1])
    step = float(grid[1] - grid[0]) if len(grid) > 1 else 1.0
    sizes = np.bincount(f.labels, minlength=len(cur))
    order = list(np.argsort(-sizes))
    lines: dict[int, dict] = {}
    best = f(cur)
    for rnd in range(max(int(s.select_part_rounds), 1)):
        for j in order:
            line: dict[float, float] = {float(cur[j]): best}

            def g(x, j=j, line=line):
                le = cur.copy()
                le[j] = x
                v = f(le)
                line[float(x)] = v
                return v

            if rnd == 0:
                pts = [cur.copy() for _ in grid]
                for p, x in zip(pts, grid):
                    p[j] = x
                vals = f.many(pts)
                if vals is None:
                    vals = [g(float(x)) for x in grid]
                else:
                    g(float(grid[int(np.argmin(vals))]))
                i = int(np.argmin(vals))
                a, b = max(lo, float(grid[i]) - step), min(hi, float(grid[i]) + step)
            else:
                a, b = max(lo, cur[j] - step), min(hi, cur[j] + step)
            golden_section(g, a, b, s.search_evals if rnd == 0 else min(int(s.search_evals), 3))
            x = min(line, key=line.get)
            if line[x] < best:
                best, cur[j] = line[x], x
            lines[int(j)] = line
    return {"log_e": cur, "loss": best, "lines": lines}


def _bracket_vertex(hp: float, fp: float, hm: float, fm: float, f0: float) -> tuple | None:
    """(offset, predicted drop) of the parabola's vertex through (0, f0), (hp, fp), (hm, fm), hm < 0 < hp or the
    reverse, with fp and fm >= f0 (a bracketed minimum): the offset within the bracket, the drop f0 minus the
    parabola's minimum (>= 0); None where the three are flat or not finite."""
    if not all(math.isfinite(v) for v in (fp, fm, f0)) or hp * hm >= 0:
        return None
    a, b = fp - f0, fm - f0
    if a <= 0 and b <= 0:
        return None
    qa = (a / hp - b / hm) / (hp - hm)           # f0 + qb x + qa x^2 through the three
    qb = a / hp - qa * hp
    if not qa > 0:
        return None
    d = float(np.clip(-qb / (2.0 * qa), min(hp, hm), max(hp, hm)))
    return d, max(qb * qb / (4.0 * qa), 0.0)


class _Stalled(Exception):
    """part_refine's simplex stopped: its best probe did not improve for a while (`stall`)."""


def _first_simplex(x0: np.ndarray, step: float, lo: float, hi: float) -> np.ndarray:
    """`part_refine`'s first simplex: `x0` and one vertex `step` along each part (-`step` where + leaves [lo, hi])."""
    n = len(x0)
    return np.vstack([x0] + [np.clip(x0 + step * np.eye(n)[j] * (1 if x0[j] + step <= hi else -1), lo, hi)
                             for j in range(n)])


def _mirror(x0: np.ndarray, v: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """A vertex `v` mirrored through `x0` (the two-sided simplex's other side), within [lo, hi]."""
    return np.clip(2 * x0 - v, lo, hi)


def first_vertices(f: PartProbe, log_e: np.ndarray, step: float, lo: float, hi: float, two_sided: bool = False) -> list:
    """The losses `part_refine` probes first from `log_e` (its start and its first simplex's vertices, each mirrored as
    its `two_sided` rule does where the vertex renders no better than the start; not the `bracket` rule's parabola):
    a screen of a simplex before it runs (fit/trend_start.starts_hook ranks the parts start against the trend start
    by it). The same points, so a `part_refine` on the same probe afterwards takes them from its cache."""
    x0 = np.clip(np.asarray(log_e, np.float64), lo, hi)
    start = f(x0)
    vals = [start]
    if not math.isfinite(start):
        return vals
    simplex = _first_simplex(x0, step, lo, hi)
    for j in range(len(x0)):
        fp = f(simplex[j + 1])
        vals.append(fp)
        if two_sided and fp >= start:
            other = _mirror(x0, simplex[j + 1], lo, hi)
            if not np.allclose(other, x0):
                vals.append(f(other))
    return vals


def part_refine(f: PartProbe, log_e: np.ndarray, lo: float, hi: float, evals: int, step: float = math.log(1.25),
                xtol: float = math.log(1.02), stall: tuple | None = None, two_sided: bool = False,
                bracket: bool = False, stall_after_simplex: bool = False, extend: tuple | None = None) -> dict:
    """All parts' log E together by a Nelder-Mead simplex (scipy; forward passes only) from the
    coordinate sweep's best `log_e`, a first simplex `step` wide along each part, within [lo, hi],
    at most `evals` probes. The parts' loss is a narrow valley that runs across the axes (a softer
    part at the hand and a stiffer one at the clamp move the tip alike), where a search along one
    part at a time stalls on the valley's floor short of its minimum; a simplex turns along it.
    `two_sided`: the first simplex's vertex along a part whose +`step` probe renders no better than the start is
    taken at -`step` instead, when that one is better (an extra probe): from the uniform E one part must soften and
    another stiffen, and a first simplex all on the stiff side spends its probes finding the way down (the demo's
    two parts, 2026-11-27: no gain in 7 probes). `stall` = (k, tol): the simplex also stops once its last k probes brought no new best more than tol
    (relative) below the best before them (the fit's plateau rule on the probes; None: off).
    `bracket` (with `two_sided`): a part whose x`step` and x1/`step` probes both render worse than the start has its
    minimum between them; where the parabola through the three probes puts it > `step` / 8 off the start or predicts a
    drop above the stall tolerance, the part's first vertex goes there (one more probe) instead of the x`step` side
    (#24, 2026-11-27: the H200's telephone_cable, whose coil wants 0.86x the uniform E, kept its x2 vertex and the
    simplex stalled before turning towards it); where every part is bracketed, none so, and the drops add up to less
    than the tolerance, the simplex stops there, with nothing found. Off in the parts start: on the CPU's foam_bar at
    grid 12 its stiff part's vertex at 1.09x sent the cut simplex to a parts' MA of 0.509 instead of 0.979
    (docs/benchmarks/fit.md, "Why the cheap parts start lost telephone_cable"). `stall_after_simplex`: the stall
    clock starts after the first simplex's vertices (their order is no descent: counted, a 3-part simplex stalled 3
    probes after its vertices on that scene); off in the parts start (the CPU's cut simplex is acf1acc's).
    `extend` = (max_evals, k, tol): a simplex still descending at `evals` goes on, up to `max_evals` probes, until its
    last k probes bring no new best more than tol (relative) below the best before them (the uncut simplex's budget
    read as a floor, not a cut: a long clip's valley, narrowed by the free swing's phase, is still being descended at
    the cap; #24, foam_bar at 36 frames: 0.0402 at the cap, 0.0387 by probe 35, the truth's parts within 4%).
    Returns {"log_e", "loss", "probes", "stalled", "extended" (probes beyond `evals`)} (the start if nothing better was
    found)."""
    from scipy.optimize import minimize

    x0 = np.clip(np.asarray(log_e, np.float64), lo, hi)
    n = len(x0)
    start = f(x0)
    out = {"log_e": x0, "loss": start, "probes": 0}
    if evals < n + 1 or not math.isfinite(start):
        return out
    simplex = _first_simplex(x0, step, lo, hi)
    if two_sided:
        drops: list = []       # per part bracketed on both sides: the drop its parabola predicts (None: not bracketed)
        moved = [False] * n    # ... and whether its vertex went to the parabola's
        tol = float(stall[1]) if stall is not None else 0.005
        for j in range(n):
            fp = f(simplex[j + 1])
            drops.append(None)
            if fp >= start:
                other = _mirror(x0, simplex[j + 1], lo, hi)
                if np.allclose(other, x0):
                    continue
                fm = f(other)
                if fm < start:
                    simplex[j + 1] = other
                elif bracket:
                    vx = _bracket_vertex(simplex[j + 1][j] - x0[j], fp, other[j] - x0[j], fm, start)
                    if vx is not None:
                        drops[j] = vx[1]
                        if abs(vx[0]) > abs(step) / 8 or vx[1] > tol * abs(start):
                            # the part's minimum is > 9% off the start (x2 ** (1/8); MA's tolerance is 20%) or its drop
                            # above the stall tolerance: worth a probe; else the x`step` vertex (probed already) stays,
                            # as the demo's stiff part (x2 +96%, x0.5 +101%: its vertex 1.008x) keeps its probes
                            d = vx[0] if abs(vx[0]) >= abs(step) / 8 else math.copysign(abs(step) / 8, vx[0])
                            simplex[j + 1] = np.clip(x0 + d * np.eye(n)[j], lo, hi)   # (>= step / 8: a simplex)
                            moved[j] = True
        if bracket and all(d is not None for d in drops) and not any(moved) and sum(drops) <= tol * abs(start):
            # every part worse both ways, each one's minimum near the start and the parabolas' drops together within
            # the stall tolerance: the simplex would find nothing (the H200's toy_rope, tow_rope, basketball,
            # hemp_rope, knit_cap: gain 0.00000 in 6-8 probes); stop
            out.update(stalled=True)
            return out
    before = len(f.cache)
    seen: list = []          # (loss, log E) of each probe, in order

    def g(v):
        x = np.clip(v, lo, hi)
        val = f(x)
        seen.append((val, x.copy()))
        if stall is not None and len(seen) > int(stall[0]) + (n if stall_after_simplex else 0):
            if _no_new_best(seen, int(stall[0]), float(stall[1])):
                raise _Stalled
        if extend is not None and len(seen) >= int(evals) and _no_new_best(seen, int(extend[1]), float(extend[2])):
            raise _Stalled
        return val

    try:
        r = minimize(g, x0, method="Nelder-Mead", bounds=[(lo, hi)] * n,
                     options={"initial_simplex": simplex, "xatol": xtol, "fatol": 1e-4 * abs(start),
                              "maxfev": int(extend[0]) if extend is not None else int(evals)})
        x = np.clip(np.asarray(r.x, np.float64), lo, hi)
    except _Stalled:
        out["stalled"] = True
        x = min(seen, key=lambda p: p[0])[1]
    v = f(x)
    out["extended"] = max(0, len(seen) - int(evals))
    out["probes"] = len(f.cache) - before
    if v < start:
        out.update(log_e=x, loss=v)
    return out


def _no_new_best(seen: list, k: int, tol: float) -> bool:
    """Whether the last `k` of the probes `seen` ((loss, log E) in order) brought no new best more than `tol`
    (relative) below the best before them (False while fewer than k + 1 were seen)."""
    if len(seen) <= k:
        return False
    prior = min(u for u, _ in seen[:-k])
    return math.isfinite(prior) and not any(u < prior - tol * abs(prior) for u, _ in seen[-k:])


def _line_interval(line: dict, rise: float) -> list[float]:
    """The hull of one part's probed E within `rise` (a share) of its line's best: [lo, hi] Pa."""
    fin = {k: v for k, v in line.items() if math.isfinite(v)}
    if not fin:
        return [float("nan"), float("nan")]
    best = min(fin.values())
    near = [k for k, v in fin.items() if v <= best * (1.0 + rise)]
    return [math.exp(min(near)), math.exp(max(near))]


def fit_parts(prob, s: FitSettings, labels: np.ndarray, log_e: np.ndarray, start: dict, iterations: int, *,
              progress: bool = False, log=None, on_iteration=None, confidence_probes: int = 0) -> FitResult:
    """A piecewise-constant E (one per part of `labels`) and one nu, polished by AdamW from
    `log_e` (per part) and `start` ({"poisson", "trajectories", "effects"}) for `iterations` steps
    (cosine-annealed; the trajectory too when `s.joint`); the best iterate is kept. The result's
    `regions` are the labels; `model["part_fit"]` each part's E, particles and, with
    `confidence_probes`, its 95% interval from the loss's curvature (`optimize.confidence`)."""
    from .material import MaterialField
    from .optimize import assemble_result, confidence, frame_metrics

    t0 = time.perf_counter()
    st = prob.scene.settings
    labels = np.asarray(labels, np.int64)
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                        device=prob.tdev, seed=s.seed)
    nu0 = float(np.median(start["poisson"])) if start.get("poisson") is not None else st.poisson_default
    mat.set_uniform(math.exp(float(np.mean(log_e))), min(nu0, 0.98 * st.poisson_max))
    mat.set_regions(labels)
    mat.set_region_log_e(np.clip(log_e, mat.lo + 1e-3, mat.hi - 1e-3))
    names = prob.sim.slot_names()
    trajs = [t.clone() for t in prob.initial_trajectories()]
    for i, n in enumerate(names):
        if n in (start.get("trajectories") or {}):
            # a copy: on the CPU `as_tensor` would share the start's array, and the optimiser's
            # in-place steps would rewrite the trajectory of the model the fit started from
            trajs[i] = torch.tensor(np.array(start["trajectories"][n]), dtype=prob.tdtype, device=prob.tdev)
    eff_raw = effect_parameters(prob, s.fit_effects, start.get("effects") or None)

    def eff_now():
        return effect_values(eff_raw, prob.traj_scale) if eff_raw else None

    fit_traj = bool(s.joint and trajs)
    for t in trajs:
        t.requires_grad_(fit_traj)
    groups = [{"params": [mat.theta], "lr": s.lr_material}, {"params": [mat.w_nu], "lr": s.lr_poisson}]
    if fit_traj:
        groups.append({"params": trajs, "lr": s.lr_trajectory})
    eff = [v for ps in eff_raw.values() for v in ps.values()]
    if eff:
        groups.append({"params": eff, "lr": s.lr_effects})
    opt = AdamW(groups, weight_decay=s.weight_decay)
    base = [g["lr"] for g in opt.param_groups]

    def snap():
        return _level_params(mat, trajs, eff_raw)

    def restore(b):
        _restore_in_place(mat, trajs, b, eff_raw)

    best_v, best = float("inf"), snap()
    history: list[float] = []
    interrupted = False
    n = max(int(iterations), 0)
    bar = None
    if progress and n:
        from tqdm import tqdm

        bar = tqdm(total=n, desc="fit parts", unit="it", dynamic_ncols=True, leave=False)
    try:
        for j in range(n):
            cosine_lr(opt, base, j, n)
            opt.zero_grad(set_to_none=True)
            try:
                out = prob.loss(mat.youngs(), mat.poisson(), trajs if trajs else None, effects=eff_now())
            except SimulationError as exc:
                if log:
                    log(f"parts iteration {j}: {exc}; halving the step")
                for g in opt.param_groups:
                    g["lr"] *= 0.5
                restore(best)
                continue
            total = out["rec"] + out["reg_traj"]
            lv = float(total.detach())
            history.append(lv)
            if lv < best_v:
                best_v, best = lv, snap()
            total.backward()
            clean_gradients(opt, trajs)
            opt.step()
            if on_iteration is not None:
                on_iteration(j + 1, lv, mat, trajs)
            if bar is not None:
                bar.set_postfix(loss=f"{lv:.4f}", parts=mat.K)
                bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        if log:
            log("interrupted: keeping the best iterate so far")
    finally:
        if bar is not None:
            bar.close()
    if history:
        restore(best)
    for t in trajs:
        t.requires_grad_(False)
    E, nu = mat.youngs().detach(), mat.poisson().detach()
    tr = [t.detach() for t in trajs] if trajs else None
    with torch.no_grad():
        out = prob.loss(E, nu, tr, effects=eff_now(), frames=range(1, prob.T), keep_renders=True)
        final_loss = float(out["rec"] + out["reg_traj"])
        x, F = out["x"], out["F"]
        renders = {0: {k: v.detach() for k, v in prob.render_frame(0, x[0], F[0]).items()}, **out["renders"]}
    metrics = frame_metrics(prob, renders)
    conf = np.ones(len(prob.x0))
    le = mat.region_log_e()
    parts = [{"e": float(math.exp(v)), "particles": int((labels == r).sum())} for r, v in enumerate(le)]
    if confidence_probes > 0 and not interrupted:
        conf, sigma = confidence(prob, mat, trajs, confidence_probes, seed=s.seed, return_sigma=True,
                                 effects=eff_now(), covariance=s.confidence_covariance)
        for r, p in enumerate(parts):
            sg = float(np.median(sigma[labels == r]))
            p["interval_95"] = [float(math.exp(le[r] - 1.96 * sg)), float(math.exp(le[r] + 1.96 * sg))]
    # the Gaussians take their values from the particles of their own colour (as the bumps field's do)
    feats = prob.particle_appearance() if s.appearance > 0 else None
    res = assemble_result(prob, s, E, nu, conf, trajs, x, F, metrics, feats, history, final_loss, t0, interrupted,
                          math.exp(float(np.mean(le))), regions=labels.copy(), model={"part_fit": parts},
                          effect_parameters=fitted_values(eff_raw, prob.traj_scale) if eff_raw else {})
    # a part's few coefficients can give a confidence of exactly 1, which the Gaussians' weights
    # (float32, summing to 1 within rounding) must not push above 1
    res.confidence = np.clip(res.confidence, 0.0, 1.0)
    res.confidence_gaussian = np.clip(res.confidence_gaussian, 0.0, 1.0)
    return res


def parts_stage(prob, view, s: FitSettings, uni: dict, ru: FitResult, iterations: int, *, progress=False, log=None,
                on_iteration=None, attach_grasped: bool = False, section_cut: bool = False,
                exposure_floor: float = 0.0) -> tuple[FitResult | None, dict]:
    """The parts step (module doc, 3.): candidate partitions (`part_candidates`), each part's E
    by a coordinate sweep (`part_sweep`) from the uniform model's E, and the best candidate's also
    from the uniform stage's other distinct minima (`select_part_starts`; the loss of a part can be
    needle-like and multimodal in E: a field that starts in the uniform optimum's well stays
    there), the best sweep refined by a simplex over all its parts' E (`part_refine`,
    `select_part_refine` probes per part; only when the sweep's parts differ by `PARTS_MIN_RATIO`
    or more) and polished by AdamW (`fit_parts`) on the training frames. Returns (the parts model or None, its record)."""
    say = log or (lambda *a: None)
    st = prob.scene.settings
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=prob.tdtype, device=prob.tdev)  # noqa: E731
    score = part_score(prob, ru, s, view._frames)
    rec: dict = {"candidates": []}
    section = object_thickness(prob) if section_cut else None
    section = SECTION_BALL * section if section else None
    unconstrained = None
    if section_cut:
        rec["section_m"] = section
    if exposure_floor > 0:
        _, trajs_u, eff_u = _result_inputs(prob, ru, s)
        expo = strain_exposure(prob, ru.youngs, ru.poisson, trajs_u, eff_u, frames=view._frames,
                               e_bound=float(np.max(ru.youngs)))
        if expo is not None:
            free = ~np.asarray(prob.held_particles(), bool)
            unconstrained = free & (expo < float(exposure_floor) * float(np.median(expo[free])))
            rec["unconstrained"] = {"floor": float(exposure_floor), "particles": int(unconstrained.sum())}
            say(f"parts: {int(unconstrained.sum())} of {int(free.sum())} free particles barely strain (exposure "
                f"< {exposure_floor:g} x the median): no part of their own")
    cands = part_candidates(prob, s, score, log=log, attach_grasped=attach_grasped, section=section,
                            unconstrained=unconstrained)
    if not cands:
        rec["why"] = "no candidate parts (one colour, and the motion does not split the object)"
        say(f"parts: {rec['why']}")
        return None, rec
    names = prob.sim.slot_names()
    trajs = [t(ru.trajectories[n]) for n in names] if names else None
    eff = None
    if ru.effect_parameters:
        eff = effect_values(effect_parameters(prob, s.fit_effects, ru.effect_parameters), prob.traj_scale)
    nu_t = t(ru.poisson)
    lo, hi = math.log(st.youngs_min), math.log(st.youngs_max)
    grid = np.linspace(lo + 0.01 * (hi - lo), hi - 0.01 * (hi - lo), max(int(s.select_part_points), 3))
    # where to start: the uniform model's E and the uniform stage's other minima (distinct by > 1.5x)
    starts = [float(np.exp(np.mean(np.log(ru.youngs))))]
    for m in uni.get("minima", []):
        if all(abs(math.log(m["e"] / e)) > math.log(1.5) for e in starts):
            starts.append(float(m["e"]))
    starts = starts[: max(int(s.select_part_starts), 1)]
    best = None
    recs = {}

    def sweep(c, e0):
        nonlocal best
        if "probe" not in c:
            c["probe"] = PartProbe(view, view._frames, c["labels"], nu_t, trajs, eff, s.select_sweep_batch)
            recs[id(c)] = {"kind": c["kind"], "parts": c["parts"], "particles": np.bincount(c["labels"]).tolist(),
                           "starts": []}
            rec["candidates"].append(recs[id(c)])
        f = c["probe"]
        r = part_sweep(f, np.full(c["parts"], math.log(e0)), grid, s)
        recs[id(c)]["starts"].append({"from_e": e0, "loss": r["loss"], "e": [math.exp(v) for v in r["log_e"]],
                                      "interval": [_line_interval(r["lines"].get(j, {}), s.select_interval_rise)
                                                   for j in range(c["parts"])]})
        recs[id(c)]["probes"] = len(f.cache)
        say(f"parts by {c['kind']} ({c['parts']} parts) from uniform {e0:.4g} Pa: E "
            + ", ".join(f"{math.exp(v):.4g}" for v in r["log_e"]) + f" Pa, training loss {r['loss']:.5f}")
        if best is None or r["loss"] < best[1]["loss"]:
            best = (c, r)

    # every candidate from the uniform model's E; the best one also from the other starts
    for c in cands:
        sweep(c, starts[0])
    lead = best[0]
    for e0 in starts[1:]:
        sweep(lead, e0)
    c, r = best
    if not math.isfinite(r["loss"]):
        rec["why"] = "every part sweep went unstable or left the grid"
        return None, rec
    rec["kind"], rec["particles"] = c["kind"], np.bincount(c["labels"]).tolist()
    n_ref = int(s.select_part_refine) * c["parts"]
    spread = float(np.exp(np.max(r["log_e"]) - np.min(r["log_e"])))
    # only parts the sweep found distinct materials: where it found one material, a simplex along
    # the flat direction between the parts fits noise (a uniform bar's two stripe colours came
    # apart and paid the held-back price)
    if n_ref > 0 and spread >= PARTS_MIN_RATIO:
        ref = part_refine(c["probe"], r["log_e"], float(grid[0]), float(grid[-1]), n_ref)
        rec["refine"] = {"from_e": [math.exp(v) for v in r["log_e"]], "e": [math.exp(v) for v in ref["log_e"]],
                         "from_loss": r["loss"], "loss": ref["loss"], "probes": ref["probes"]}
        say(f"parts by {c['kind']}: simplex over the parts' E together ({ref['probes']} probes): E "
            + ", ".join(f"{math.exp(v):.4g}" for v in ref["log_e"]) + f" Pa, training loss {ref['loss']:.5f}")
        r = {**r, "log_e": ref["log_e"], "loss": ref["loss"]}
    start = {"poisson": np.array(ru.poisson), "trajectories": {n: np.array(v) for n, v in (ru.trajectories or {}).items()},
             "effects": ru.effect_parameters}
    rp = fit_parts(view, s, c["labels"], r["log_e"], start, iterations, progress=progress, log=log,
                   on_iteration=on_iteration)
    rec["sweep_loss"] = r["loss"]
    return rp, rec


def frame_losses(prob: FitProblem, r: FitResult, s: FitSettings, frames, e_bound: float | None = None) -> list[float]:
    """The reconstruction loss of each of `frames` for a fit result (one forward pass). `e_bound`:
    simulate at the adaptive substep of that stiffness (`pinned_substep`), not the one the
    simulator happens to hold."""
    t, trajs, eff = _result_inputs(prob, r, s)
    return field_frame_losses(prob, t(r.youngs), t(r.poisson), trajs, eff, frames, e_bound)


def field_frame_losses(prob: FitProblem, E: torch.Tensor, nu: torch.Tensor, trajs, eff, frames,
                       e_bound: float | None = None) -> list[float]:
    """`frame_losses` for a field given as tensors (E, nu, the trajectories and effects' values); inf where the
    simulation fails."""
    with torch.no_grad(), pinned_substep(prob, e_bound):
        try:
            x, F = prob.simulate(E, nu, trajs, eff)
        except SimulationError:
            return [float("inf")] * len(frames)
        return [float(prob.frame_loss(k, prob.render_frame(k, x[k], F[k]))["total"]) for k in frames]


SIGN_P = 0.125      # a start's field must also be lower on so many held-back frames that a fair coin would do so
                    # with p <= this (`heldback_test`; the trend start's rule, fit/trend_start.py)


def sign_test_p(better: int, n: int) -> float:
    """One-sided sign test: the chance that a fair coin comes up `better` or more times in `n`."""
    return float(sum(math.comb(n, k) for k in range(int(better), n + 1)) / 2.0 ** n) if n > 0 else 1.0


def heldback_test(prob: FitProblem, s: FitSettings, E0, E1, added: int, nu, trajs, eff,
                  frames) -> dict:
    """A start's field E1 against the field E0 it would replace (per-particle E, arrays or tensors), on the held-back `frames` at one substep (the
    stiffer field's): kept when `select_rule` keeps it (its mean drop beyond the price of `added` coefficients) and
    it is lower on so many frames that a coin would not be (sign test p <= SIGN_P). {"keep", "why", "sign_p",
    "rule"}."""
    E0, E1 = (torch.as_tensor(np.asarray(e), dtype=prob.tdtype, device=prob.tdev) for e in (E0, E1))
    bound = float(max(float(E0.max()), float(E1.max())))
    h0 = field_frame_losses(prob, E0, nu, trajs, eff, frames, bound)
    h1 = field_frame_losses(prob, E1, nu, trajs, eff, frames, bound)
    rule = select_rule(h0, h1, int(added), s)
    p = sign_test_p(int(rule.get("better_frames", 0)), len(frames))
    keep = bool(rule["keep_field"] and p <= SIGN_P)
    why = f"{rule['why']} (sign test p {p:.3f}{' <= ' if p <= SIGN_P else ' > '}{SIGN_P})"
    return {"keep": keep, "why": why, "sign_p": p, "rule": rule}


def select_rule(uniform_val: list[float], field_val: list[float], added: int, s: FitSettings) -> dict:
    """The held-back test (module doc, 4.): {"keep_field", "mean_drop", "penalty", "better_frames",
    "why", "loss0" (the simpler model's mean held-back loss)}."""
    u, f = np.asarray(uniform_val, float), np.asarray(field_val, float)
    if not len(u):
        return {"keep_field": False, "why": "no held-back frames (fewer than 6 frames): the simpler model"}
    d = u - f
    mean = float(d.mean())
    penalty = float(s.select_penalty * added * u.mean())
    better = int((d > 0).sum())
    keep = bool(np.isfinite(f).all() and mean > penalty and better > len(d) / 2)
    why = (f"held-back loss {u.mean():.5f} -> {f.mean():.5f}: mean drop {mean:.2e} "
           f"{'>' if mean > penalty else '<='} the price of {added} more coefficients {penalty:.2e}; lower on "
           f"{better} of {len(d)} held-back frames")
    return {"keep_field": keep, "mean_drop": mean, "penalty": penalty, "better_frames": better, "why": why,
            "loss0": float(u.mean())}


def fit_select(prob: FitProblem, s: FitSettings, *, progress: bool = True, log=None, start: dict | None = None,
               on_iteration=None, uniform_e: float | None = None, candidates: dict | None = None,
               field_uniform_iterations: int | None = None, attach_grasped: bool = False,
               section_cut: bool = False, exposure_floor: float = 0.0) -> FitResult:
    """The "select" schedule (module doc). A resumed fit (`start`) goes on with the bumps field.
    `candidates` (a dict, optional): receives every candidate model's FitResult by name, trained on
    the training frames (benchmarks: what each candidate would have scored).
    `field_uniform_iterations` (benchmarks): the field from the uniform model's iterations (default:
    the field step's, n; the bumps ladder spends `level_share[-1]` of its budget there, 15 of 20).
    `attach_grasped` (benchmarks): `part_candidates`' option. `section_cut`, `exposure_floor`
    (benchmarks, #24): the motion score averaged over the object's thickness before the cut, and the
    particles strained less than `exposure_floor` x the median (the uniform model's rollout) given
    no motion part of their own (`parts_stage`)."""
    if start is not None:
        return fit_bumps(prob, s, progress=progress, log=log, start=start, on_iteration=on_iteration)
    say = log or (lambda *a: None)
    st = prob.scene.settings
    nu0 = min(st.poisson_default, 0.98 * st.poisson_max)
    train, val = problem_holdout(prob, s)
    view = FrameView(prob, train)
    N, n_uni, n_final = _stage_budgets(s)
    stages = _Stages(on_iteration)
    run = stages.run
    # 1. the uniform stage
    if uniform_e is not None:   # a search already found it (app: the support sizing)
        uni = {"e": float(uniform_e), "loss": None, "shape": "given", "minima": [], "sweep": {}, "skipped": []}
    else:
        uni = uniform_stage(prob, train, s, nu0, log=log, progress=progress)
    say(f"uniform E: {uni['e']:.4g} Pa (loss curve {uni['shape']}; minima "
        + ", ".join(f"{m['e']:.4g} Pa [{m['interval'][0]:.3g}, {m['interval'][1]:.3g}]" for m in uni["minima"]) + ")")
    model = {"schedule": "select", "held_back_frames": val, "training_frames": train, "uniform_stage": uni}
    # 2. the uniform model; 3. parts; 4. the field from the simpler model kept
    k_field = int(s.levels[-1])
    with_parts = bool(s.select_parts)
    n_parts = max(int(round(s.select_parts_share * N)), 1) if (N and with_parts) else 0
    n_field = max(N - n_uni - n_final - n_parts, 1 if N else 0)
    su = dataclasses.replace(s, levels=(1,), level_share=(1.0,), iterations=n_uni, confidence_probes=0,
                             trajectory_levels=1, fit_poisson_levels=1)
    ru = run(lambda cb: fit_bumps(view, su, progress=progress, log=log, on_iteration=cb, uniform_e=uni["e"]))
    models = {"uniform": ru}
    coeffs = {"uniform": 1}
    losses = {}

    def judge(name, e_bound=None):
        r_ = models[name]
        every = sorted(set(train) | set(val))           # one forward pass for both
        fl = dict(zip(every, frame_losses(prob, r_, s, every, e_bound)))
        tl, vl = [fl[k] for k in train], [fl[k] for k in val]
        losses[name] = {"training": float(np.mean(tl)), "held_back": float(np.mean(vl)) if vl else None,
                        "held_back_frames": vl, "coefficients": coeffs[name], "median_e": float(np.median(r_.youngs))}

    def rejudge(names):
        """The models compared, at one substep: the one for the stiffest of them."""
        e_top = max(float(np.max(models[n].youngs)) for n in names)
        for n in names:
            judge(n, e_top)
        model["judged_at_e"] = e_top

    judge("uniform")
    tests = {}
    base = "uniform"
    if with_parts and not ru.interrupted:
        got = {}

        def parts_go(cb):
            got["r"], got["rec"] = parts_stage(prob, view, s, uni, ru, n_parts, progress=progress, log=log,
                                               on_iteration=cb, attach_grasped=attach_grasped,
                                               section_cut=section_cut, exposure_floor=exposure_floor)
            return got["r"] if got["r"] is not None else types.SimpleNamespace(loss_history=[])

        run(parts_go)
        rp, prec = got["r"], got["rec"]
        if rp is not None:
            models["parts"] = rp
            coeffs["parts"] = len(rp.model["part_fit"])
            prec["e"] = [p["e"] for p in rp.model["part_fit"]]
            rejudge(["uniform", "parts"])
            if not rp.interrupted:
                tests["parts"] = select_rule(losses["uniform"]["held_back_frames"], losses["parts"]["held_back_frames"],
                                             coeffs["parts"] - 1, s)
                ratio = max(prec["e"]) / max(min(prec["e"]), 1e-30)
                if tests["parts"]["keep_field"] and ratio < PARTS_MIN_RATIO:
                    # parts of one material (a finer search than the uniform model's can still pay the price)
                    tests["parts"]["keep_field"] = False
                    tests["parts"]["why"] += (f"; but the parts' E agree within {ratio:.2f}x (< {PARTS_MIN_RATIO}x): "
                                              "one material")
                if tests["parts"]["keep_field"]:
                    base = "parts"
                say(f"parts ({prec['kind']}, E " + ", ".join(f"{e:.4g}" for e in prec["e"]) + " Pa): "
                    + ("kept" if base == "parts" else "refused") + f" ({tests['parts']['why']})")
        model["parts"] = prec
    nested = bool(s.select_field_nested)

    def field_start(r_):        # nested: on the kept model's own per-particle E, the offsets from zero
        return {**start_of(r_), "base_youngs": models[base].youngs} if nested else start_of(r_)

    if not models[base].interrupted and k_field > 1:
        sf = dataclasses.replace(s, levels=(k_field,), level_share=(1.0,), iterations=n_field, confidence_probes=0,
                                 search_effects=())
        models["field"] = run(lambda cb: fit_bumps(view, sf, progress=progress, log=log, on_iteration=cb,
                                                   start=field_start(models[base])))
        # nested: all k_field offsets are added to the kept model's coefficients
        coeffs["field"] = coeffs[base] + k_field if nested else k_field
        judge("field")
        model["field_from"] = base
        model["field_nested"] = nested
    # 4b. where parts were kept, the field from the uniform model too: the parts may be the wrong
    # partition, and a field nested on them keeps their boundaries (docs/benchmarks/fit.md, session 8)
    if (base == "parts" and bool(s.select_field_from_uniform) and k_field > 1
            and not any(m.interrupted for m in models.values())):
        n_fu = n_field if field_uniform_iterations is None else max(int(field_uniform_iterations), 1)
        sf = dataclasses.replace(s, levels=(k_field,), level_share=(1.0,), iterations=n_fu, confidence_probes=0,
                                 search_effects=())
        models["field_uniform"] = run(lambda cb: fit_bumps(view, sf, progress=progress, log=log, on_iteration=cb,
                                                           start=start_of(models["uniform"])))
        coeffs["field_uniform"] = k_field
        judge("field_uniform")
    # 5. the held-back tests: each step kept only if it pays for its added coefficients, every
    # model simulated at one substep
    if not any(m.interrupted for m in models.values()):
        rejudge(list(models))
    chosen = base
    if "field" in models and not models["field"].interrupted:
        test = select_rule(losses[base]["held_back_frames"], losses["field"]["held_back_frames"],
                           max(coeffs["field"] - coeffs[base], 1), s)
        tests["field"] = test
        chosen = "field" if test["keep_field"] else base
        say(f"model: {chosen} ({test['why']})")
    if "field_uniform" in models and not models["field_uniform"].interrupted:
        # against the model chosen so far (not nested in it): it must pay for the coefficients it has
        # beyond that model's, on the same held-back frames, and beat its held-back loss
        test = select_rule(losses[chosen]["held_back_frames"], losses["field_uniform"]["held_back_frames"],
                           max(coeffs["field_uniform"] - coeffs[chosen], 1), s)
        tests["field_uniform"] = test
        if test["keep_field"]:
            chosen = "field_uniform"
        say(f"the field from uniform: {'kept' if test['keep_field'] else 'refused'} ({test['why']})")
    if tests:
        model["tests"] = tests
        model["test"] = tests.get("field", tests.get("parts"))
    model["models"] = losses
    model["chosen"] = chosen
    if candidates is not None:
        candidates.update(models)
    r = models[chosen]
    # 6. the chosen model on all frames, with its confidence
    interrupted = any(m.interrupted for m in models.values())
    if not interrupted:
        if chosen == "parts":
            labels = np.asarray(r.regions, np.int64)
            log_e = np.log([p["e"] for p in r.model["part_fit"]])
            r = run(lambda cb: fit_parts(prob, s, labels, log_e, start_of(models["parts"]), n_final, progress=progress,
                                         log=log, on_iteration=cb, confidence_probes=s.confidence_probes))
            model["parts"]["final"] = r.model["part_fit"]
        else:
            levels = (1,) if chosen == "uniform" else (k_field,)
            sc = dataclasses.replace(s, levels=levels, level_share=(1.0,), iterations=n_final, search_effects=(),
                                     trajectory_levels=1,
                                     fit_poisson_levels=1 if chosen == "uniform" else s.fit_poisson_levels)
            r0 = r
            r = run(lambda cb: fit_bumps(prob, sc, progress=progress, log=log, on_iteration=cb,
                                         start=field_start(r0) if chosen == "field" else start_of(r0)))
    r.loss_history = stages.history
    r.uniform_start = uni["e"]
    r.interrupted = r.interrupted or interrupted
    r.settings = {**r.settings,
                  **{k: v for k, v in dataclasses.asdict(s).items() if k not in ("levels", "level_share")},
                  "levels": list(s.levels), "level_share": list(s.level_share), "iterations": int(s.iterations)}
    r.model = {**model, **{k: v for k, v in (r.model or {}).items() if k != "schedule"}}
    return r
