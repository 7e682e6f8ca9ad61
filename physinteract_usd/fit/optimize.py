"""Joint fit of the material field and the interaction trajectory.

Schedule (each part measured on the synthetic suite, see docs/fit.md):
1. a uniform E from a golden-section search on log E over the allowed range (forward passes only;
   never looks at ground truth);
2. coarse-to-fine: AdamW on the basis coefficients of log E (and nu at the coarsest levels) and,
   jointly, on the trajectory (unless `joint=False`, the paper's "w/o JO"), with cosine-annealed
   learning rates inside each level; the best iterate (lowest total loss) is kept;
3. per-particle confidence from the Gauss-Newton diagonal (Hutchinson probes of J^T J), on the
   finest basis of the schedule whichever level the kept iterate came from;
4. per-frame metrics of the kept iterate; the final loss is its entry in the loss history.
Ctrl-C stops the loop and keeps the best iterate so far (its confidence is still estimated). A
resumed fit (`start`) spends all its iterations on the finest basis, from the field it was given.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from .. import metrics as M
from .. import stopping
from ..devices import device_name
from ..errors import SimulationError
from .adamw import AdamW
from .converge import improved, level_patience, lr_scale, plateaued
from .gauss_newton import forwards_to_iterations, gauss_newton_step
from .effect_params import effect_parameters, effect_values, fitted_values, search_effects
from .material import MaterialField, appearance_transfer_weights, neighbour_pairs, pair_weights
from .phases import Phases
from .problem import FitProblem
from .exposure import EXPOSURE_FLOOR, exposure_of_rollout, unconstrained_particles
from .search import GOLDEN, UniformProbe, golden_section, has_ground, no_finite_uniform_probe


@dataclass
class FitSettings:
    iterations: int = 60
    levels: tuple = (1, 8)              # basis sizes, coarse to fine (foam_bar: (1, 8) MA 0.45 vs
    level_share: tuple = (0.25, 0.75)   # (1, 8, 32) 0.33 and (1, 4, 8) 0.26: finer bases fit discretisation error)
    lr_material: float = 0.1            # on the basis coefficients (logit space)
    lr_poisson: float = 0.03
    lr_trajectory: float = 3e-4         # metres per step (Adam)
    basis_width: float = 0.6            # bump sigma / centre spacing (smaller: sharper material edges)
    appearance: float = 1.0             # appearance prior: a full colour change counts as this many object
                                        # extents in the basis and smoothness (0: position only)
    trajectory_levels: int = 1          # the trajectory is fitted in the last this-many levels only
    weight_decay: float = 0.0
    joint: bool = True
    search_evals: int = 7               # golden-section steps for the uniform E
    confidence_probes: int = 4
    confidence_covariance: str = "sandwich"  # the confidence's interval (optimize.confidence): "sandwich" (the larger
                                        # of the Laplace covariance and the frame-clustered sandwich: the frames' own
                                        # disagreement; 6 CPU suite scenes at grid 16: confident and wrong 0.61 -> 0.20,
                                        # the demo 0.07 -> 0.04), "full" (the Laplace covariance), "diag" (the diagonal's
                                        # bound). #24
    seed: int = 0
    fit_poisson_levels: int = 2         # nu is fitted while the basis has at most this many levels
    schedule: str = "bumps"             # "ladder": model selection, uniform E -> regions split by score
                                        # (fit/ladder.py); "bumps": the coarse-to-fine RBF field below;
                                        # "select": uniform vs field by held-back frames (fit/select.py)
    select_holdout_every: int = 3       # select: every this-many-th frame from frame 2 is held back
    select_sweep_points: int = 15       # ... log-spaced uniform E probes (forward only) over the range
    select_sweep_batch: str = "cuda"    # ... as tiled copies in few rollouts: "cuda" (on a GPU), "always", "never"
    select_minima: int = 3              # ... local minima of the sweep refined (golden, search_evals each)
    select_minima_tolerance: float = 0.5  # ... those within this (relative) of the best one
    select_flat: float = 0.01           # ... the curve is "flat" when it spans less than this (relative)
    select_interval_rise: float = 0.01  # ... a minimum's interval: where the loss rises by this share
    select_penalty: float = 0.002       # ... the field is kept when its held-back drop exceeds this x added
                                        # coefficients x the uniform's held-back loss, on most held-back frames
    select_uniform_share: float = 0.3   # ... iteration budget: the uniform model, the final polish on all
    select_final_share: float = 0.15    # frames (the field gets the rest)
    select_parts: bool = True           # ... the "parts" step between uniform and field (per-part E; fit/select.py)
    select_parts_share: float = 0.2     # ... its gradient polish's share of the iterations
    select_part_points: int = 7         # ... per part, log-spaced E probes over the range (forward only)
    select_part_starts: int = 2         # ... sweeps start from this many distinct uniform minima
    select_part_rounds: int = 2         # ... coordinate rounds over the parts (later rounds: golden, local)
    select_part_refine: int = 12        # ... then a simplex over all parts' log E together, this many probes per part
    select_max_parts: int = 4           # ... at most this many parts in a candidate
    select_field_nested: bool = True    # ... the field is the kept model's E (fixed) plus a bumps offset from
                                        # zero (MaterialField.set_base); False: the kept model projected onto bumps
    select_field_from_uniform: bool = True  # ... where parts were kept, also the field from the uniform model (what
                                        # bumps fits), kept over the parts' model only if it pays on held-back frames
    holdout_every: int = 4              # ladder: every this-many-th frame is held back to judge a split
    sweep_points: int = 7               # ladder: log-spaced uniform E probes before the golden refinement
    flat_tolerance: float = 0.02        # ... minima within this (relative) of the best are refined too
    max_regions: int = 5
    region_min_share: float = 0.03      # a candidate part holds at least this share of the particles
    split_candidates: int = 3           # candidates whose curvature is measured per round (2 forwards each)
    split_min_drop: float = 0.01        # a split is tried when its predicted drop exceeds this share of the loss
    split_margin: float = 0.005         # ... and kept when the held-back frames' loss falls by more than this
    uniform_share: float = 0.2          # ladder budget: one E, each split, the final joint polish
    split_share: float = 0.15
    final_share: float = 0.2
    fit_effects: tuple = ()             # the effects whose parameters are fitted, by either schedule (the
                                        # stage's effect APIs with fit = true; fit/effect_params.py)
    lr_effects: float = 0.05            # ... on their log values (the ground's height as is)
    search_effects: tuple = ()          # effects just switched on: their start found first by a 1-D search
    effect_search_points: int = 6       # ... of this many log-spaced probes (+ 4 golden-section steps)
    plateau_patience: int = 3           # convergence stop (fit/converge.py): a level ends when its last this-many
    plateau_tol: float = 0.005          # losses brought no new best this much (relative) below the best before,
    plateau_tail: int = 4               # ... after this many iterations from the best iterate at a falling LR (0: the
                                        # level ends at its best iterate). Session 9 tried patience 2 / tail 0 and the
                                        # uniform level skipped (patience 1): on the demo 9 iterations fewer at the same
                                        # MA, but on hemp_rope (H200, grid auto) level 2 stopped at loss 0.00616 instead
                                        # of 0.00464 and MA fell 0.801 -> 0.397: reverted (docs/benchmarks/fit.md)
    plateau_patience_searched: int = 3  # ... the patience of a uniform level that starts at the start search's minimum
    skip_searched_uniform: bool | None = None  # ... that level skipped where the next one fits nu too (no effects
                                        # fitted). None (the default): where the starts run (fit.fit's before-finest
                                        # hook: CUDA's default), else not. The starts judge every candidate against the
                                        # uniform E again, and on the paper row (H200, 2026-11-29) the level's 4
                                        # iterations (8.3 s) never beat the start search's E: skipped, the fit clock
                                        # 56.0-57.2 -> 51.0 s, the same final loss and MA 1.000. #26
    select_supports: bool = True        # the first fit of a guessed support sizes it by the loss
    support_layers: int = 3             # ... at most this many layers more or less than found
    support_margin: float = 0.01        # ... a layer is taken when it lowers the loss by more than this
    track_weight: float = 0.0           # the video's point tracks against the projected Gaussians as a loss term
                                        # (fit/tracks_loss.py; 1: a 1-px error on every track ~ a 1-px outline shift)
    unconstrained_floor: float = 0.0    # after the fit, particles whose strain exposure over the clip is below this
                                        # share of the median (select.EXPOSURE_FLOOR = 0.1) and the held ones are
                                        # "unconstrained": confidence 0, E filled from the constrained material they
                                        # are attached to (select.fill_unconstrained; 0: off). #24
    gn_steps: int = 0                   # schedule bumps: Gauss-Newton steps on the finest level's bump amplitudes
                                        # before its Adam iterations, each charged to its budget at the forwards
                                        # it costs (fit/gauss_newton.py; 0: off). #24, foam_bar: Adam's step cap
    parts_start: int | None = None      # schedule bumps (through fit.fit): the finest level starts from the appearance parts' E, found by
                                        # a simplex of at most this many forward probes from the uniform E (and at most
                                        # 3 (parts + 1) + parts on the CPU: parts_start.probe_budget, stopped when it
                                        # stalls; on CUDA all of them, uncut: parts_start.refine_kwargs; charged
                                        # to the level's budget when taken; fit/parts_start.py; 0: off). #24, foam_bar.
                                        # None (the default): parts_start.PARTS_START_CUDA (20) where the problem's
                                        # tensors are on CUDA (the 12 suite scenes gained, none lost: mean MA 0.399 ->
                                        # 0.513), 0 on the CPU (the demo's +16-20 CPU s for no MA; docs/benchmarks/fit.md)
    parts_nest: bool = False            # the parts start as the trend start is judged and held: its simplex on the training
                                        # frames, kept only if its field beats the uniform E on the held-back ones (one
                                        # coefficient per part more, and a sign test), then the fixed base of a nested
                                        # field (exact: no projection onto the bumps, which leaks a part near the range's
                                        # top into its neighbours). Opt-in for starts_order "parts_first"; always so in "screened" (the default)
    trend_start: int | None = None      # schedule bumps (through fit.fit): (ordered with the parts start by starts_order) the finest level
                                        # starts from a log-linear trend of E along one of the object's axes (gravity's,
                                        # principal ones) when it beats the uniform E on held-back frames, its two ends
                                        # found by at most this many probes after a 4-6-probe screen per axis
                                        # (fit/trend_start.py; 0: off). None (the default): trend_start.TREND_START_CUDA
                                        # (20) where the problem's tensors are on CUDA (the 12 suite scenes on the H200:
                                        # mean MA 0.580 -> 0.626, >= 0.9 on 4 not 2; the paper row 0.821 -> 1.000), 0 on
                                        # the CPU (as the parts start: its probes cost the demo time). #24, balloon
    trend_extend: bool = True           # the trend start's simplex goes on past its cap while still descending, as the
                                        # parts start's uncut one does (parts_start.EXTEND_CAP, `extend_window`); False:
                                        # it stops at the cap (before the 35th session). #24
    parts_by_shape: bool = True         # the parts start (fit/parts_start.py): where the colours make no regions (one colour,
                                        # or a pattern's interleaved classes), the parts by thickness (thin against thick:
                                        # regions.thickness_clusters) where the shape has them; False: colour parts only. #24
    starts_order: str = "screened"      # where both starts run (fit/trend_start.starts_hook): "screened", both screened on the
                                        # training frames, the parts start nested, the lower screen's simplex first, the
                                        # other's only where it is not taken; "parts_first", the projected parts start then
                                        # the trend start (the 29th session's). #24 / #26
    gn_max_basis: int = 32              # ... only while the basis has at most this many functions (K forwards a step)
    uniform_guard: bool = False         # schedule bumps: the field is returned only if its held-back loss is clearly
                                        # below the best uniform E's, else the uniform model (select.fit_guarded). #24
    nuisance_damping: bool = False      # fit a global `damping` c jointly with E though the stage has no damping effect
                                        # (app.fit.prepare_fit switches it on, its start searched): the numerical
                                        # dissipation the truth or the video has and the fit lacks goes into c instead
                                        # of E (#24; docs/benchmarks/fit.md "A fitted damping as a nuisance"). Opt-in


@dataclass
class FitResult:
    youngs: np.ndarray                  # (P,)
    poisson: np.ndarray                 # (P,)
    confidence: np.ndarray              # (P,)
    trajectories: dict                  # contact name -> (T, 3)
    positions: np.ndarray               # (T, P, 3)
    deformation: np.ndarray             # (T, P, 3, 3)
    gaussian_means: np.ndarray          # (T, N, 3)
    gaussian_covs: np.ndarray           # (T, N, 3, 3)
    youngs_gaussian: np.ndarray         # (N,)
    poisson_gaussian: np.ndarray
    confidence_gaussian: np.ndarray
    frame_metrics: list                 # per frame dicts
    loss_history: list
    final_loss: float
    runtime_s: float
    device: str
    settings: dict
    effects: dict = field(default_factory=dict)
    interrupted: bool = False
    uniform_start: float = 0.0
    regions: np.ndarray | None = None   # (P,) the material region of each particle (schedule "ladder")
    model: dict = field(default_factory=dict)  # the material model chosen and why (regions, their E and
                                        # intervals, the splits tried with predicted / realised drops)
    effect_parameters: dict = field(default_factory=dict)  # {effect: {parameter: value}} fitted ones


def _gn_step(prob, mat, trajs, eff, pairs, pair_w, lam_smooth, log=None) -> dict:
    """One Gauss-Newton step on the field's coefficients (fit/gauss_newton.py), the path, nu and
    the effects where they are; the smoothness term as the bumps loop counts it."""
    n_pairs = max(len(pairs), 1)

    def reg_fn(residuals: bool = False):
        if not (len(pairs) and mat.K > 1):
            z = torch.zeros((0,) if residuals else (), dtype=prob.tdtype, device=prob.tdev)
            return z
        if not residuals:
            return lam_smooth * mat.smoothness(pairs, pair_w)
        le = mat.log_e()
        if mat.base is not None:
            le = le - (mat.lo + (mat.hi - mat.lo) * torch.sigmoid(mat.base))
        return torch.sqrt(lam_smooth * pair_w / n_pairs) * (le[pairs[:, 0]] - le[pairs[:, 1]])

    tr = [t.detach() for t in trajs] if trajs else None
    reg_traj = 0.0
    if tr is not None and prob.weights.trajectory > 0:
        with torch.no_grad():
            reg_traj = float(prob.trajectory_prior(tr))
    nu = mat.poisson().detach()
    return gauss_newton_step(prob, mat, nu, tr, eff, reg_fn, reg_traj, log)


def _seed(s):
    torch.manual_seed(s)
    np.random.seed(s)


def golden_uniform_search(prob: FitProblem, mat: MaterialField, evals: int, log=None, with_loss: bool = False,
                          skipped: list | None = None, seen: dict | None = None):
    """Golden-section search of the reconstruction loss over a uniform log E (no gradients): the
    best E (and, `with_loss`, its loss). A probe whose simulation goes unstable or leaves the grid
    (or whose loss is not finite) is reported (`log`; its E appended to `skipped`) and skipped: the
    search moves away from it and it is never the answer. Where the search meets nothing finite, a
    sweep over the range looks for a finite probe before giving up with a SimulationError."""
    lo, hi = mat.lo, mat.hi
    nu = mat.poisson().detach()
    f = UniformProbe(lambda E: prob.loss(E, nu)["rec"], len(mat.points), mat.dtype, mat.device, log, skipped,
                     many=_probes_beside(prob, nu))
    cache = f.cache

    a, b = lo + 0.02 * (hi - lo), hi - 0.02 * (hi - lo)
    f.prefetch([b - GOLDEN * (b - a), a + GOLDEN * (b - a)])     # the first two probes at once (two threads)
    if not (math.isfinite(f(b - GOLDEN * (b - a))) or math.isfinite(f(a + GOLDEN * (b - a)))):
        # both first probes failed: a coarse sweep finds where the simulation holds, the search
        # continues around the best finite probe
        for le in np.linspace(a, b, 5):
            f(float(le))
        fin = [k for k in cache if math.isfinite(cache[k])]
        if fin:
            k = min(fin, key=cache.get)
            step = (b - a) / 4
            a, b = max(a, k - step), min(b, k + step)
    golden_section(f, a, b, evals)
    if f.many is not None:
        prob.sim.drop_probe_twins()
        if log:
            log(f"start search on two threads: {f.ahead_used} of {len(cache)} probes from the pairs, "
                f"{f.ahead_wasted} guessed ahead in vain")
    if seen is not None:      # every probe, E -> loss (None: unstable), for what the video says about E
        seen.update({f"{math.exp(k):.5g}": (round(v, 7) if math.isfinite(v) else None) for k, v in sorted(cache.items())})
    fin = [k for k in cache if math.isfinite(cache[k])]
    if not fin:
        raise no_finite_uniform_probe(f.errors, has_ground(prob))
    best = min(fin, key=cache.get)
    return (math.exp(best), cache[best]) if with_loss else math.exp(best)


def _probes_beside(prob: FitProblem, nu):
    """`UniformProbe`'s `many` for a search's uniform-E probes on two threads (`simulation.sim_threads`, the
    CPU only; None otherwise): `many([E1, E2])` simulates E1 in the calling thread and E2 in a worker,
    each on an eager twin at the rung the one-at-a-time search would take it at (E2's after E1's:
    `Simulation.rung_wanted`), and renders E1's loss while E2 simulates. Its callables, called in the
    search's order, move the simulation's rung as `prob.loss` would have and give `prob.loss`'s value
    (E2's rendered from its simulated states; recomputed by `prob.loss` if the rung is not the one
    assumed): the one-thread search's probes, values and decisions (tests/test_fit_probes_threads.py)."""
    import threading

    from .. import simulation as simulation_mod

    sim = getattr(prob, "sim", None)
    if (not isinstance(prob, FitProblem) or not isinstance(sim, simulation_mod.Simulation)
            or not str(sim.device).startswith("cpu")
            or "simulate" in vars(prob) or type(prob).simulate is not FitProblem.simulate
            or simulation_mod.sim_threads(sim.device) < 2):
        return None

    def many(Es):
        E1, E2 = Es[0], Es[1]
        r1 = sim.rung_wanted(float(E1.max()))
        r2 = sim.rung_wanted(float(E2.max()), current=r1)
        sim.twin_at(r1, 0)
        sim.twin_at(r2, 1)           # both built here, before the worker starts (one per thread)
        box: dict = {}

        def work():
            try:
                box["x"] = sim.forward_at(r2, E2, nu, slot=1)
            except SimulationError as e:
                box["error"] = e
            except BaseException as e:  # noqa: BLE001  (re-raised in the calling thread)
                box["failed"] = e

        t = threading.Thread(target=work, name="physinteract-probe", daemon=True)
        t.start()
        try:
            with torch.no_grad():
                sim.ensure_stable(float(E1.max()))          # the rung E1's probe moves to (nothing simulated)
                try:
                    first = float(prob.loss(E1, nu, simulated=sim.forward_at(r1, E1, nu, slot=0))["rec"])
                except SimulationError as e:
                    first = e
        finally:
            t.join()
        if "failed" in box:
            raise box["failed"]

        def one():
            if isinstance(first, SimulationError):
                raise first
            return first

        def two():
            e_max = float(E2.max())
            if sim.rung_wanted(e_max) != r2:                # not asked right after E1: simulate it here
                return float(prob.loss(E2, nu)["rec"])
            sim.ensure_stable(e_max)
            if "error" in box:
                raise box["error"]
            return float(prob.loss(E2, nu, simulated=box["x"])["rec"])

        return [one, two]

    return many


def uniform_loss(prob: FitProblem, evals: int, log=None, seen: dict | None = None) -> tuple[float, float]:
    """(best uniform E, its reconstruction loss) for a problem, from a fresh uniform field (`seen`: every probe,
    as `golden_uniform_search` gives it)."""
    st = prob.scene.settings
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype, device=prob.tdev)
    mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
    return golden_uniform_search(prob, mat, evals, log, with_loss=True, seen=seen)


def select_supports(make_problem, contacts: list, x0: np.ndarray, spacing: float, settings: FitSettings,
                    log=None) -> tuple[list, FitProblem, float, list]:
    """The size of guessed supports (extracted where no still region was in view: a ball pressed
    onto a stand the camera never sees), chosen by what they render. Starting from the guess, grow
    it one layer at a time (`problem.support_layer`) while the best uniform E's reconstruction loss
    falls by more than `settings.support_margin` (relative); if the first layer more does not,
    shrink it the same way. At most `settings.support_layers` layers either way; a tie keeps the
    guess. `make_problem(contacts)` builds a FitProblem. Returns (contacts, problem, uniform E,
    [(label, particles held, loss)]).

    Only guesses: at one uniform E, holding more of an object whose held end is stiffer than the
    rest renders better whether or not that material is held (on the synthetic suite the loss grew
    foam_bar's measured clip support 194 -> 322 particles and glove's 423 -> 718, and their fits'
    MA fell 0.95 -> 0.43 and 0.37 -> 0.00), so a support the video measured is kept as measured."""
    from .problem import support_layer

    def held(cs):
        return int(sum(len(c.indices) for c in cs if c.type == "fixed"))

    prob = make_problem(contacts)
    e, loss = uniform_loss(prob, settings.search_evals)
    tried = [("as found", held(contacts), loss)]
    best = (contacts, prob, e, loss)
    if log:
        log(f"supports as found ({held(contacts)} particles): loss {loss:.5f} at uniform E {e:.4g} Pa")
    for direction in ("more", "less"):
        cur = best
        for step in range(1, int(settings.support_layers) + 1):
            cs = support_layer(x0, spacing, cur[0], direction)
            if cs is None:
                break
            p = make_problem(cs)
            try:
                e, loss = uniform_loss(p, settings.search_evals)
            except SimulationError:  # unstable at every uniform E with these supports: not taken
                e, loss = float("nan"), float("inf")
            label = f"{step} layer{'s' if step > 1 else ''} {direction}"
            tried.append((label, held(cs), loss))
            if log:
                log(f"supports {label} ({held(cs)} particles): loss {loss:.5f} at uniform E {e:.4g} Pa")
            if not loss < cur[3] * (1.0 - settings.support_margin):
                break
            cur = (cs, p, e, loss)
        if cur is not best:
            best = cur
            break
    return best[0], best[1], best[2], tried


def fit_bumps(prob: FitProblem, settings: FitSettings | None = None, *, progress: bool = True, log=None,
              start: dict | None = None, on_iteration=None, uniform_e: float | None = None,
              before_finest=None) -> FitResult:
    """Run the fit. `before_finest(prob, mat, settings, trajs, effects, total_fn, log)`: a hook that may
    move the field before the finest level's optimiser starts (fit/parts_start.py: `fit` passes it
    when `settings.parts_start` > 0), returning {"forwards", "used", "loss0", "loss"}; its forward
    simulations are charged to that level's budget. `start` (resume): {"youngs", "poisson", "trajectories"} to start from; with
    "base_youngs" too, the field is nested on that per-particle E (`MaterialField.set_base`: the
    simpler model's E held fixed, the bumps fit an offset that starts at what "youngs" adds to it,
    zero when they are the same), as the select schedule's field step does.
    `uniform_e`: the uniform E to start from when a search already found it (`select_supports`)."""
    s = settings or FitSettings()
    _seed(s.seed)
    t0 = time.perf_counter()
    clock = Phases()           # where the time goes (model["phases_s"], #26)
    st = prob.scene.settings
    feats = prob.particle_appearance() if s.appearance > 0 else None
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                        device=prob.tdev, seed=s.seed, width=s.basis_width, features=feats,
                        appearance=s.appearance, centre_mask=~prob.held_particles())
    mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
    trajs = [t.clone().requires_grad_(s.joint) for t in prob.initial_trajectories()]
    levels, shares = tuple(int(k) for k in s.levels), tuple(s.level_share)
    start_skipped: list = []
    probes: dict = {}       # the start search's uniform E -> loss
    if start is not None:
        # resume where the last fit ended: on the finest basis (a coarse one would flatten the
        # field it left), all iterations there
        levels, shares = levels[-1:], (1.0,)
        mat.set_basis(levels[0])
        if start.get("base_youngs") is not None:    # nested on a simpler model's E
            mat.set_base(np.asarray(start["base_youngs"]))
        mat.set_values(np.asarray(start["youngs"]), np.asarray(start["poisson"]))
        for i, (slot, _) in enumerate(prob.traj_slots):
            name = prob.contacts[slot].name
            if name in start.get("trajectories", {}):
                # a copy: on the CPU torch.as_tensor would share the caller's numpy array, and the
                # optimiser would rewrite the result this fit starts from in place
                trajs[i] = torch.tensor(np.asarray(start["trajectories"][name]), dtype=prob.tdtype,
                                        device=prob.tdev).requires_grad_(s.joint)
        e_uniform = float(np.exp(np.mean(np.log(start["youngs"]))))
    else:
        skipped: list = []
        with clock("start_search"):
            e_uniform = uniform_e if uniform_e is not None else golden_uniform_search(prob, mat, s.search_evals, log,
                                                                                      skipped=skipped, seen=probes)
        if skipped:
            start_skipped = sorted(skipped)
        mat.set_uniform(e_uniform)
    # the effects the stage asks to fit (a warm start: from the previous version's values)
    eff_raw = effect_parameters(prob, s.fit_effects, (start or {}).get("effects"))

    def eff_now():
        return effect_values(eff_raw, prob.traj_scale) if eff_raw else None

    searched = {}
    if eff_raw and s.search_effects:
        with torch.no_grad():
            E_s, nu_s = mat.youngs().detach(), mat.poisson().detach()
            tr_s = [t.detach() for t in trajs] if trajs else None
        searched = search_effects(lambda: prob.loss(E_s, nu_s, tr_s, effects=eff_now())["rec"], eff_raw,
                                  tuple(s.search_effects), (st.youngs_min, st.youngs_max), prob.traj_scale,
                                  points=s.effect_search_points, log=log)
        if log:
            for e, r in searched.items():
                log(f"{e}: start {r['parameter']} = {r['value']:.4g} (1-D search, loss {r['loss']:.5f})")
    pairs_np = neighbour_pairs(prob.x0, 1.6 * st.particle_spacing)
    pairs = torch.as_tensor(pairs_np, device=prob.tdev)
    pair_w = torch.as_tensor(pair_weights(pairs_np, feats, s.appearance), dtype=prob.tdtype, device=prob.tdev)
    lam_smooth = prob.weights.smooth if feats is not None else prob.weights.smooth_plain
    history: list[float] = []
    best = {"loss": float("inf")}
    interrupted = False
    gn_log: list = []
    parts_log: list = []
    iter_s: list = []          # each gradient iteration's seconds (model["iteration_s"]: where a slow one is, #26)

    def snapshot(loss_value, sim=None):
        best.update(loss=loss_value, sim=sim, theta=mat.theta.detach().clone(), w_nu=mat.w_nu.detach().clone(),
                    B=mat.B, nu_basis=mat.nu_basis, base=mat.base, trajs=[t.detach().clone() for t in trajs],
                    effects={e: {p: v.detach().clone() for p, v in ps.items()} for e, ps in eff_raw.items()})

    budget = max(int(s.iterations), 0)
    per_level = _split(budget, shares, len(levels))
    bar = None
    if progress and budget:
        from tqdm import tqdm

        bar = tqdm(total=budget, desc="fit", unit="it", dynamic_ncols=True)
    it = 0
    try:
        for li, (k, n_it) in enumerate(zip(levels, per_level)):
            if (li == 0 and start is None and bool(s.skip_searched_uniform) and k == 1 and mat.K == 1 and len(levels) > 1
                    and s.fit_poisson_levels > 1 and not eff_raw):
                # the uniform level after the start search: the search minimised this loss over
                # this E and the next level fits nu too, so the level would repeat them (on the demo
                # its iterations never beat its first: docs/benchmarks/cpu.md, "Levers, session 9")
                if log:
                    log("level 1 (K=1) skipped: the start search found its E, level 2 fits nu too")
                continue
            if li > 0:
                if "theta" in best:  # refine from the best iterate so far
                    mat.B, mat.nu_basis = best["B"], best["nu_basis"]
                    mat.base = best.get("base", mat.base)    # (a start may have nested the field: trend_start.py)
                    with torch.no_grad():
                        mat.theta = best["theta"].clone().requires_grad_(True)
                        mat.w_nu = best["w_nu"].clone().requires_grad_(True)
                    trajs = [t.clone().requires_grad_(s.joint) for t in best["trajs"]]
                mat.refine(k, refine_nu=False)
            elif k != mat.K:  # a schedule that starts above one basis function
                mat.refine(k, refine_nu=False)
            if before_finest is not None and start is None and li == len(levels) - 1 and mat.K > 1 and n_it > 0:
                # e.g. the appearance parts' E as the finest level's start (fit/parts_start.py; opt-in, #24)
                def total_now():
                    with torch.no_grad():
                        o = prob.loss(mat.youngs(), mat.poisson(), [t.detach() for t in trajs] if trajs else None,
                                      effects=eff_now())
                        rg = lam_smooth * mat.smoothness(pairs, pair_w) if len(pairs) and mat.K > 1 else 0.0
                        return float(o["rec"] + o["reg_traj"] + rg)

                stopping.check("backward")
                t_hook = time.perf_counter()
                ps = before_finest(prob, mat, s, trajs, eff_now(), total_now, log)
                clock.add("starts", time.perf_counter() - t_hook)
                # charged to the budget only when taken: a start not taken leaves the fit exactly the old one
                # (its probes' time is extra, recorded in the model's "parts_start")
                charged = (min(forwards_to_iterations(ps["forwards"], BACKWARD_PER_FORWARD), n_it)
                           if ps["forwards"] and ps["used"] else 0)
                n_it -= charged
                for _c in range(charged):
                    history.append(ps["loss"])
                    it += 1
                    if bar is not None:
                        bar.update(1)
                if ps["used"] and ps["loss"] < best["loss"]:
                    snapshot(ps["loss"])
                parts_log.append({k: v for k, v in ps.items()} | {"charged": charged})
            n_gn = int(s.gn_steps) if (li == len(levels) - 1 and mat.K > 1 and mat.K <= s.gn_max_basis) else 0
            for _ in range(n_gn):
                # Gauss-Newton on the few bump amplitudes (fit/gauss_newton.py; opt-in, #24): Adam moves a
                # coefficient ~its learning rate per iteration, a Newton step as far as the curvature says
                if it >= budget or n_it <= 0:
                    break
                stopping.check("backward")   # (its forwards are a step's work, as a backward)
                step = _gn_step(prob, mat, trajs, eff_now(), pairs, pair_w, lam_smooth, log)
                charged = min(forwards_to_iterations(step["forwards"], BACKWARD_PER_FORWARD), n_it)
                n_it -= charged
                for _c in range(charged):
                    history.append(step["loss"])
                    it += 1
                    if bar is not None:
                        bar.update(1)
                if step["loss"] < best["loss"]:
                    snapshot(step["loss"])
                gn_log.append({k: v for k, v in step.items() if k != "tried"} | {"level": li + 1, "charged": charged})
                if not step["accepted"]:
                    break
            fit_nu = li < s.fit_poisson_levels
            groups = [{"params": [mat.theta], "lr": s.lr_material}]
            if fit_nu:
                groups.append({"params": [mat.w_nu], "lr": s.lr_poisson})
            fit_traj = s.joint and trajs and li >= len(levels) - s.trajectory_levels
            if fit_traj:  # material first: T0 is a guide, and early trajectory noise hides E's signal
                groups.append({"params": trajs, "lr": s.lr_trajectory})
            if eff_raw:   # the effects' parameters at every level
                groups.append({"params": [v for ps in eff_raw.values() for v in ps.values()], "lr": s.lr_effects})
            opt = AdamW(groups, weight_decay=s.weight_decay)
            base = [g["lr"] for g in opt.param_groups]
            level_losses, tail, stop_at = [], None, n_it
            patience = level_patience(s.plateau_patience, start is None and li == 0 and mat.K == 1,
                                      s.plateau_patience_searched)
            for j in range(n_it):
                if j >= stop_at:   # the level plateaued and its tail is done (fit/converge.py)
                    break
                scale = lr_scale(j, n_it, tail)
                for g, b0 in zip(opt.param_groups, base):
                    g["lr"] = b0 * scale
                t_it = time.perf_counter()
                opt.zero_grad(set_to_none=True)
                E = mat.youngs()
                nu = mat.poisson()
                try:
                    out = prob.loss(E, nu, trajs if trajs else None, effects=eff_now())
                except SimulationError as exc:
                    if log:
                        log(f"iteration {it}: {exc}; halving the step")
                    for g in opt.param_groups:
                        g["lr"] *= 0.5
                    _restore(mat, trajs, best, s.joint, eff_raw)
                    it += 1
                    continue
                reg = lam_smooth * mat.smoothness(pairs, pair_w) if len(pairs) and mat.K > 1 else 0.0
                total = out["rec"] + out["reg_traj"] + reg
                lv = float(total.detach())
                history.append(lv)
                if not level_losses or lv < min(level_losses):   # this level's best (the tail's start)
                    level_best = _level_params(mat, trajs, eff_raw)
                level_losses.append(lv)
                if lv < best["loss"]:   # with its simulation: the last pass renders it, no rerun
                    snapshot(lv, (out["x"].detach(), out["F"].detach()))
                total.backward()
                clean_gradients(opt, trajs)
                opt.step()
                iter_s.append(round(time.perf_counter() - t_it, 3))
                it += 1
                if bar is not None:
                    with torch.no_grad():
                        bar.set_postfix(loss=f"{lv:.4f}", best=f"{best['loss']:.4f}", K=mat.K,
                                        E=f"{float(E.median()):.3g}")
                    bar.update(1)
                if on_iteration is not None:
                    on_iteration(it, lv, mat, trajs)
                if tail is None and plateaued(level_losses, patience, s.plateau_tol):
                    # converged: the level's best iterate, no momentum, a short annealed tail
                    # (a level that never beat its first loss has nothing to anneal: it ends here)
                    n_tail = s.plateau_tail if improved(level_losses, s.plateau_tol) else 0
                    tail, stop_at = (j + 1, scale, n_tail), min(n_it, j + 1 + n_tail)
                    _restore_in_place(mat, trajs, level_best, eff_raw)
                    for st_ in opt.state.values():   # no momentum back into the overshoot; the
                        if "exp_avg" in st_:         # step sizes Adam learnt stay (a cleared state's
                            st_["exp_avg"].zero_()   # first step is a full-LR one in every coordinate)
                    if log and stop_at < n_it:
                        log(f"level {li + 1} (K={mat.K}) plateaued at iteration {j + 1} of {n_it}: "
                            + (f"{n_tail} annealed iterations more" if n_tail else
                               "ends at its best iterate" if improved(level_losses, s.plateau_tol) else
                               "no better than its start, ends"))
    except KeyboardInterrupt:
        interrupted = True
        if log:
            log("interrupted: keeping the best iterate so far")
    finally:
        if bar is not None:
            bar.close()
    if "theta" in best:
        _restore(mat, trajs, best, s.joint, eff_raw)
    E = mat.youngs().detach()
    nu = mat.poisson().detach()
    # final pass: renders, metrics, animation; the loss as the history counts it (frames 1.., the
    # smoothness term), so the reported final loss is the kept iterate's entry in the history
    t_loop = time.perf_counter() - t0 - sum(clock.seconds.values())
    clock.add("iterations", t_loop)           # the levels' iterations (and the effect search, if any)
    t_final = time.perf_counter()
    with torch.no_grad():   # (the kept iterate's own simulation when the loop ran it)
        stopping.finishing()
        out = prob.loss(E, nu, [t.detach() for t in trajs] if trajs else None, effects=eff_now(),
                        frames=range(1, prob.T), keep_renders=True, simulated=best.get("sim"))
        reg = lam_smooth * mat.smoothness(pairs, pair_w) if len(pairs) and mat.K > 1 else 0.0
        final_loss = float(out["rec"] + out["reg_traj"] + reg)
        x, F = out["x"], out["F"]
        renders = {0: {n: v.detach() for n, v in prob.render_frame(0, x[0], F[0]).items()}, **out["renders"]}
    metrics = frame_metrics(prob, renders)
    clock.add("final_pass", time.perf_counter() - t_final)
    conf = np.ones(len(prob.x0))
    t_conf = time.perf_counter()
    if s.confidence_probes > 0:  # also after Ctrl-C: the kept iterate is written, with its confidence
        if interrupted and log:
            log("estimating the kept iterate's confidence (Ctrl-C again quits without writing)")
        same = None if interrupted else (x, F)   # the final pass's rollout is this field's (unless refined below)
        if mat.K < max(levels) or mat.centre_mask is not None:
            # the kept iterate may come from a coarse level (a uniform E has one uniform
            # confidence): judge it at the finest resolution the schedule reaches, with bumps on
            # held particles too (the fit gives them none, so they share their free neighbours'
            # value; what the video says about them alone is what the confidence reports)
            mat.centre_mask = None
            mat.refine(max(levels))
            same = None
        conf = confidence(prob, mat, trajs, s.confidence_probes, seed=s.seed, effects=eff_now(),
                          covariance=s.confidence_covariance, simulated=same)
    clock.add("confidence", time.perf_counter() - t_conf)
    model = {"schedule": "bumps", "effect_search": searched} if searched else {}
    model["phases_s"] = dict(clock.seconds)
    model["iteration_s"] = iter_s
    if mat.base is not None:
        model["nested"] = True                    # the field was an offset on a fixed base's E
    if parts_log:
        model["parts_start"] = parts_log[0]       # the appearance parts' start (FitSettings.parts_start)
    if gn_log:
        model["gauss_newton"] = gn_log            # the Gauss-Newton steps (FitSettings.gn_steps)
    if probes:
        model["uniform_probes"] = probes          # the start search's uniform E -> loss
    if start_skipped:
        model["uniform_skipped"] = start_skipped  # start-search probes that went unstable / left the grid
    return assemble_result(prob, s, E, nu, conf, trajs, x, F, metrics, feats, history, final_loss, t0,
                           interrupted, e_uniform, model=model,
                           effect_parameters=fitted_values(eff_raw, prob.traj_scale) if eff_raw else {})


def assemble_result(prob: FitProblem, s: FitSettings, E, nu, conf, trajs, x, F, metrics, feats, history,
                    final_loss, t0, interrupted, e_uniform, **extra) -> FitResult:
    """The FitResult of a kept iterate: the animation's Gaussians, the material per Gaussian (from
    the particles of its own colour when the appearance prior is on), the trajectories by name."""
    means, covs = [], []
    with torch.no_grad():
        for k in range(prob.T):
            m, c = prob.gaussians_at(x[k], F[k])
            means.append(m.cpu().numpy())
            covs.append(c.cpu().numpy())
    w, idx = gaussian_weights(prob, feats)
    En = E.detach().cpu().numpy()
    nun = nu.detach().cpu().numpy()
    names = prob.sim.slot_names()
    return FitResult(
        youngs=En, poisson=nun, confidence=conf,
        trajectories={n: t.detach().cpu().numpy() for n, t in zip(names, trajs)},
        positions=x.cpu().numpy(), deformation=F.cpu().numpy(), gaussian_means=np.stack(means),
        gaussian_covs=np.stack(covs), youngs_gaussian=np.exp((w * np.log(En)[idx]).sum(1)),
        poisson_gaussian=(w * nun[idx]).sum(1), confidence_gaussian=(w * conf[idx]).sum(1),
        frame_metrics=metrics, loss_history=history, final_loss=final_loss,
        runtime_s=time.perf_counter() - t0, device=device_name(prob.device),
        settings={**asdict(s), "levels": list(s.levels), "level_share": list(s.level_share)},
        effects=dict(prob.effects), interrupted=interrupted, uniform_start=e_uniform, **extra)


def gaussian_weights(prob: FitProblem, feats) -> tuple[np.ndarray, np.ndarray]:
    """(weights, particle indices) (N, k) that carry per-particle material values to the Gaussians:
    the binding's, restricted to the particles of the Gaussian's own colour when the appearance prior
    is on (`feats`: the particles' appearance features, None when it is off)."""
    w = prob.binding.weight.cpu().numpy()
    idx = prob.binding.index.cpu().numpy()
    if feats is not None:  # material values per Gaussian from the particles of its own colour
        w = appearance_transfer_weights(w, idx, prob.gaussian_appearance(), feats)
    return w, idx


def _split(total, shares, n):
    shares = np.asarray(shares[:n], float)
    shares = shares / shares.sum()
    counts = np.floor(shares * total).astype(int)
    counts[-1] += total - counts.sum()
    return counts.tolist()


def _restore(mat, trajs, best, joint, eff_raw=None):
    if "theta" not in best:
        return
    for e, ps in best.get("effects", {}).items():
        for p, v in ps.items():
            with torch.no_grad():
                eff_raw[e][p].copy_(v)
    mat.B, mat.nu_basis = best["B"], best["nu_basis"]
    mat.base = best.get("base", mat.base)
    mat.K = mat.B.shape[1]
    with torch.no_grad():
        mat.theta = best["theta"].clone().requires_grad_(True)
        mat.w_nu = best["w_nu"].clone().requires_grad_(True)
    for t, b in zip(trajs, best["trajs"]):
        with torch.no_grad():
            t.copy_(b)


def cosine_lr(opt, base: list, j: int, n: int) -> None:
    """Iteration j of n: each parameter group's rate on a cosine from its base rate down to 10% of it."""
    cos = 0.5 * (1 + math.cos(math.pi * j / max(n, 1)))
    for g, b0 in zip(opt.param_groups, base):
        g["lr"] = b0 * (0.1 + 0.9 * cos)


def clean_gradients(opt, trajs) -> None:
    """Before an optimiser step: the trajectories' rest frame is observed, so its position is not a
    parameter (gradient zeroed); a rare non-finite gradient (a degenerate F) becomes 0, so that
    parameter skips the step. Without a host read: every gradient goes through nan_to_num, which leaves a
    finite one bitwise as it is (a test per tensor cost a device sync each on a GPU, #26)."""
    for tr in trajs:
        if tr.grad is not None:
            tr.grad[0] = 0
    for g in opt.param_groups:
        for p in g["params"]:
            if p.grad is not None:
                p.grad = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)


def _level_params(mat, trajs, eff_raw) -> dict:
    """A copy of the parameters the level's optimiser holds."""
    return {"theta": mat.theta.detach().clone(), "w_nu": mat.w_nu.detach().clone(),
            "trajs": [t.detach().clone() for t in trajs],
            "effects": {e: {p: v.detach().clone() for p, v in ps.items()} for e, ps in (eff_raw or {}).items()}}


def _restore_in_place(mat, trajs, saved, eff_raw=None):
    """`_level_params`' copy back into the tensors the optimiser holds."""
    with torch.no_grad():
        mat.theta.copy_(saved["theta"])
        mat.w_nu.copy_(saved["w_nu"])
        for t, b in zip(trajs, saved["trajs"]):
            t.copy_(b)
        for e, ps in saved["effects"].items():
            for p, v in ps.items():
                eff_raw[e][p].copy_(v)


def frame_metrics(prob: FitProblem, renders: dict) -> list:
    """Per frame (sorted), the image metrics of `renders` against the video. The frames' SSIM filters (numpy and
    scipy, which let go of the GIL) run on a few threads: the paper row's 45 frames at 512^2 took ~2 s on one (#26);
    the values are each frame's own, whatever the threads."""
    from concurrent.futures import ThreadPoolExecutor

    def one(k):
        r = renders[k]
        pred = r["rgb"].cpu().numpy()
        sil = r["alpha"].cpu().numpy() > 0.5
        true = prob.obs.frames[k]
        true_sil = prob.obs.masks[k] if prob.obs.masks is not None else sil
        hand = prob.obs.hand_masks[k] if prob.obs.hand_masks is not None else None
        d = M.frame_metrics(pred, true, sil, true_sil, hand)
        d["frame"] = int(k)
        return d

    ks = sorted(renders)
    threads = max(1, min(METRIC_THREADS, os.cpu_count() or 1, len(ks)))
    if threads == 1:
        return [one(k) for k in ks]
    with ThreadPoolExecutor(threads) as ex:
        return list(ex.map(one, ks))


METRIC_THREADS = 8   # frame_metrics' threads at most (each frame's SSIM is a few scipy filters)


def residual_correlation(residuals: list) -> float:
    """How many pixels one independent residual spans: the integral of the residuals' normalised
    spatial autocorrelation (pixels) times that of their frame-to-frame correlation (frames), both
    >= 1. Independent pixel noise gives ~1; a smooth, persistent model error gives its blob area
    times the number of frames it persists over. The Fisher information, which counts pixels, is
    divided by this (a sandwich-style correction for correlated residuals)."""
    if not residuals:
        return 1.0
    R = np.stack(residuals).astype(np.float64)          # (T, H, W)
    R = R - R.mean()
    var = float((R ** 2).mean())
    if var <= 0:
        return 1.0
    T, H, W = R.shape
    f = np.fft.rfft2(R, s=(2 * H, 2 * W))               # zero-padded: linear, not circular
    ac = np.fft.irfft2((f * np.conj(f)).sum(0), s=(2 * H, 2 * W))
    ac /= max(ac[0, 0], 1e-30)
    # positive lobe around zero lag (a noisy tail would sum to anything): lags within the region
    # where the correlation stays above zero along both axes
    lim_y = int(np.argmax(ac[:H, 0] <= 0)) or H
    lim_x = int(np.argmax(ac[0, :W] <= 0)) or W
    core = np.concatenate([ac[:lim_y], ac[-lim_y + 1:]] if lim_y > 1 else [ac[:1]], axis=0)
    core = np.concatenate([core[:, :lim_x], core[:, -lim_x + 1:]] if lim_x > 1 else [core[:, :1]], axis=1)
    area = max(float(np.clip(core, 0, None).sum()), 1.0)
    frames = 1.0
    if T > 1:
        flat = R.reshape(T, -1)
        norms = np.linalg.norm(flat, axis=1)
        ok = (norms[:-1] > 0) & (norms[1:] > 0)
        if ok.any():
            rho = float(np.mean((flat[:-1] * flat[1:]).sum(1)[ok] / (norms[:-1] * norms[1:])[ok]))
            rho = min(max(rho, 0.0), 0.99)
            frames = min((1 + rho) / (1 - rho), float(T))   # AR(1) integrated correlation time
    return area * frames


BACKWARD_PER_FORWARD = 3.0   # the simulator's backward costs ~3 forwards (the demo: 4.66 / 1.55 s CPU)
FD_LOG_E_STEP = 0.01         # the finite-difference estimator's step: 1% of E where the coefficient acts most


def confidence(prob: FitProblem, mat: MaterialField, trajs, probes: int, seed: int = 0,
               tol: float = math.log(1.2), return_sigma: bool = False, effects: dict | None = None,
               method: str = "auto", return_diag: bool = False, covariance: str = "full",
               exposure_floor: float | None = None, simulated=None):
    """Per-particle confidence in E: the probability that log E lies within the MA tolerance of
    the estimate, from the Gauss-Newton curvature of the current basis coefficients.

    diag(J^T J), J the Jacobian of the weighted pixel residuals (RGB and silhouette) w.r.t. the
    coefficients, comes from one of two estimators (`method`):
    - "probes": Rademacher probes s, E[(J^T s)^2] = diag(J^T J): one simulation, then a backward
      per probe (unbiased, with a variance that falls as 1 / probes);
    - "fd": J's columns by one-sided finite differences (one simulation per coefficient, each
      coefficient stepped down so that E moves by FD_LOG_E_STEP where it acts most; down, so the
      adaptive substep keeps its rung): the diagonal itself, no sampling variance, first-order
      truncation error (checked against 200 probes in tests/test_fit_confidence.py);
    - "auto": "fd" when its K simulations cost less than the probes' backwards (K < BACKWARD_PER_FORWARD
      x probes: the demo's 8 bumps against 4 probes), else "probes"; "fd" falls back to "probes"
      when a stepped simulation fails or changes the substep.
    The noise variance is the mean squared residual, inflated by the residuals' correlation (see
    `residual_correlation`): what is left after a fit is mostly model error (discretisation, missing
    effects), smooth in space and persistent in time, not independent pixel noise, and counting
    every pixel as independent evidence claims a precision the data do not hold.
    With "fd" the columns give the whole Gauss-Newton matrix J^T J (`covariance="full"`, this function's
    default): sigma(log E_p)^2 = dlogE_p^2 B_p Sigma B_p^T, Sigma = noise x (J^T J)^-1 (the Laplace
    covariance: a valley along which two regions' E trade, which the diagonal cannot see, widens both; a
    direction the video does not pin at all gives sigma -> inf, confidence 0). `covariance="sandwich"` (the
    fit's default, `FitSettings.confidence_covariance`): the larger of that and the frame-clustered sandwich
    (`sandwich_variance`: how far the frames' own gradients disagree), which sees a model error that pulls
    the frames apart, not one they all share. With the probes, columns over `GRAM_COLUMNS_BYTES`, or
    `covariance="diag"`, only the diagonal: sigma(log E_p) = sum_k |B_pk dlogE/dtheta_k| sigma_k.
    Where the video cannot see a particle's E the confidence is 0, whatever the curvature says (a
    smooth basis function shares one coefficient between a strained region and a held or unstrained
    one, which would lend it the strained region's certainty): a support holds it, or its strain
    exposure in the same rollout is below `exposure_floor` x the free particles' median
    (`exposure.unconstrained_particles`; default `exposure.EXPOSURE_FLOOR`, 0 turns it off).
    `return_diag`: (confidence, diag(J^T J), the method used) instead. `simulated`: (x, F), the rollout of this very
    field, trajectories and effects that the caller already ran (the fit's final pass): with the finite differences
    (no graph needed) it is not simulated again (#26: one forward of the paper-size fit's confidence).
    """
    theta = mat.theta.detach().clone().requires_grad_(True)
    mat.theta = theta
    rss, count = 0.0, 0
    residuals = []
    tr = [t.detach() for t in trajs] if trajs else None
    nu = mat.poisson().detach()
    eff = {e: {p: v.detach() for p, v in ps.items()} for e, ps in effects.items()} if effects else None
    K = int(theta.numel())
    use_fd = method == "fd" or (method == "auto" and K < BACKWARD_PER_FORWARD * max(int(probes), 0))

    # one simulation and one set of renders at the estimate: the noise, and every probe's graph (the
    # probes differ only in their random signs, so each is a backward of the same graph, kept
    # between them) or the finite differences' base
    E = mat.youngs()
    with torch.set_grad_enabled(not use_fd):
        if use_fd and simulated is not None:
            x, F = simulated
        else:
            x, F = prob.simulate(E if not use_fd else E.detach(), nu, tr, eff)
        res = _weighted_residuals(prob, x, F)
    unseen = _unseen_particles(prob, F, exposure_floor)
    for r, rm in res:
        if rm is not None:
            rss += float((rm.detach() ** 2).sum())
            count += rm.numel()
        rss += float((r.detach() ** 2).sum())
        count += r.numel()
        residuals.append(r.detach().float().mean(-1).cpu().numpy())
    diag = gram = frame_grads = None
    used = "probes"
    if use_fd:
        gram, frame_grads = _gn_gram_fd(prob, mat, nu, tr, eff, res, per_frame=True)
        if gram is not None:
            diag = torch.diagonal(gram).clone()
            used = "fd"
        else:   # a stepped simulation failed or changed the substep: the probes, on a fresh graph
            E = mat.youngs()
            x, F = prob.simulate(E, nu, tr, eff)
            res = _weighted_residuals(prob, x, F)
    if diag is None:
        gen = torch.Generator(device="cpu").manual_seed(seed + 11)
        diag = torch.zeros_like(theta)
        for p in range(probes):
            acc = 0.0
            for r, rm in res:       # the signs drawn in the same order as one simulation per probe drew them
                sgn = (torch.randint(0, 2, r.shape, generator=gen) * 2 - 1).to(r)
                acc = acc + (sgn * r).sum()
                if rm is not None:
                    sm = (torch.randint(0, 2, rm.shape, generator=gen) * 2 - 1).to(rm)
                    acc = acc + (sm * rm).sum()
            g, = torch.autograd.grad(acc, theta, retain_graph=p < probes - 1)
            diag += g.detach() ** 2
        diag /= max(int(probes), 1)
    noise_var = max(rss / max(count, 1), 1e-8) * residual_correlation(residuals)
    sigma_theta = torch.sqrt(noise_var / diag.clamp_min(1e-30))
    with torch.no_grad():
        s = torch.sigmoid(mat.u())                     # (a nested field's base included)
        dlog = (mat.hi - mat.lo) * s * (1 - s)          # d logE_p / d u_p
        if frame_grads is not None and covariance in ("full", "sandwich"):   # the columns kept: J^T J whole
            Bd = mat.B.detach().double().cpu()
            var = noise_var * laplace_variance(Bd, gram.double().cpu())
            if covariance == "sandwich":
                var = torch.maximum(var, sandwich_variance(Bd, gram.double().cpu(), frame_grads.cpu()))
            sigma_p = torch.sqrt(var).to(dlog) * dlog
        else:
            sigma_p = (mat.B * sigma_theta[None, :]).sum(1) * dlog
        conf = torch.erf(tol / (sigma_p * math.sqrt(2.0)).clamp_min(1e-12))
        if unseen is not None:
            conf = torch.where(torch.as_tensor(unseen, device=conf.device), torch.zeros_like(conf), conf)
    if return_diag:
        return conf.cpu().numpy(), diag.detach().cpu().numpy(), used
    if return_sigma:     # and sigma(log E) per particle (the Laplace interval's half-width / 1.96)
        return conf.cpu().numpy(), sigma_p.cpu().numpy()
    return conf.cpu().numpy()


def _unseen_particles(prob: FitProblem, F, floor: float | None) -> np.ndarray | None:
    """(P,) bool: the particles whose E the video cannot see (held by a support, or barely strained
    in this rollout: `exposure.unconstrained_particles`); None when off (floor 0) or not known."""
    floor = EXPOSURE_FLOOR if floor is None else float(floor)
    if floor <= 0 or prob.T < 2:
        return None
    try:
        held = np.asarray(prob.held_particles(), bool)
    except AttributeError:
        held = np.zeros(len(prob.x0), bool)
    expo = exposure_of_rollout(F, list(range(1, prob.T)))
    if expo is None:
        return None
    return unconstrained_particles(expo, held, floor)


def _weighted_residuals(prob: FitProblem, x, F) -> list:
    """Per frame 1..T-1: the weighted RGB residual and the weighted silhouette residual (or None)."""
    res = []
    for k in range(1, prob.T):
        out = prob.render_frame(k, x[k], F[k])
        w = prob.weight[k] if prob.weight is not None else torch.ones_like(out["alpha"])
        r = (out["rgb"] - prob.frames[k]) * w[..., None]
        rm = (out["alpha"] - prob.masks[k]) * w if prob.masks is not None else None
        res.append((r, rm))
    return res


def fd_batched(sim) -> bool:
    """Whether the finite differences' K stepped fields go as tiled copies in one rollout (#26): on CUDA (the paper
    row's confidence on an H200: 8.6 -> 6.7 s, the same stage, one lease); on the CPU copies cost their sum, and the
    stepped fields go on threads instead (`Simulation.simulate_each`).
    `PHYSINTERACT_FD_BATCH` = "never" / "always" overrides it (the benchmarks' A/B)."""
    how = os.environ.get("PHYSINTERACT_FD_BATCH", "cuda")
    if how == "never" or not hasattr(sim, "simulate_batch"):
        return False
    return how == "always" or str(getattr(sim, "tdev", "cpu")).startswith("cuda")


def _fd_columns_batched(prob: FitProblem, mat: MaterialField, nu, tr, eff, jobs, hs, diag, cols):
    """`_gn_diag_fd`'s stepped simulations as tiled copies side by side (`Simulation.simulate_batch`; `fd_batched`
    says where), **with the unstepped field as copy 0**: each column is the
    difference of two copies of one rollout (a tiled copy's arithmetic is not bitwise the solo rollout's, and a 1%
    step's response would carry that difference). Every job is at the current rung (checked by the caller), so the
    batch runs at it. Fills `diag` (or `cols`) as the caller would; None when a copy failed (as the solo path); False
    where the batch does not apply (a scene that cannot be tiled): the caller goes on with its own path."""
    from ..sim.batch import TilingError

    sim = prob.sim
    E = torch.stack([mat.youngs().detach()] + [torch.as_tensor(j[0]).detach() for j in jobs])
    trajs = None if tr is None else [t.detach() for t in tr]
    try:
        with torch.no_grad():
            x, F, bad = sim.simulate_batch(E, nu, trajs, eff)
    except (TilingError, ValueError):
        return False
    if bool(np.any(bad)):
        return None
    with torch.no_grad():
        base_b = _weighted_residuals(prob, x[0], F[0])
        for k, h in enumerate(hs):
            if cols is not None:
                cols.append(_fd_column(prob, base_b, x[k + 1], F[k + 1], h))
            else:
                diag[k] = _fd_column_sq(prob, base_b, x[k + 1], F[k + 1], h)
    return diag


def _fd_column(prob: FitProblem, base, x, F, h: float) -> torch.Tensor:
    """J_k from one stepped simulation (x, F): the weighted residuals' change from `base` over h, every
    frame's RGB and silhouette residual flattened into one vector."""
    parts = []
    for (r0, rm0), (r, rm) in zip(base, _weighted_residuals(prob, x, F)):
        parts.append(((r0.detach() - r) / h).reshape(-1))
        if rm0 is not None:
            parts.append(((rm0.detach() - rm) / h).reshape(-1))
    return torch.cat(parts)


def _fd_column_sq(prob: FitProblem, base, x, F, h: float) -> float:
    """|J_k|^2 from one stepped simulation (x, F)."""
    return float((_fd_column(prob, base, x, F, h).double() ** 2).sum())


# the whole Gauss-Newton matrix from the finite-difference columns while they fit in this many bytes
# (the columns are kept until all are simulated); beyond it, the diagonal alone
GRAM_COLUMNS_BYTES = 2 << 30


def laplace_variance(B: torch.Tensor, gram: torch.Tensor, rcond: float = 1e-9) -> torch.Tensor:
    """Per row b_p of B: b_p (J^T J)^-1 b_p^T, in the eigenbasis of J^T J (sum_i (b_p . v_i)^2 / lambda_i),
    an eigenvalue floored at rcond x the largest: a direction the video does not pin gets a huge, finite
    variance, and a row that does not reach it is not swamped by round-off (its projection is squared
    before it is divided)."""
    g = 0.5 * (gram + gram.T)
    w, V = torch.linalg.eigh(g)
    top = float(w.max()) if w.numel() else 0.0
    w = w.clamp_min(rcond * max(top, 1e-300))
    return ((B @ V) ** 2 / w[None, :]).sum(1)


def sandwich_variance(B: torch.Tensor, gram: torch.Tensor, frame_grads: torch.Tensor,
                      rcond: float = 1e-9) -> torch.Tensor:
    """Per row b_p of B: b_p S b_p^T, S = G^-1 M G^-1 the frame-clustered sandwich covariance: G = J^T J,
    M = T / (T - 1) sum_f (g_f - mean g)(g_f - mean g)^T over the frames' gradients g_f (T, K). Where the
    frames agree on the coefficients (every g_f alike) it is 0; where they pull apart (the early frames
    want one E and the late ones another: an error of the model, not of the pixels) it is their spread.
    G's eigenvalues floored as in `laplace_variance`."""
    T = int(frame_grads.shape[0])
    if T < 2:
        return torch.zeros(B.shape[0], dtype=B.dtype)
    g = frame_grads.to(B.dtype)
    d = g - g.mean(0, keepdim=True)
    M = (d.T @ d) * (T / (T - 1))
    w, V = torch.linalg.eigh(0.5 * (gram + gram.T))
    top = float(w.max()) if w.numel() else 0.0
    w = w.clamp_min(rcond * max(top, 1e-300))
    A = (B @ V) / w[None, :]                       # b_p V Lambda^-1
    return ((A @ (V.T @ M @ V)) * A).sum(1).clamp_min(0.0)


def _gn_gram_fd(prob: FitProblem, mat: MaterialField, nu, tr, eff, base, per_frame: bool = False):
    """J^T J (K x K) from the finite-difference columns (`_gn_diag_fd`'s simulations; its columns kept
    instead of their squared norms); where K columns would not fit `GRAM_COLUMNS_BYTES`, only the
    diagonal (a diagonal matrix). None as `_gn_diag_fd`. `per_frame`: (J^T J, the frames' gradients
    (T-1, K) of 0.5 |r_f|^2), the gradients None where only the diagonal is known."""
    K = int(mat.theta.numel())
    n = sum(r.numel() + (rm.numel() if rm is not None else 0) for r, rm in base)
    if K * n * 4 > GRAM_COLUMNS_BYTES:
        d = _gn_diag_fd(prob, mat, nu, tr, eff, base)
        g = None if d is None else torch.diag(d)
        return (g, None) if per_frame else g
    cols = _gn_diag_fd(prob, mat, nu, tr, eff, base, columns=True)
    if cols is None:
        return (None, None) if per_frame else None
    # in float64 a column pair at a time (the columns stay float32: a paper-size clip's 8 columns are ~1.5 GB)
    G = torch.zeros(K, K, dtype=torch.float64, device=cols[0].device)
    for i in range(K):
        ci = cols[i].double()
        for j in range(i + 1):
            G[i, j] = G[j, i] = ci @ cols[j].double()
    gram = G.to(mat.theta.detach())
    if not per_frame:
        return gram
    # each frame's gradient of 0.5 |r_f|^2: g_f = J_f^T r_f (the columns hold the frames in base's order)
    grads, at = [], 0
    for r, rm in base:
        rv = torch.cat([r.detach().reshape(-1)] + ([rm.detach().reshape(-1)] if rm is not None else [])).double()
        grads.append(torch.stack([c[at:at + rv.numel()].double() @ rv for c in cols]))
        at += rv.numel()
    return gram, torch.stack(grads)


def _gn_diag_fd(prob: FitProblem, mat: MaterialField, nu, tr, eff, base, columns: bool = False):
    """diag(J^T J) from one-sided finite differences of the weighted residuals `base` (at the
    current coefficients): coefficient k stepped down by h_k, h_k such that log E moves by
    FD_LOG_E_STEP where basis function k acts most. None when a stepped simulation fails or the
    adaptive substep changes (a different rollout: not a derivative). `columns`: the list of the
    columns J_k themselves (`_fd_column`) instead of the diagonal."""
    theta = mat.theta
    with torch.no_grad():
        s_ = torch.sigmoid(mat.u())
        dlog = (mat.hi - mat.lo) * s_ * (1 - s_)                      # d log E_p / d u_p
        reach = (mat.B.abs() * dlog[:, None]).amax(0)                # (K,) d log E / d theta_k at most
    substeps = getattr(prob.sim, "substeps", None)
    diag = torch.zeros_like(theta.detach())
    cols: list | None = [] if columns else None
    par = _gn_diag_fd_threaded(prob, mat, nu, tr, eff, base, reach, diag, cols)
    if par is not False:
        return cols if (columns and par is not None) else par
    for k in range(int(theta.numel())):
        h = float(min(FD_LOG_E_STEP / max(float(reach[k]), 1e-12), 1.0))
        step = torch.zeros_like(theta.detach())
        step[k] = h
        stopping.check("backward")   # these forwards are the estimate's work: a stop acts here (as in a backward)
        with torch.no_grad():
            mat.theta = theta.detach() - step
            try:
                x, F = prob.simulate(mat.youngs(), nu, tr, eff)
            except SimulationError:
                return None
            finally:
                mat.theta = theta
            if getattr(prob.sim, "substeps", None) != substeps:
                return None
        if cols is not None:
            cols.append(_fd_column(prob, base, x, F, h))
        else:
            diag[k] = _fd_column_sq(prob, base, x, F, h)
    return cols if columns else diag


def _gn_diag_fd_threaded(prob: FitProblem, mat: MaterialField, nu, tr, eff, base, reach, diag, cols=None):
    """`_gn_diag_fd`'s simulations as independent jobs on two threads (`Simulation.simulate_each`: the
    second core), the same values; False where that does not apply (a problem whose simulation is not
    a Simulation's, or a stepped field that would move the rung: the sequential loop decides those)."""
    sim = prob.sim
    if not hasattr(sim, "simulate_each") or "simulate" in vars(prob) or type(prob).simulate is not FitProblem.simulate:
        return False
    theta = mat.theta
    jobs, hs = [], []
    for k in range(int(theta.numel())):
        h = float(min(FD_LOG_E_STEP / max(float(reach[k]), 1e-12), 1.0))
        step = torch.zeros_like(theta.detach())
        step[k] = h
        with torch.no_grad():
            mat.theta = theta.detach() - step
            try:
                Ek = mat.youngs()
            finally:
                mat.theta = theta
        if sim.rung_wanted(float(Ek.detach().max())) != sim.e_bound:
            return False
        jobs.append((Ek, nu, tr, eff))
        hs.append(h)
    stopping.check("backward")   # these forwards are the estimate's work: a stop acts here (as in a backward)
    if fd_batched(sim):
        got = _fd_columns_batched(prob, mat, nu, tr, eff, jobs, hs, diag, cols)
        if got is not False:
            return got
    sims = sim.simulate_each(jobs)
    with torch.no_grad():
        for k, (r_, h) in enumerate(zip(sims, hs)):
            if isinstance(r_, SimulationError):
                return None
            x, F = r_
            if cols is not None:
                cols.append(_fd_column(prob, base, x, F, h))
            else:
                diag[k] = _fd_column_sq(prob, base, x, F, h)
    return diag
