"""The digital twin as a differentiable simulation: a scene's particles, material defaults, grid and
effects (the simulator's `SimModel`), its contacts as controls, and the Gaussians bound to the
particles. `build_simulation` is the one place that assembles it; the fit (`fit.problem`) and
`simulate` both use it. No USD here.

    sim = build_simulation(scene, contacts, n_frames=T, effects=..., device="cpu")
    x, F = sim.simulate(E, nu)                      # (T, P, 3), (T, P, 3, 3), differentiable
    means, covs = sim.gaussians_at(x[k], F[k])      # the splats at frame k
"""

from __future__ import annotations

import os
import threading

import numpy as np
import torch

from .contacts import ContactSet, check_disjoint
from .devices import torch_device
from .errors import InputError
from .render import GaussianBinding, covariance_from_scales_quats
from .scene import SceneData, SimSettings
from .sim import Contact, Control, GridSpec, Rollout, SimModel
from .sim.cfl import rung
from .sim.model import GROUND_CONTACTS

# Independent forwards without gradients (the start search's probes, the confidence's finite differences, the
# interaction check's counterfactuals: `sim_threads`) on this many threads: Warp's CPU kernels run inside ctypes
# calls, which release the GIL, so a second thread simulates on the second core. Bitwise the same results either
# way. None (default): `sim_threads` decides per phase, on the CPU only (CUDA: 1, its probes batched instead).
# PHYSINTERACT_SIM_THREADS=N sets it (1: off)
SIM_THREADS: int | None = int(os.environ["PHYSINTERACT_SIM_THREADS"]) if os.environ.get("PHYSINTERACT_SIM_THREADS") \
    else None
# SIM_THREADS None on the CPU: two threads where >= 2 cores are the process's and at least `lanes.SPARE_MIN` of a
# core sat idle beside it over 0.1 s (sim/lanes.py's measure), else one. Measured on the demo (docs/benchmarks/
# cpu.md, 19th session): -4.5 s wall on average of six A/B pairs (-12.1 to +2.3 s), the three phases -7.7 s; on a
# machine without a core to spare the second thread only waits for one (sessions 13 and 15: slower). On the idle VM
# the demo took 2:38.6 with it against 2:55.8 on one thread (19th session, cpu.md): it stays on
AUTO_THREADS = True


def sim_threads(device="cpu") -> int:
    """How many threads a phase of independent forwards runs on (`SIM_THREADS`, `AUTO_THREADS`)."""
    if SIM_THREADS is not None:
        return max(1, int(SIM_THREADS))
    if not AUTO_THREADS or not str(device).startswith("cpu"):
        return 1
    from .sim.lanes import SPARE_MIN, free_cores, spare_cores
    if free_cores() < 2:
        return 1
    # a 0.1 s window; where another process's blip filled it, a longer one decides (on the idle VM one phase of
    # four read busy once, 19th session); a busy machine reads busy in both
    return 2 if spare_cores() >= SPARE_MIN or spare_cores(0.25) >= SPARE_MIN else 1


# The simulation's domain (#24). A particle whose quadratic stencil passes the grid's valid box is clamped to
# the last nodes and blows up within ~a cell (docs/benchmarks/world_fits.md 1b: dev_0141's bar swinging about its
# hook, dev_0255's released sheet flapping about its clamp, 190-290 mm from the support, past the face of a grid
# grown only around the hand's path). `grid_covering` grows the stage's grid (same dx, same node lattice) to what
# the object can reach: around the hand's path (as before), about each support (`support_reach`: a free end's
# pendulum swing below its rest height, and the rotation the hand's path drives, both ways), and a fall after a
# release with nothing holding it (down to the ground when there is one). The growth beyond the stage's domain and
# the hand's path is capped at REACH_CAP x the object's extent on each side (memory and speed); what still leaves
# the grid is a clear "left the grid" error (sim/solver.py), never a silent clamp.
REACH_CAP = 1.0
REACH_MARGIN_CELLS = 1.0     # room beyond the reach, in cells, besides the stencil's own (the valid box)
# PHYSINTERACT_GRID_REACH=0 in the environment: the hand's path only, as before #24 (an A/B of the cost; read at import)
GRID_REACH = os.environ.get("PHYSINTERACT_GRID_REACH", "1").strip() not in ("0", "off", "false")


def _ground_height(effects: dict | None) -> float | None:
    g = (effects or {}).get("ground")
    if g is None:
        return None
    h = g.get("height", g.get("h", 0.0)) if isinstance(g, dict) else 0.0
    try:
        return float(h)
    except (TypeError, ValueError):
        return None


def _rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """The least rotation turning direction a into direction b (None: either is ~0)."""
    from scipy.spatial.transform import Rotation

    if np.linalg.norm(a) < 1e-12 or np.linalg.norm(b) < 1e-12:
        return None
    return Rotation.align_vectors(np.asarray(b, float)[None], np.asarray(a, float)[None])[0].as_matrix()


def support_reach(x0: np.ndarray, contacts, gravity=(0.0, -9.81, 0.0), fps: float | None = None,
                  ground: float | None = None) -> np.ndarray | None:
    """Points bounding where the object's particles can go about what holds them (a (N, 3) array whose box is the
    reach; None: nothing holds it). Pivots: the fixed supports (each particle about its nearest), or, without any,
    the pointAdherent grasps while they hold (translated along the hand's path).
    - gravity: a free end swings as a rigid pendulum about its pivot from rest: down to r below the pivot (r its
      distance from it; not below the ground) and sideways by its horizontal distance from the pivot, both ways
      (by r where it starts above the pivot's height: a bar released horizontally swings through the bottom and
      up the other side);
    - a driving contact (a hand, a poke) about each fixed support: the rigid rotation about the support that takes
      the contact's point at its grasp to its position at each frame it acts, and the same rotation reversed (the
      rebound after a release swings as far to the other side), stretched by the contact's distance from the
      support where the hand pulls away from it."""
    x0 = np.asarray(x0, np.float64)
    g = np.asarray(gravity, np.float64)
    down = g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, -1.0, 0.0])
    fixed = [c for c in contacts if c.type == "fixed" and len(c.indices)]
    out = []

    def pendulum(pivot, pts):
        o = pts - pivot
        r = np.linalg.norm(o, axis=1)
        h = -(o @ down)                                  # height above the pivot
        oh = o + h[:, None] * down                       # horizontal part
        a = np.linalg.norm(oh, axis=1)
        e = np.where(a[:, None] > 1e-12, oh / np.maximum(a, 1e-12)[:, None], 0.0)
        b = np.where(h >= 0, r, a)                       # the farthest sideways below the rest height
        lowest = -r
        if ground is not None and abs(down[1]) > 0.999:  # not below the ground plane y = h (gravity along y)
            lowest = np.maximum(lowest, np.minimum(ground - float(pivot[1]), h))
        pts_ = []
        for side in (1.0, -1.0):
            for y in (lowest, np.minimum(h, r)):
                pts_.append(pivot + side * b[:, None] * e - y[:, None] * down)
        # a particle above the pivot may topple in any horizontal direction (a sheet standing on its clamp flops
        # out of its plane): r along every horizontal axis
        top = h > 0
        if top.any():
            for ax in range(3):
                u = np.eye(3)[ax] - (np.eye(3)[ax] @ down) * down
                if np.linalg.norm(u) > 1e-9:
                    u = u / np.linalg.norm(u)
                    for side in (1.0, -1.0):
                        pts_.append(pivot + side * r[top, None] * u[None] - lowest[top, None] * down)
        return np.concatenate(pts_)

    if fixed:
        held = np.zeros(len(x0), bool)
        for c in fixed:
            held[c.indices] = True
        pivots = np.stack([x0[c.indices].mean(0) for c in fixed])
        free = np.where(~held)[0]
        near = np.argmin(np.linalg.norm(x0[free][:, None] - pivots[None], axis=-1), axis=1) if free.size else free
        for i, pv in enumerate(pivots):
            pts = x0[free[near == i]]
            if not len(pts):
                continue
            out.append(pendulum(pv, pts))
            rel = pts - pv
            r2 = float(np.mean(np.sum(rel ** 2, axis=1)))            # I / m about the pivot, at least
            cm = rel.mean(0)
            rc_h = -float(cm @ down)                                 # the centre of mass's height above the pivot
            for c in contacts:
                tr = getattr(c, "trajectory", None)
                if c.type == "fixed" or tr is None or fps is None:
                    continue
                tr = np.asarray(tr, np.float64)
                g0 = min(max(int(c.grasp_frame), 0), len(tr) - 1)
                end = len(tr) if c.release_frame is None else min(int(c.release_frame) + 1, len(tr))
                q = tr[g0] - pv
                rq = np.linalg.norm(q)
                if rq < 1e-9 or end - g0 < 2:
                    continue
                # the path's own rotations (as driven, and reversed: the rebound after a release swings as far
                # to the other side), stretched where the hand pulls away from the support
                frames = np.arange(g0, end)
                frames = frames[np.unique(np.linspace(0, frames.size - 1, min(frames.size, 64)).astype(int))]
                best, axis = 0.0, None
                for t in frames:
                    R = _rotation(q, tr[t] - pv)
                    if R is None:
                        continue
                    s = max(1.0, float(np.linalg.norm(tr[t] - pv)) / rq)
                    out.append(pv + s * rel @ R.T)
                    out.append(pv + s * rel @ R)
                    k = np.cross(q, tr[t] - pv)
                    ang = float(np.arctan2(np.linalg.norm(k), np.dot(q, tr[t] - pv)))
                    if ang > best and np.linalg.norm(k) > 1e-12:
                        best, axis = ang, k / np.linalg.norm(k)
                # and the swing the contact's speed can add (a rigid body about the pivot: its kinetic energy
                # 1/2 I w^2, w <= the contact point's speed / its distance, x 2 for a push that may bounce the
                # object off it, lifts its centre of mass by I w^2 / (2 m g) above the angle reached)
                v = np.diff(tr[g0:end], axis=0) * fps
                sp = np.linalg.norm(v, axis=1)
                i = int(np.argmax(sp))
                if sp[i] <= 0:
                    continue
                w = (1.0 if c.type == "pointAdherent" else 2.0) * sp[i] / rq
                gmag = float(np.linalg.norm(g)) or 9.81
                lift = r2 * w * w / (2.0 * gmag)
                if axis is None:
                    k = np.cross(q, v[i])
                    if np.linalg.norm(k) < 1e-12:
                        continue
                    axis = k / np.linalg.norm(k)
                rc = float(np.linalg.norm(cm))
                if rc_h >= 0 or rc < 1e-9:
                    amp = np.pi                                    # above the pivot: it may go over
                else:
                    amp = float(np.arccos(np.clip(np.cos(best) - lift / rc, -1.0, 1.0)))
                if amp <= best + 1e-9:
                    continue
                from scipy.spatial.transform import Rotation

                for R in Rotation.from_rotvec(np.linspace(-amp, amp, 13)[:, None] * axis[None]).as_matrix():
                    out.append(pv + rel @ R.T)
        return np.concatenate(out) if out else None
    for c in contacts:                                   # no support: the grasps hold it while they act
        tr = getattr(c, "trajectory", None)
        if c.type != "pointAdherent" or tr is None or not len(c.indices):
            continue
        tr = np.asarray(tr, np.float64)
        g0 = min(max(int(c.grasp_frame), 0), len(tr) - 1)
        end = len(tr) if c.release_frame is None else min(int(c.release_frame) + 1, len(tr))
        pv = x0[c.indices].mean(0)
        held = np.zeros(len(x0), bool)
        held[c.indices] = True
        sw = pendulum(pv, x0[~held]) if (~held).any() else x0[c.indices]
        d = tr[g0:end] - tr[g0]
        out += [sw + d.min(0), sw + d.max(0)]
    return np.concatenate(out) if out else None


def fall_reach(x0: np.ndarray, contacts, n_frames: int | None, fps: float | None, gravity=(0.0, -9.81, 0.0),
               ground: float | None = None) -> np.ndarray | None:
    """Points bounding a free fall: the frames no support or grasp holds the object (from a release to the end,
    or all of them with no contact holding it), from where the hand left it at the hand's speed then, under
    gravity, not below the ground. None: always held (a fixed support) or no frames / fps given."""
    if not n_frames or not fps or any(c.type == "fixed" and len(c.indices) for c in contacts):
        return None
    T = int(n_frames)
    held = np.zeros(T, bool)
    grasps = [c for c in contacts if c.type == "pointAdherent" and len(c.indices) and c.trajectory is not None]
    for c in grasps:
        held[max(int(c.grasp_frame), 0):T if c.release_frame is None else min(int(c.release_frame), T)] = True
    if held.all():
        return None
    x0 = np.asarray(x0, np.float64)
    g = np.asarray(gravity, np.float64)
    out = []
    k = 0
    while k < T - 1:
        if held[k]:
            k += 1
            continue
        a = k
        while k < T - 1 and not held[k]:
            k += 1
        t = (k - a) / float(fps)
        shift, v = np.zeros(3), np.zeros(3)
        for c in grasps:                                 # where a hand that let go left it, and its speed
            if c.release_frame is not None and int(c.release_frame) == a and a >= 1:
                tr = np.asarray(c.trajectory, np.float64)
                i = min(a, len(tr) - 1)
                shift = tr[i] - tr[min(max(int(c.grasp_frame), 0), i)]
                v = (tr[i] - tr[i - 1]) * fps
        d = v * t + 0.5 * g * t * t
        lo_pts = x0 + shift + d
        if ground is not None and g[1] < 0:
            lo_pts[:, 1] = np.maximum(lo_pts[:, 1], ground)
        out += [x0 + shift, lo_pts]
    return np.concatenate(out) if out else None


def grid_covering(settings: SimSettings, x0: np.ndarray, trajectories=(), *, contacts=(), effects: dict | None = None,
                  fps: float | None = None, n_frames: int | None = None) -> GridSpec:
    """The stage's grid, grown (same dx, same node lattice) to hold the object's reach: the trajectories with a
    margin of half the object's extent (the hand may lead the object out of the init domain), and, given the
    contacts, the reach about the supports and a fall after a release (`support_reach`, `fall_reach`; growth
    beyond the stage's domain and the trajectories' box capped at REACH_CAP x the object's extent a side). The one
    rule every simulation of a stage uses (`Simulation`: fit, simulate, report, evaluate, diagnose)."""
    st = settings
    lo = np.asarray(st.domain_min, float)
    hi = lo + np.asarray(st.grid_resolution) * st.cell_size
    x0 = np.asarray(x0, float)
    ext = float(np.max(np.ptp(x0, axis=0)))
    trajectories = [t for t in trajectories if t is not None]
    need_lo, need_hi = lo.copy(), hi.copy()
    if trajectories:
        pts = np.concatenate([np.asarray(t, float) for t in trajectories])
        need_lo = np.minimum(need_lo, pts.min(0) - 0.5 * ext - np.array([0.0, 0.3 * ext, 0.0]))  # room to sag
        need_hi = np.maximum(need_hi, pts.max(0) + 0.5 * ext)
    contacts = list(contacts or ())
    if contacts and GRID_REACH:
        ground = _ground_height(effects)
        reach = [r for r in (support_reach(x0, contacts, st.gravity, fps, ground),
                             fall_reach(x0, contacts, n_frames, fps, st.gravity, ground)) if r is not None]
        if reach:
            pts = np.concatenate(reach)
            pts = pts[np.all(np.isfinite(pts), axis=1)]
            if len(pts):
                # the valid box is [lower + dx/2, upper - 3 dx/2] (the stencil), plus the margin
                r_lo = pts.min(0) - (0.5 + REACH_MARGIN_CELLS) * st.cell_size
                r_hi = pts.max(0) + (1.5 + REACH_MARGIN_CELLS) * st.cell_size
                cap = REACH_CAP * ext
                need_lo = np.minimum(need_lo, np.maximum(r_lo, need_lo - cap))
                need_hi = np.maximum(need_hi, np.minimum(r_hi, need_hi + cap))
    lo = lo - np.maximum(np.ceil((lo - need_lo) / st.cell_size), 0) * st.cell_size
    hi = hi + np.maximum(np.ceil((need_hi - hi) / st.cell_size), 0) * st.cell_size
    res = tuple(int(round(r)) for r in (hi - lo) / st.cell_size)
    return GridSpec(tuple(lo), st.cell_size, res)


def sim_contact(c: ContactSet, trajectory=None) -> Contact:
    """The simulator's control for a contact (its T0 unless `trajectory` is given)."""
    tr = c.trajectory if trajectory is None else trajectory
    if c.type in ("pointAdherent", "fixed"):
        return Contact(c.type, indices=c.indices, trajectory=None if c.type == "fixed" else tr,
                       grasp_frame=c.grasp_frame, release_frame=c.release_frame)
    if c.type == "pointNonAdherent":
        return Contact(c.type, trajectory=tr, radius=c.radius, shape="sphere", friction=c.friction,
                       grasp_frame=c.grasp_frame, release_frame=c.release_frame)
    return Contact(c.type, trajectory=tr, normal=c.normal, friction=c.friction, grasp_frame=c.grasp_frame,
                   release_frame=c.release_frame)



# A grid node's pin blend is clamp(gain * (pinned share - floor), 0, 1) (sim.model.SimModel.pin_gain).
# The default (4, 0: a quarter of a node's mass held -> the node fully held) moves a clamp's face
# ~0.75 cell out: the test bar's cantilever (L / h ~ 2.3) against the Timoshenko beam swings 1.69x /
# 1.36x / 1.24x / 1.16x too fast and sags 0.32x / 0.57x / 0.68x / 0.79x at grid 10 / 16 / auto (24) /
# 32. The band (5, 0.4: free below 40% held, fully held from 60%) keeps the face where the particles
# end: 1.02x / 0.98x at grid 16, 1.04x / 0.99x at auto (tests/test_known_answers.py,
# docs/benchmarks/fit.md 2026-11-26). It is not the default (a default changes every fit): it is
# chosen by the environment's PHYSINTERACT_PIN_RULE=band (`pin_rule`) for measurements first (#24).
CLAMP_BAND = (5.0, 0.4)
DEFAULT_PIN_RULE = (4.0, 0.0)


def pin_rule(value: str | None) -> tuple[float, float]:
    """The pin rule a setting names (the environment's PHYSINTERACT_PIN_RULE, read once at import):
    unset, empty or "default": DEFAULT_PIN_RULE; "band": CLAMP_BAND (against the Timoshenko beam at
    3 cells through the thickness within 2%, the default 1.36x the frequency and 0.57x the sag:
    tests/test_known_answers.py); "GAIN,FLOOR": that rule (e.g. "1,0": the blend by the held share)."""
    v = (value or "").strip().lower()
    if v in ("", "default"):
        return DEFAULT_PIN_RULE
    if v == "band":
        return CLAMP_BAND
    try:
        gain, floor = (float(t) for t in v.split(","))
    except ValueError:
        raise InputError("PHYSINTERACT_PIN_RULE", f"{value!r}: expected 'default', 'band' or 'GAIN,FLOOR' "
                         "(e.g. '5,0.4')") from None
    if not (gain > 0 and 0 <= floor < 1):
        raise InputError("PHYSINTERACT_PIN_RULE", f"{value!r}: the gain must be > 0 and the floor in [0, 1)")
    return gain, floor


PIN_RULE = pin_rule(os.environ.get("PHYSINTERACT_PIN_RULE"))


# The supports' pin rule (a fixed contact's nodes; sim.model.SimModel.support_rule): None, the grasps' (PIN_RULE).
# The environment's PHYSINTERACT_SUPPORT_RULE (read once at import; the values PHYSINTERACT_PIN_RULE takes, unset:
# None) sets it, for measurements (#24). Not a default: the band at the supports only kept the world captures' hanging
# balls 0.15-0.34x too soft and lost the named suite as the band everywhere did (0.507 -> 0.331), whose truths hold
# their supports as the default rule does (docs/benchmarks/world_fits.md and fit.md, 26th session).
def support_rule(value: str | None) -> tuple[float, float] | None:
    """The supports' pin rule a setting names (the environment's PHYSINTERACT_SUPPORT_RULE): unset or empty: None
    (the grasps' rule); else as `pin_rule` reads it."""
    if not (value or "").strip():
        return None
    try:
        return pin_rule(value)
    except InputError as exc:
        raise InputError("PHYSINTERACT_SUPPORT_RULE", exc.problem) from None


SUPPORT_RULE = support_rule(os.environ.get("PHYSINTERACT_SUPPORT_RULE"))
# The CFL number of the adaptive substep (dt = CFL dx / c_p at the rung's E; sim/cfl.py's default,
# 0.4, sets the stage's substep at the E range's top). On the demo 0.6 takes 2/3 of the substeps at
# the same MA and masked PSNR (0.927 / 34.4 dB vs 0.931 / 34.4); the rollout is stable up to 1.0
# there, and its max deviation from a half-step rollout is 3.2 mm of 44 mm of motion (1.7 mm at
# 0.4): docs/benchmarks/cpu.md. The environment's PHYSINTERACT_CFL (read once at import) sets another, for
# measurements (#24: on a dev bar on the floor the rollout at 0.6 is far from step-converged after its release, yet
# fits at 0.3 found the floor objects' E no closer: docs/benchmarks/world_fits.md, "Floor objects").
DEFAULT_CFL = 0.6


def cfl_number(value: str | None) -> float:
    """The CFL number a setting names (the environment's PHYSINTERACT_CFL): unset or empty: DEFAULT_CFL; else a
    number in (0, 1]."""
    v = (value or "").strip()
    if not v:
        return DEFAULT_CFL
    try:
        c = float(v)
    except ValueError:
        raise InputError("PHYSINTERACT_CFL", f"{value!r}: expected a number in (0, 1], e.g. 0.3") from None
    if not 0 < c <= 1:
        raise InputError("PHYSINTERACT_CFL", f"{value!r}: the CFL number must be in (0, 1] (1 is the stability bound)")
    return c


CFL = cfl_number(os.environ.get("PHYSINTERACT_CFL"))


# Where the ground effect's plane acts (`SimModel.ground_contact`): "nodes", the grid nodes' projection (the default,
# which every stage and table so far used; it brakes a rolling body: docs/sim.md), or "penalty", an elastic push at the
# particles with friction at their contact points (a ball rolls on; it sinks a little). The environment's
# PHYSINTERACT_GROUND (read once at import) picks it for measurements (#24): the synthetic truths and the fits both read
# it, so a world capture and its fit share it.
def ground_contact(value: str | None) -> str:
    """The ground contact a setting names (the environment's PHYSINTERACT_GROUND): unset or empty: "nodes"."""
    v = (value or "").strip().lower()
    if not v:
        return "nodes"
    if v not in GROUND_CONTACTS:
        raise InputError("PHYSINTERACT_GROUND", f"{value!r}: expected one of {', '.join(GROUND_CONTACTS)}")
    return v


GROUND_CONTACT = ground_contact(os.environ.get("PHYSINTERACT_GROUND"))


class Simulation:
    """A scene's simulation under its contacts for `n_frames` frames (frame 0 = rest).

    `contacts[i]` drives the simulator's contact i; `traj_slots` lists (i, T0 tensor) of the
    contacts whose trajectory is an input (all but fixed), in order: `simulate(E, nu,
    trajectories=[...])` takes one (T, 3) tensor per slot."""

    def __init__(self, scene: SceneData, contacts: list[ContactSet], n_frames: int, *, effects: dict | None = None,
                 device: str = "cpu", dtype: str = "float32", knn: int = 4, adaptive_substeps: bool = True,
                 prestress_from: "Simulation | None" = None):
        if n_frames < 2:
            raise ValueError("a simulation needs at least 2 frames")
        check_disjoint(contacts)
        self.scene, self.contacts, self.T = scene, list(contacts), int(n_frames)
        self.device = device
        self.tdev = torch_device(device)
        self.tdtype = torch.float32 if dtype == "float32" else torch.float64
        st = scene.settings
        self.x0 = scene.particles_positions
        self.effects = dict(effects or {})
        for c in self.contacts:
            if c.type != "fixed" and (c.trajectory is None or len(c.trajectory) != self.T):
                raise ValueError(f"contact {c.name}: a ({self.T}, 3) trajectory is needed")
        self.grid = grid_covering(st, self.x0, [c.trajectory for c in self.contacts], contacts=self.contacts,
                                  effects=self.effects, fps=scene.fps, n_frames=self.T)
        self.dtype = dtype
        self.traj_slots = [(i, torch.as_tensor(c.trajectory, dtype=self.tdtype, device=self.tdev))
                           for i, c in enumerate(self.contacts) if c.type != "fixed"]
        self.control = Control([sim_contact(c) for c in self.contacts], n_frames=self.T - 1)
        self.adaptive = bool(adaptive_substeps)
        self._rollouts: dict[float, Rollout] = {}
        self._batch_rollouts: dict = {}          # (rung, copies) -> (Tiled, Rollout)
        self._twins: dict = {}                   # rung -> eager Rollouts for `simulate_each`'s other threads
        self._probe_twins: dict = {}             # (rung, slot) -> an eager Rollout for `forward_at` (probes on two threads)
        self.e_bound = float(st.youngs_max)
        # the Maxwell branch's modulus the substep is made stable for (None: up to the E bound, which takes
        # ~sqrt(2) x the substeps; `match_substeps_to_base`)
        self.viscous_cfl_modulus: float | None = None
        self._use_bound(self.e_bound if not self.adaptive else
                        self.bound_for(float(np.max(scene.youngs_modulus.clip(st.youngs_min, st.youngs_max)))))
        # the scan's preload (init --preload; sim.preload): the stress that holds the scan at rest on frame 0's
        # supports, solved once (it does not depend on E); every forward starts from its stretch at the call's E.
        # `prestress_from` (forward_twin): another simulation's, taken where it was solved for the same scene, grid
        # and holds (a probe under another hand path; the solve costs ~12 s at 48k particles on 2 CPU cores)
        self.prestress = None
        self._solved_prestress = None
        self._holds = self._holding_key()
        if getattr(st, "preload", False):     # True; None (the fit decides, `use_preload`) and False: stress-free
            try:
                self.use_preload(True, share_from=prestress_from)
            except ValueError as exc:
                raise InputError(scene.path, f"{exc} (the stage was made with init --preload: give the object its "
                                             "support or the ground effect, or init it again without --preload)") \
                    from None
        g = scene.gaussians
        self.binding = GaussianBinding.knn(g.means, self.x0, k=knn, dtype=self.tdtype, device=self.tdev)
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=self.tdtype, device=self.tdev)  # noqa: E731
        self.cov0 = covariance_from_scales_quats(t(g.scales), t(g.quats))
        self.colors = t(g.colors)
        self.opacities = t(g.opacities)

    # ------------------------------------------------------------------ the substep
    def match_substeps_to_base(self) -> None:
        """Take the substep as the model without a Maxwell branch would (its modulus at the effect's
        value, not up to the E bound): a superset simulator whose viscoelasticity is at its null (E_v =
        0: `diagnose`) then steps exactly as the fitted base model did. Without it the branch's CFL
        allowance takes ~sqrt(2) x the substeps, and the base simulated there is not the fitted model (on
        the tests' tiny bar 15 substeps against the fit's 10: 0.1-2.9 mm apart, a systematic residual the
        fit never saw; docs/diagnose.md). The rollouts built so far are dropped."""
        self.substeps_unmatched = int(self.substeps)
        self.viscous_cfl_modulus = 0.0
        self._rollouts.clear()
        self._batch_rollouts.clear()
        self._twins.clear()
        self._probe_twins.clear()
        self._use_bound(self.e_bound)

    def bound_for(self, e_max: float) -> float:
        """The stiffness the substep is taken at for a field whose largest E is `e_max`: the
        smallest rung of a ladder of ratio sqrt(2) below the stage's E range's top that is >= e_max
        (`sim.cfl.rung`; so a field may stiffen ~40% before the model is rebuilt, and rollouts are reused per rung)."""
        return rung(e_max, float(self.scene.settings.youngs_max))

    def _model_at(self, bound: float):
        """The simulator's model with its substep taken at rung `bound` (one of this simulation's rollouts' or
        a probe twin's where one is at that rung: the same model, built once)."""
        if bound in self._rollouts:
            return self._rollouts[bound].model
        for (b, _), ro in self._probe_twins.items():
            if b == bound:
                return ro.model
        st = self.scene.settings
        return SimModel.create(
            self.x0, self.scene.particles_volumes, st.density,
            np.minimum(self.scene.youngs_modulus.clip(st.youngs_min, st.youngs_max), bound),
            self.scene.poisson_ratio.clip(1e-3, st.poisson_max), material=st.constitutive_model, grid=self.grid,
            fps=self.scene.fps, substeps=None if self.adaptive else st.substeps, E_max=bound, nu_max=st.poisson_max,
            E_v_max=self.viscous_cfl_modulus, cfl=CFL,
            max_speed=self.control.max_speed(self.scene.fps) if self.adaptive else 0.0, gravity=st.gravity,
            effects=self.effects, dtype=self.dtype, device=self.device,
            # the contacts' partial blends keep the rate they have at the stage's substep
            blend_dt=1.0 / (self.scene.fps * st.substeps) if self.adaptive else 0.0,
            pin_gain=PIN_RULE[0], pin_floor=PIN_RULE[1], support_rule=SUPPORT_RULE, transfer_tau=st.transfer_tau,
            ground_contact=GROUND_CONTACT)

    def _use_bound(self, bound: float) -> None:
        if bound not in self._rollouts:
            model = self._model_at(bound)
            if len(self._rollouts) >= 3:     # keep a few rungs' buffers and graphs
                self._twins.pop(next(iter(self._rollouts)), None)
                self._rollouts.pop(next(iter(self._rollouts)))
            self._rollouts[bound] = Rollout(model, self.control)
        for b, r in self._rollouts.items():   # only the rung in use keeps its substep states (memory)
            if b != bound:
                r.drop_states()
        self.e_bound = bound
        self.rollout = self._rollouts[bound]
        self.model = self.rollout.model

    def ensure_stable(self, e_max: float) -> bool:
        """Make the model's substep stable for a field whose largest E is `e_max` (the CFL bound at
        the field, not at the top of the allowed range: a soft object takes far fewer substeps).
        Returns True when the rung changed. Without `adaptive_substeps`, the stage's substep (taken
        at the range's top) is kept."""
        if not self.adaptive:
            return False
        want = self.bound_for(e_max)
        # hysteresis: step down a rung only when the field is well inside the lower one
        if want < self.e_bound and e_max * 1.1 > want:
            want = self.e_bound
        if want == self.e_bound:
            return False
        self._use_bound(want)
        return True

    @property
    def substeps(self) -> int:
        return self.model.substeps

    def initial_trajectories(self) -> list[torch.Tensor]:
        return [tr.clone() for _, tr in self.traj_slots]

    def slot_names(self) -> list[str]:
        return [self.contacts[i].name for i, _ in self.traj_slots]

    def held_particles(self) -> np.ndarray:
        """(P,) True for particles a fixed support holds from the first frame (the video cannot see
        their material)."""
        held = np.zeros(len(self.x0), bool)
        for c in self.contacts:
            if c.type == "fixed" and c.grasp_frame <= 0:
                held[np.asarray(c.indices, np.int64)] = True
        return held

    def use_preload(self, on: bool, share_from: "Simulation | None" = None) -> None:
        """Start every forward from the scan's preload (`on`) or stress-free. The stress is solved once, on first use
        (or taken from `share_from` where that simulation solved it for the same scene, grid and holds), and kept for
        a later switch back. Raises ValueError where nothing holds the object at frame 0 (no support, no ground)."""
        if not on:
            self.prestress = None
            return
        if self._solved_prestress is None:
            if share_from is not None and share_from._solved_prestress is not None \
                    and share_from._holds == self._holds:
                self._solved_prestress = share_from._solved_prestress
            else:
                from .sim.preload import equilibrium_stress

                self._solved_prestress = equilibrium_stress(self.model, self.control)
        self.prestress = self._solved_prestress

    def _holding_key(self) -> tuple:
        """What the preload's stress depends on besides the material's nu: the scene, the grid, the supports held from
        frame 0 and the ground."""
        held = tuple(sorted(tuple(np.sort(np.asarray(c.indices)).tolist()) for c in self.control.contacts
                            if c.type == "fixed" and c.active_mask(self.control.n_frames)[0]))
        ground = tuple(sorted(self.model.effects.params.get("ground", {}).items()))
        return id(self.scene), self.grid, held, ground

    def forward_twin(self, contacts=None, scene: SceneData | None = None) -> "Simulation":
        """A simulation like this one (effects, device, dtype, frames) under other `contacts` or another
        `scene`, for one-off forward passes (probes, counterfactuals): its frame graphs off, since
        capturing them would cost another forward."""
        sim = Simulation(self.scene if scene is None else scene, self.contacts if contacts is None else contacts,
                         self.T, effects=self.effects, device=self.device, dtype=self.dtype,
                         adaptive_substeps=self.adaptive, prestress_from=self)
        for ro in sim._rollouts.values():
            ro.graphs = False
        return sim

    def simulate(self, E, nu, trajectories=None, effects=None):
        """x (T, P, 3), F (T, P, 3, 3) for E, nu (P,) and optionally the slots' trajectories and
        the effects' parameters (tensors: differentiable)."""
        E, trajs = self._inputs(E, trajectories)
        return self.forward_on(self.rollout, E.to(self.tdtype), nu.to(self.tdtype), effects=effects,
                               trajectories=trajs)

    def forward_on(self, ro: Rollout, E, nu, **kw):
        """`ro(E, nu, **kw)` (one of this simulation's rollouts) from the scan's preload where the stage asks for it,
        F measured from the scan (`_from_scan`)."""
        F0 = self.preload_F(E, nu)
        return self._from_scan(*ro(E, nu, F0=F0, **kw), F0)

    def preload_F(self, E, nu):
        """Frame 0's deformation gradient (P, 3, 3) at E, nu (differentiable): the scan's preload's stretch
        (`sim.preload`) where the stage asks for it, else None (the identity: the scan stress-free)."""
        if self.prestress is None:
            return None
        from .sim.preload import preload_F
        E = torch.as_tensor(E).to(device=self.tdev, dtype=self.tdtype)
        nu = torch.as_tensor(nu).to(device=self.tdev, dtype=self.tdtype)
        return preload_F(self.prestress, E, nu, self.scene.settings.constitutive_model)

    @staticmethod
    def _from_scan(x, F, F0):
        """(x, F) with F the deformation from the scan (F F0^-1: what the splats, drawn on the scan, deform by)."""
        if F0 is None:
            return x, F
        return x, F @ torch.linalg.inv(F0).to(F.dtype)

    def _inputs(self, E, trajectories):
        """E as a tensor (the adaptive substep moved to its stable rung) and the slots' trajectories by slot."""
        trajs = None
        if trajectories is not None:
            trajs = {slot: tr for (slot, _), tr in zip(self.traj_slots, trajectories)}
        E = torch.as_tensor(E)
        if self.adaptive:
            self.ensure_stable(float(E.detach().max()))
        return E, trajs

    def simulate_from(self, start: int, states: dict, E, nu, trajectories=None, effects=None):
        """`simulate` without gradients, frames 0 .. `start` taken from `states` (`rollout.checkpoints()`
        after a forward of a simulation whose model and inputs are this one's and whose contacts agree
        with these before frame `start`: a grasp or release frame moved to >= start; `Rollout.
        forward_from`). The caller checks that the model is the same (`substeps`, `grid`, rung)."""
        E, trajs = self._inputs(E, trajectories)
        E, nu = E.to(self.tdtype), nu.to(self.tdtype)
        with torch.no_grad():
            F0 = self.preload_F(E, nu)
            return self._from_scan(*self.rollout.forward_from(start, states, E, nu, effects=effects,
                                                              trajectories=trajs, F0=F0), F0)

    def rung_wanted(self, e_max: float, current: float | None = None) -> float:
        """The rung `ensure_stable(e_max)` would move to (the current one when it would not move); from rung
        `current` instead of the one in use where given (the rung after a sequence of probes)."""
        cur = self.e_bound if current is None else float(current)
        if not self.adaptive:
            return cur
        want = self.bound_for(e_max)
        if want < cur and e_max * 1.1 > want:
            want = cur
        return want

    def twin_at(self, bound: float, slot: int = 0) -> Rollout:
        """An eager rollout (no graph capture: safe beside another thread's launches) at rung `bound`, for
        `forward_at`, one per `slot` (one per thread: two threads never share a twin); built here, in the
        calling thread, before any worker uses it. The three most recent kept (`drop_probe_twins` frees them)."""
        key = (bound, int(slot))
        ro = self._probe_twins.pop(key, None)      # (re-inserted: the most recent)
        if ro is not None:
            self._probe_twins[key] = ro
        else:
            ro = Rollout(self._model_at(bound), self.control, graphs=False)
            while len(self._probe_twins) >= 3:
                self._probe_twins.pop(next(iter(self._probe_twins)))
            self._probe_twins[key] = ro
        return ro

    def drop_probe_twins(self) -> None:
        self._probe_twins.clear()

    def forward_at(self, bound: float, E, nu, trajectories=None, effects=None, slot: int = 0):
        """x, F of `simulate(E, nu, ...)` without gradients on the eager twin at rung `bound` and `slot`
        (`twin_at`, built first), this simulation's own rung and rollouts untouched: callable from a worker
        thread while the calling thread simulates on another slot. Bitwise `simulate`'s where `bound` is the
        rung it would take (`rung_wanted`; tests/test_sim_threads.py)."""
        ro = self._probe_twins[(bound, int(slot))]
        trajs = None
        if trajectories is not None:
            trajs = {slot_: tr for (slot_, _), tr in zip(self.traj_slots, trajectories)}
        with torch.no_grad():
            return self.forward_on(ro, torch.as_tensor(E).detach().to(self.tdtype),
                                   torch.as_tensor(nu).detach().to(self.tdtype), effects=effects, trajectories=trajs)

    def simulate_each(self, jobs: list, threads: int | None = None) -> list:
        """Independent simulations without gradients at the current rung: `jobs` a list of (E, nu,
        trajectories, effects) as `simulate` takes them, each at an E for which `rung_wanted` is the
        current rung (checked: ValueError). Returns, in order, (x, F) or the SimulationError a job
        raised. On `threads` (default `sim_threads()`) threads: the calling one on this rollout where its
        forward graphs are captured (else on an eager twin: no capture while other threads launch), the
        others on eager twins of it (own buffers). Bitwise what `simulate` gives, one job after another
        (tests/test_sim_threads.py)."""
        from .errors import SimulationError

        for E, *_ in jobs:
            if self.rung_wanted(float(torch.as_tensor(E).detach().max())) != self.e_bound:
                raise ValueError("simulate_each: a job's E needs another rung than the current one")
        if threads is None:
            threads = sim_threads(self.device) if len(jobs) > 1 else 1
        out: list = [None] * len(jobs)
        lock = threading.Lock()
        todo = iter(range(len(jobs)))

        def take():
            with lock:
                return next(todo, None)

        def run(ro, i):
            E, nu, tr, eff = jobs[i]
            trajs = None if tr is None else {slot: t for (slot, _), t in zip(self.traj_slots, tr)}
            with torch.no_grad():
                try:
                    out[i] = self.forward_on(ro, torch.as_tensor(E).detach().to(self.tdtype),
                                             torch.as_tensor(nu).detach().to(self.tdtype), effects=eff,
                                             trajectories=trajs)
                except SimulationError as e:
                    out[i] = e

        ro = self.rollout
        workers: list = []
        failed: list = []

        def work(twin):
            try:
                while (i := take()) is not None:
                    run(twin, i)
            except BaseException as e:  # noqa: BLE001  (re-raised in the calling thread)
                failed.append(e)

        def captured() -> bool:    # no capture of the calling thread's rollout can start while workers run
            if not ro.graphs:
                return True
            if ro.frame_graphs:
                return "forward" in ro._fwd_graphs
            return len(ro._fwd_graphs) == ro.T

        def start(own: bool = False):
            """The workers on their twins (and with `own` one more twin, returned, for the calling thread)."""
            twins = self._twins.setdefault(self.e_bound, [])
            while len(twins) < threads - 1 + own:
                twins.append(Rollout(self.model, self.control, graphs=False))
            for twin in twins[:threads - 1]:
                t = threading.Thread(target=work, args=(twin,), daemon=True)
                t.start()
                workers.append(t)
            return twins[threads - 1] if own else None

        try:
            if threads > 1 and len(jobs) > 1:
                if captured():          # the calling thread replays its graphs beside the others from the start
                    start()
                else:
                    # its graphs not captured yet: none captured here (a capture records every thread's launches,
                    # and costs ~2 eager forwards: on the demo 2.7 s against 1.6 s eager, 1.2 s a replay): the
                    # calling thread on an eager twin too, beside the others from the start
                    ro = start(own=True)
            while (i := take()) is not None:
                run(ro, i)
        finally:
            for t in workers:
                t.join()
        if failed:
            raise failed[0]
        return out

    def simulate_batch(self, E, nu, trajectories=None, effects=None, copies_per_rollout: int | None = None):
        """B rollouts in few: copies of the scene side by side on one grid (`sim.batch`), each with
        its own E, nu (B, P) (nu may be (P,)), sharing the trajectories and effects. Returns x (B,
        T, P, 3), F (B, T, P, 3, 3) and `escaped` (B,) bool: copies that went unstable or left their
        own box (their x is not to be trusted). `trajectories`: one tensor per slot, (T, 3) shared by
        the copies or (B, T, 3) one per copy. The substep is the one for the largest E of all
        copies. `copies_per_rollout` caps the copies per rollout (default: as many as fit, <= 16)."""
        from .errors import SimulationError
        from .sim.batch import max_copies, tile

        E = torch.as_tensor(E).to(device=self.tdev, dtype=self.tdtype)
        if E.dim() != 2 or E.shape[1] != len(self.x0):
            raise ValueError(f"E must be (copies, {len(self.x0)}), got {tuple(E.shape)}")
        B = E.shape[0]
        nu = torch.as_tensor(nu).to(device=self.tdev, dtype=self.tdtype)
        nu = nu.expand(B, len(self.x0)) if nu.dim() == 1 else nu
        if self.adaptive:
            self.ensure_stable(float(E.detach().max()))
        cap = min(max_copies(self.control), copies_per_rollout or 16)
        xs, Fs, bad = [], [], []
        for start in range(0, B, cap):
            n = min(cap, B - start)
            # per-copy trajectories ((B, T, 3) per slot) are cut to this rollout's copies
            part = None if trajectories is None else \
                [tr[start:start + n] if torch.as_tensor(tr).dim() == 3 else tr for tr in trajectories]
            trajs = None if part is None else {slot: tr for (slot, _), tr in zip(self.traj_slots, part)}
            key = (self.e_bound, n)
            if key not in self._batch_rollouts:
                tl = tile(self.model, self.control, n)
                if len(self._batch_rollouts) >= 2:
                    self._batch_rollouts.pop(next(iter(self._batch_rollouts)))
                self._batch_rollouts[key] = (tl, Rollout(tl.model, tl.control))
            tl, ro = self._batch_rollouts[key]
            F0 = None
            if self.prestress is not None:     # each copy's own preload, copy after copy as the tiled particles are
                F0 = torch.cat([self.preload_F(E[b], nu[b]) for b in range(start, start + n)])
            try:
                x, F = ro(tl.stack(E[start:start + n]), tl.stack(nu[start:start + n]), effects=effects,
                          trajectories=tl.trajectories(trajs, like=E), F0=F0)
                x, F = self._from_scan(x, F, F0)
            except SimulationError:
                if n == 1:
                    x = torch.full((self.T, len(self.x0), 3), float("nan"), dtype=self.tdtype, device=self.tdev)
                    xs.append(x[None])
                    Fs.append(torch.full((1, self.T, len(self.x0), 3, 3), float("nan"), dtype=self.tdtype,
                                         device=self.tdev))
                    bad.append(np.ones(1, bool))
                    continue
                # one copy failed the whole rollout: find which, one at a time
                out = self.simulate_batch(E[start:start + n], nu[start:start + n], part, effects,
                                          copies_per_rollout=1)
                xs.append(out[0])
                Fs.append(out[1])
                bad.append(out[2])
                continue
            xb, Fb = tl.split(x), tl.split(F)
            xs.append(xb)
            Fs.append(Fb)
            bad.append(tl.escaped(xb.detach()))
        return torch.cat(xs), torch.cat(Fs), np.concatenate(bad)

    def gaussians_at(self, x_k, F_k):
        """(means (N, 3), covariances (N, 3, 3)) of the splats for particle state x_k, F_k."""
        return self.binding.apply(x_k, F_k, self.cov0)


def build_simulation(scene: SceneData, contacts: list[ContactSet], n_frames: int | None = None, **kw) -> Simulation:
    """`Simulation(scene, contacts, n_frames or scene.n_frames, effects=, device=, dtype=, knn=)`."""
    return Simulation(scene, contacts, scene.n_frames if n_frames is None else n_frames, **kw)


def warm_kernels(device="cpu", dtype: str = "float32") -> list[str]:
    """Compile the Warp modules a fit on ``device`` launches (the simulator's substep and hand-written
    adjoints, the renderer; on CUDA also the fused transfers and the per-frame graph kernels) into Warp's
    kernel cache and return their names: what `scripts/setup.sh` runs once after an install, so that the
    first fit on a fresh machine loads them instead of compiling them (~20 s of CPU on the demo,
    docs/benchmarks/cpu.md; on a fresh H200 the first fit's clock was 59.8 s against 10.7 s once
    compiled, docs/benchmarks/gpu.md; #26). Two at a time on the CPU (a 2-core box), all at once on CUDA
    (the compiler's calls release the GIL). The cache is keyed by the kernels' source and options: a
    changed kernel compiles again at its first launch."""
    import os

    import warp as wp

    from .devices import quiet_warp_init
    from .render.rasterizer import kernels as render_kernels
    from .sim.kernels import get_kernels

    quiet_warp_init(device)
    K = get_kernels(dtype)
    R = render_kernels(wp.float32 if dtype == "float32" else wp.float64)
    names = [K.modules.core, K.modules.adj, R.module]
    if not str(device).startswith("cuda"):
        # (the two lanes' small module, sim/lanes.py, is opt-in: compiled at its first use, not here)
        wp.force_load(device=device, modules=[wp.get_module(n) for n in names], max_workers=2)
        return names
    from .sim.frame_graphs import get_frame_kernels
    from .sim.solver import launch_block_dim

    get_frame_kernels(dtype)
    sim = [K.modules.core, K.modules.adj, K.modules.cuda, f"physinteract_framegraph_{dtype}"]
    # every launch of the simulator's modules runs launch_block_dim's threads a block, and each block size is its own
    # variant of a module: compiled at Warp's default (256) they were of no use to the fit (a fresh H200, 2026-11-29:
    # the first fit after such a warm-up still took 38-39 s of fit clock against 10 s); the renderer at the default
    workers = max(1, min(len(sim) + 1, os.cpu_count() or 1))
    wp.force_load(device=device, modules=[wp.get_module(n) for n in sim], block_dim=launch_block_dim(device),
                  max_workers=workers)
    wp.force_load(device=device, modules=[wp.get_module(R.module)], max_workers=1)
    return sim + [R.module]
