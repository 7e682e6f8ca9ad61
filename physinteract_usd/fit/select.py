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
3. The "field" model: the bumps field (the finest level of `levels`) warm-started from the uniform
   model, training frames only.
4. Selection on the held-back frames (every `select_holdout_every`-th frame from frame 2, but never
   the first frame after a release, which carries most of the free motion's evidence: neither
   model ever fits them; interleaved rather than a time split, so both halves see the grasp, the
   lift and the release alike, and the trajectory at a held-back frame is still pinned by the
   frames after it). The field is kept only if, over the held-back frames, its loss falls by more
   than its added freedom predicts: the mean per-frame drop d must exceed `select_penalty` x
   (added coefficients) x the uniform model's held-back loss (a BIC-like price per parameter), and
   the field must be better on most held-back frames (a sign test: one frame that the uniform model
   misses badly, the one after the release, does not carry the choice alone; a paired t-test was
   tried first and refused a two-part bar's field whose held-back loss fell 2.5x, because that frame
   dominated the variance). A tie keeps the simpler model.
5. The chosen model polished on all frames (`select_final_share` of the iterations) with its
   confidence (`optimize.confidence`).

The result's `model` says which model was chosen and why: the uniform stage's curve, minima and
intervals, both models' training and held-back losses and the test. No USD here."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ..errors import SimulationError
from .effect_params import effect_parameters, effect_values
from .optimize import FitResult, FitSettings, fit_bumps
from .problem import FitProblem
from .search import UniformProbe, golden_section, no_finite_uniform_probe


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
        raise no_finite_uniform_probe()
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


def frame_losses(prob: FitProblem, r: FitResult, s: FitSettings, frames) -> list[float]:
    """The reconstruction loss of each of `frames` for a fit result (one forward pass)."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=prob.tdtype, device=prob.tdev)  # noqa: E731
    names = prob.sim.slot_names()
    trajs = [t(r.trajectories[n]) for n in names] if names else None
    eff = None
    if r.effect_parameters:
        eff = effect_values(effect_parameters(prob, s.fit_effects, r.effect_parameters), prob.traj_scale)
    with torch.no_grad():
        try:
            x, F = prob.simulate(t(r.youngs), t(r.poisson), trajs, eff)
        except SimulationError:
            return [float("inf")] * len(frames)
        return [float(prob.frame_loss(k, prob.render_frame(k, x[k], F[k]))["total"]) for k in frames]


def select_rule(uniform_val: list[float], field_val: list[float], added: int, s: FitSettings) -> dict:
    """The held-back test (module doc, 4.): {"keep_field", "mean_drop", "penalty", "better_frames",
    "why"}."""
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
    return {"keep_field": keep, "mean_drop": mean, "penalty": penalty, "better_frames": better, "why": why}


def sweep_interval(sweep: dict, rise: float) -> list[float] | None:
    """The hull of the uniform E values whose loss is within `rise` (a share) of the best one seen
    (the sweep's points and the refinements'): [E_lo, E_hi] Pa. Unlike the interval from the
    curvature at a minimum, it holds a flat or bumpy curve's every near-best stretch, so a video
    that does not determine E gets a wide interval. None without a finite value."""
    pts = [(float(e), float(v)) for e, v in sweep.items() if v is not None and math.isfinite(float(v))]
    if not pts:
        return None
    best = min(v for _, v in pts)
    near = [e for e, v in pts if v <= best * (1.0 + rise)]
    return [min(near), max(near)]


# how wide (hi / lo) the uniform interval may be for E to count as determined within the MA
# tolerance (+-20%: 1.2 / 0.8 = 1.5), roughly (within 2x either way: 4)
DETERMINED_RATIO, ROUGH_RATIO = 1.5, 4.0


def identifiability(model_sum: dict, confidence_mean: float | None, e_median: float,
                    rise: float = 0.01) -> dict:
    """What the video says about E, plainly: {"interval": [lo, hi] | None, "ratio", "level":
    "determined" | "rough" | "undetermined" | "unknown", "sentence"}. The interval is the
    uniform sweep's near-best hull (`sweep_interval`, schedule select); without a sweep, the bumps
    start search's probes (`uniform_probe_interval`, a lower bound of the width: wider than 4x is
    "undetermined" for sure), else the fit's mean confidence (the share of the object whose E is
    likely within 20%)."""
    iv = model_sum.get("uniform_sweep_interval")
    pv = model_sum.get("uniform_probe_interval")
    out = {"interval": iv, "ratio": None, "level": "unknown", "sentence": ""}
    if not iv and pv and pv[1] / pv[0] > ROUGH_RATIO:
        # the bumps start search's few probes: their near-best hull is a lower bound of the width
        out.update(interval=pv, ratio=pv[1] / pv[0], level="undetermined",
                   sentence=f"this video does not determine E: uniform E from {pv[0]:.3g} to {pv[1]:.3g} Pa (at "
                            f"least) fit within {rise:.0%} of the best the start search found; the median "
                            f"{e_median:.3g} Pa is one choice among many (`fit --schedule select` sweeps the "
                            "whole range)")
        return out
    if iv:
        ratio = iv[1] / iv[0]
        out["ratio"] = ratio
        level = "determined" if ratio <= DETERMINED_RATIO else "rough" if ratio <= ROUGH_RATIO else "undetermined"
        out["level"] = level
        span = (f"a uniform E anywhere in {iv[0]:.3g} .. {iv[1]:.3g} Pa fits within {rise:.0%} of the best"
                if ratio > 1.001 else
                f"no other uniform E of the sweep comes within {rise:.0%} of the best, {iv[0]:.3g} Pa")
        if level == "determined":
            out["sentence"] = f"E is determined by this video: {span}"
        elif level == "rough":
            out["sentence"] = (f"E is determined only roughly ({ratio:.1f}x wide): {span}; take the interval, not "
                               "the number")
        else:
            out["sentence"] = (f"this video does not determine E: {span} ({ratio:.0f}x wide); the median "
                               f"{e_median:.3g} Pa is one choice among many. A release with free swinging, a sag "
                               "under gravity or a larger deformation would pin it down")
    elif confidence_mean is not None:
        out["level"] = "determined" if confidence_mean >= 0.8 else "rough" if confidence_mean >= 0.4 else "undetermined"
        if out["level"] != "determined":
            out["sentence"] = (f"E may not be determined by this video: mean confidence {confidence_mean:.2f} (the "
                               "share of the object whose E is likely within 20%); `fit --schedule select` sweeps "
                               "a uniform E and gives the interval")
    return out


def model_summary(model: dict | None) -> dict:
    """The material model a fit chose, in short (`fit --json`, the report): the schedule, the model
    chosen, the uniform stage's E, curve shape and minima, each model's training and held-back
    losses and the test's verdict."""
    m = model or {}
    out = {"schedule": m.get("schedule", "bumps")}
    if "chosen" in m:
        out["chosen"] = m["chosen"]
    uni = m.get("uniform_stage")
    if uni:
        out["uniform_e"] = uni["e"]
        out["uniform_curve"] = uni["shape"]
        out["uniform_minima"] = [{"e": x["e"], "loss": x["loss"], "interval": x["interval"]} for x in uni["minima"]]
        if uni.get("sweep"):
            out["uniform_sweep_interval"] = sweep_interval(uni["sweep"], uni.get("rise", 0.01))
    if m.get("uniform_probes") and not uni:
        out["uniform_probe_interval"] = sweep_interval(m["uniform_probes"], 0.01)
    if "models" in m:
        out["losses"] = {k: {"training": v["training"], "held_back": v["held_back"], "median_e": v.get("median_e")}
                         for k, v in m["models"].items()}
    if "test" in m:
        out["test"] = m["test"].get("why", "")
    if "regions" in m:          # the ladder's
        out["regions"] = m["regions"]
    return out


def fit_select(prob: FitProblem, s: FitSettings, *, progress: bool = True, log=None, start: dict | None = None,
               on_iteration=None, uniform_e: float | None = None) -> FitResult:
    """The "select" schedule (module doc). A resumed fit (`start`) goes on with the bumps field."""
    if start is not None:
        return fit_bumps(prob, s, progress=progress, log=log, start=start, on_iteration=on_iteration)
    say = log or (lambda *a: None)
    st = prob.scene.settings
    nu0 = min(st.poisson_default, 0.98 * st.poisson_max)
    after_release = [c.release_frame + 1 for c in prob.contacts if getattr(c, "release_frame", None) is not None]
    train, val = holdout_frames(prob.T, int(s.select_holdout_every), keep=after_release)
    view = FrameView(prob, train)
    N = max(int(s.iterations), 0)
    n_final = int(round(s.select_final_share * N)) if N else 0
    n_uni = max(int(round(s.select_uniform_share * N)), 1) if N else 0
    n_field = max(N - n_uni - n_final, 1 if N else 0)
    used = [0]
    histories = []

    def stage_cb(it, loss, mat, trajs):
        if on_iteration is not None:
            on_iteration(used[0] + it, loss, mat, trajs)

    def run(p, settings, **kw):
        r = fit_bumps(p, settings, progress=progress, log=log, on_iteration=stage_cb, **kw)
        used[0] += len(r.loss_history)
        histories.extend(r.loss_history)
        return r

    def start_of(r: FitResult) -> dict:
        return {"youngs": r.youngs, "poisson": r.poisson, "trajectories": r.trajectories,
                "effects": r.effect_parameters}

    # 1. the uniform stage
    if uniform_e is not None:   # a search already found it (app: the support sizing)
        uni = {"e": float(uniform_e), "loss": None, "shape": "given", "minima": [], "sweep": {}, "skipped": []}
    else:
        uni = uniform_stage(prob, train, s, nu0, log=log, progress=progress)
    say(f"uniform E: {uni['e']:.4g} Pa (loss curve {uni['shape']}; minima "
        + ", ".join(f"{m['e']:.4g} Pa [{m['interval'][0]:.3g}, {m['interval'][1]:.3g}]" for m in uni["minima"]) + ")")
    model = {"schedule": "select", "held_back_frames": val, "training_frames": train, "uniform_stage": uni}
    # 2. the uniform model; 3. the field from it
    k_field = int(s.levels[-1])
    su = dataclasses.replace(s, levels=(1,), level_share=(1.0,), iterations=n_uni, confidence_probes=0,
                             trajectory_levels=1, fit_poisson_levels=1)
    ru = run(view, su, uniform_e=uni["e"])
    models = {"uniform": ru}
    if not ru.interrupted and k_field > 1:
        sf = dataclasses.replace(s, levels=(k_field,), level_share=(1.0,), iterations=n_field, confidence_probes=0,
                                 search_effects=())
        models["field"] = run(view, sf, start=start_of(ru))
    # 4. the held-back test
    losses = {}
    for name, r in models.items():
        tl = frame_losses(prob, r, s, train)
        vl = frame_losses(prob, r, s, val)
        losses[name] = {"training": float(np.mean(tl)), "held_back": float(np.mean(vl)) if vl else None,
                        "held_back_frames": vl, "coefficients": 1 if name == "uniform" else k_field,
                        "median_e": float(np.median(r.youngs))}
    chosen = "uniform"
    if "field" in models and not models["field"].interrupted:
        test = select_rule(losses["uniform"]["held_back_frames"], losses["field"]["held_back_frames"], k_field - 1, s)
        model["test"] = test
        chosen = "field" if test["keep_field"] else "uniform"
        say(f"model: {chosen} ({test['why']})")
    model["models"] = losses
    model["chosen"] = chosen
    r = models[chosen]
    # 5. the chosen model on all frames, with its confidence
    interrupted = any(m.interrupted for m in models.values())
    if not interrupted:
        levels = (1,) if chosen == "uniform" else (k_field,)
        sc = dataclasses.replace(s, levels=levels, level_share=(1.0,), iterations=n_final, search_effects=(),
                                 trajectory_levels=1,
                                 fit_poisson_levels=1 if chosen == "uniform" else s.fit_poisson_levels)
        r = run(prob, sc, start=start_of(r))
    r.loss_history = histories
    r.uniform_start = uni["e"]
    r.interrupted = r.interrupted or interrupted
    r.settings = {**r.settings,
                  **{k: v for k, v in dataclasses.asdict(s).items() if k not in ("levels", "level_share")},
                  "levels": list(s.levels), "level_share": list(s.level_share), "iterations": int(s.iterations)}
    r.model = {**model, **{k: v for k, v in (r.model or {}).items() if k != "schedule"}}
    return r
