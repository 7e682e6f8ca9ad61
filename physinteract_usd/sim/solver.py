"""MPMSolver: one MLS-MPM substep (forward) and its adjoint (reverse), plus the per-frame check.

The forward substep is p2g_stress -> p2g_scatter -> grid_update -> g2p_gather -> g2p_update
(on CUDA fused into p2g_fused -> grid_update -> g2p_fused, `FUSED_KERNELS`; the same arithmetic)
(kernels.py). The adjoint of a substep first recomputes that substep's grid from the stored particle
state (so no grid is kept per substep), then runs the reverse kernels in reverse order: Warp's
generated adjoints for the per-particle / per-node physics (stress, update, grid update) and
hand-written adjoints for the two transfers (p2g_scatter_adj, g2p_gather_adj), which are gathers
of the grid adjoints and much cheaper than the generated ones. Grid arrays are reused: nothing
is allocated per substep.

Zeroing: with ``fused_zero`` (the default on CUDA devices, see `FUSED_ZERO`) a forward substep
clears its four grid arrays in one kernel over the nodes (kernels.zero_grid), and a backward
substep clears those four and the five grid adjoints in one kernel over the nodes (zero_grid_adj)
and its particle-side adjoint buffers (plus, when asked, the adjoint of its input state) in one
kernel over the particles (zero_particle_adj): 3 launches where there were 21 memsets (each one
a node of the captured graph).
``fused_zero=False`` keeps the memsets (``array.zero_()``): the CPU's default, where a memset is
faster than a Warp loop over the nodes and there is no launch latency to save (fused: +2-5% CPU
time per substep, docs/benchmarks/gpu.md). Results are bitwise the same either way.

Substep tapes (`new_tape`, the `save` argument of `step` / `step_adjoint`): a forward substep given a
`SubstepSave` computes its grid and its gathered / affine particle buffers into it instead of the
solver's own arrays, and an adjoint given the same save reads them from there instead of recomputing
them (no p2g_stress, p2g_scatter, grid_update forward or g2p_gather in the backward: ~30% of a CPU
backward substep, docs/benchmarks/cpu.md). Bitwise the same gradients (the same kernels on the same
inputs; tests/test_sim_tape.py); the rollout decides which frames keep one (sim/rollout.py `TAPE_GRID`).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from types import SimpleNamespace

import numpy as np
import warp as wp

from ..errors import SimulationError
from .control import Control, ControlArrays
from .effects import N_PARAMS
from .kernels import F_GROUND, F_GROUND_PENALTY, F_VISCO, GROUND_BETA, GROUND_K, N_STATUS, SCATTERED, get_kernels
from .state import SimState

# how new solvers clear their grid / adjoint buffers: True fused kernels, False memsets, None (default)
# fused on CUDA devices and memsets on the CPU
FUSED_ZERO: bool | None = None
# whether new solvers launch the fused transfer kernels (kernels.p2g_fused: stress + scatter; g2p_fused:
# gather + particle update, forward only): 4 launches per forward substep instead of 6 (with fused
# zeroing), one fewer per backward substep; bitwise the same results (tests/test_fused_kernels.py).
# None (default): fused on CUDA devices (launch-bound graphs), separate on the CPU (its graphs replay
# without launch overhead, and the fused forward measured +4-6% CPU time there); True / False force it
FUSED_KERNELS: bool | None = None
# whether new solvers run their grid kernels (clear, grid update, their adjoints) over a box of nodes
# bounded to the object (`MPMSolver.set_box`; the box a rollout picks is rollout.Rollout's) instead of
# the whole grid: True / False force it, None (default) on CUDA devices only (where a 100^3 grid's
# clear and scan are ~30% of a 15k substep); bitwise the same results (tests/test_grid_box.py)
GRID_BOX: bool | None = None
# threads per block of the solver's launches on CUDA devices (every substep kernel, forward and adjoint). A small
# fit's particle kernels run on ceil(P / block) blocks (the demo's 1,769 particles: 7 blocks of 256 on an H200's 132
# SMs), each thread's work a long serial chain: fewer threads per block spread them over more SMs. Default 64 on CUDA
# since session 17 (#26, H200, benchmarks/gpu_iter26.py --block-dims and gpu_cli26.sh, docs/benchmarks/gpu.md): the
# CLI small fit's iteration 0.260 -> 0.184 s (32: 0.182 s), the CLI fit 20.0-20.8 -> 15.5-16.6 s; hemp_rope at paper
# size (21k particles) unchanged (55 s of fit clock both, MA 0.821 both). Each value is its own variant of the
# kernels' modules (compiled and loaded on first use). The CPU ignores it (256). The results are the same up to the
# order of the float atomics, which CUDA never fixed. PHYSINTERACT_SIM_BLOCK_DIM=N in the environment sets it for a
# process (256: Warp's default, the code before)
BLOCK_DIM: int | None = int(os.environ["PHYSINTERACT_SIM_BLOCK_DIM"]) if os.environ.get("PHYSINTERACT_SIM_BLOCK_DIM") \
    else 64


def launch_block_dim(device) -> int:
    """Threads per block of every launch of the simulator's modules on ``device`` (BLOCK_DIM on CUDA, Warp's
    default 256 elsewhere). One value for all of them: each block size is its own compiled variant of a module, and
    the set-up's CUDA warm-up (`simulation.warm_kernels`) compiles this one (a launch at another size compiled the
    whole module again in a fresh machine's first fit, 14.5 s on an H200, 2026-11-29)."""
    return int(BLOCK_DIM) if (BLOCK_DIM and wp.get_device(device).is_cuda) else 256


class SimParams:
    """The differentiable inputs of the kernels: per-particle E, nu and the effect parameter vector."""

    def __init__(self, model, E=None, nu=None, effect_vector=None, requires_grad: bool = False):
        K = get_kernels(model.dtype)
        nd = model.np_dtype
        d = model.device
        P = model.n_particles
        E = model.E if E is None else np.broadcast_to(np.asarray(E, dtype=np.float64), (P,))
        nu = model.nu if nu is None else np.broadcast_to(np.asarray(nu, dtype=np.float64), (P,))
        ev = model.effect_vector() if effect_vector is None else effect_vector
        self.E = wp.array(np.ascontiguousarray(E, dtype=nd), dtype=K.T, device=d, requires_grad=requires_grad)
        self.nu = wp.array(np.ascontiguousarray(nu, dtype=nd), dtype=K.T, device=d, requires_grad=requires_grad)
        self.eff = wp.array(np.asarray(ev, dtype=nd).reshape(N_PARAMS), dtype=K.T, device=d,
                            requires_grad=requires_grad)

    @classmethod
    def zeros_like(cls, other: "SimParams") -> "SimParams":
        p = cls.__new__(cls)
        p.E = wp.zeros_like(other.E)
        p.nu = wp.zeros_like(other.nu)
        p.eff = wp.zeros_like(other.eff)
        return p

    def zero_(self):
        self.E.zero_()
        self.nu.zero_()
        self.eff.zero_()


class ControlAdjoint:
    """Adjoint arrays of a ControlArrays' trajectories."""

    def __init__(self, ctrl: ControlArrays):
        self.pin_pos = wp.zeros_like(ctrl.pin_pos)
        self.col_pos = wp.zeros_like(ctrl.col_pos)

    def zero_(self):
        self.pin_pos.zero_()
        self.col_pos.zero_()


class MPMSolver:
    """Steps a SimModel. ``step(s_in, s_out, frame, substep)`` advances one substep of frame ``frame``."""

    def __init__(self, model, control: Control | ControlArrays | None = None, params: SimParams | None = None):
        self.model = model
        self.K = get_kernels(model.dtype)
        K = self.K
        g = model.grid
        d = model.device
        self.device = d
        # threads per block of every launch (BLOCK_DIM on CUDA; Warp's default 256 otherwise: the same kernels)
        self.block_dim = launch_block_dim(d)
        self.res = tuple(g.resolution)
        self.lo = K.vec3(*g.lower)
        self.inv_dx = 1.0 / g.dx
        self.dx = g.dx
        self.dt = model.dt
        self.fps = model.fps
        self.S = model.substeps
        self.flags = model.effects.flags
        if getattr(model, "ground_contact", "nodes") == "penalty" and self.flags & F_GROUND:
            self.flags |= F_GROUND_PENALTY      # the ground at the particles (kernels.ground_impulse), not the nodes
        self.material = model.material_id
        self.gravity = K.vec3(*model.gravity)
        self.band = model.contact_band
        self.pin_gain = model.pin_gain
        self.pin_floor = model.pin_floor
        # a support's pin rule (a fixed contact's; grasps: pin_gain, pin_floor)
        self.sup_gain, self.sup_floor = model.support_rule
        # the pins' and colliders' partial blends are rates per `model.blend_dt` (0: per substep)
        self.blend_r = float(self.dt / model.blend_dt) if model.blend_dt > 0 else 1.0
        self.m_eps = float(1e-9 * np.min(model.mass))  # grid nodes lighter than this are empty
        self.res3 = wp.vec3i(*self.res)
        if control is None:
            control = Control([], n_frames=1)
        self.ctrl = control if isinstance(control, ControlArrays) else ControlArrays(model, control)
        self.params = params if params is not None else SimParams(model)
        self.dev = model.device_arrays()
        self.gm = wp.zeros(self.res, dtype=K.T, device=d)
        self.gmv = wp.zeros(self.res, dtype=K.vec3, device=d)
        self.gpm = wp.zeros(self.res, dtype=K.T, device=d)
        self.gpmv = wp.zeros(self.res, dtype=K.vec3, device=d)
        self.gsm = wp.zeros(self.res, dtype=K.T, device=d)
        self.gv = wp.zeros(self.res, dtype=K.vec3, device=d)
        P = model.n_particles
        self.A = wp.zeros(P, dtype=K.mat33, device=d)     # affine matrices (stress + APIC)
        self.vg = wp.zeros(P, dtype=K.vec3, device=d)     # gathered grid velocity
        self.Cg = wp.zeros(P, dtype=K.mat33, device=d)    # gathered velocity gradient
        n_nodes = int(np.prod(self.res))
        self.n_nodes = n_nodes
        # the grid box: nodes box_lo .. box_hi - 1 per axis, device-side (box[0] = lower, box[1] =
        # extent) so that captured graphs stay valid when it changes; with the box on every p2g counts the particles
        # whose stencil leaves it into box_flag[0] (the caller checks and redoes the pass on the full grid)
        self.contig = 1 if wp.get_device(d).is_cpu else 0      # CPU: runs of consecutive nodes (kernels.box_span)
        # nodes per thread of the grid kernels over the whole grid, and of the box's on the CPU (the CPU
        # pays per thread, most in the generated adjoints; one node per thread on a GPU)
        self.chunk = 64 if wp.get_device(d).is_cpu else 1
        self.box = wp.array(np.array([[0, 0, 0], list(self.res)], dtype=np.int32), dtype=wp.vec3i, device=d)
        self.box_flag = wp.zeros(1, dtype=wp.int32, device=d)
        # per particle: how far past the grid's valid box its stencil was clamped at this frame's substeps (kernels.
        # mark_clamped, written by p2g; counted into the status row and cleared by the frame's check)
        self.clamped = wp.zeros(model.n_particles, dtype=wp.int32, device=d)
        self.box_lo = (0, 0, 0)
        self.box_hi = tuple(self.res)
        self._flat = {k: getattr(self, k).flatten() for k in SCATTERED + ("gv",)}
        self._adj_grid = None
        self._adj_flat = None
        # read when launching: set it before a rollout captures its graphs
        self.fused_zero = wp.get_device(d).is_cuda if FUSED_ZERO is None else bool(FUSED_ZERO)
        self.fused_kernels = wp.get_device(d).is_cuda if FUSED_KERNELS is None else bool(FUSED_KERNELS)
        self.grid_box = wp.get_device(d).is_cuda if GRID_BOX is None else bool(GRID_BOX)
        # the rate transfer (SimModel.transfer_tau > 0): f = exp(-dt / tau) and the grid's pre-force momentum /
        # velocity and its gather at the particles (recomputed in the adjoint from the substep's input state and
        # its grid mass, also from a tape's: tapes do not keep them); 0: APIC, none of it launched
        tau_t = float(getattr(model, "transfer_tau", 0.0) or 0.0)
        self.rate_f = float(np.exp(-self.dt / tau_t)) if tau_t > 0 else 0.0
        if self.rate_f > 0 and self.flags & F_GROUND_PENALTY:
            raise ValueError("the rate transfer (transfer_tau > 0) and the particles' ground (ground_contact='penalty') "
                             "do not go together: take one")
        # the particles' ground (F_GROUND_PENALTY): the velocity p2g scatters (each particle's own plus the ground's
        # push and friction, kernels.ground_impulse) and its adjoint; None: p2g scatters the state's velocity
        self.vgr = wp.zeros(P, dtype=K.vec3, device=d) if self.flags & F_GROUND_PENALTY else None
        self.ground_k = GROUND_K * float(np.linalg.norm(model.gravity) or 9.81)   # kernels.GROUND_K, in g
        self._a_vgr = wp.zeros(P, dtype=K.vec3, device=d) if self.flags & F_GROUND_PENALTY else None
        if self.rate_f > 0:
            self.gmo = wp.zeros(self.res, dtype=K.vec3, device=d)
            self.gvo = wp.zeros(self.res, dtype=K.vec3, device=d)
            self.vgo = wp.zeros(P, dtype=K.vec3, device=d)
            self.Cgo = wp.zeros(P, dtype=K.mat33, device=d)    # gathered, not used
            # their adjoints (allocated here, not in a graph capture)
            self._rate_adj = dict(gmo=wp.zeros(self.res, dtype=K.vec3, device=d),
                                  gvo=wp.zeros(self.res, dtype=K.vec3, device=d),
                                  vgo=wp.zeros(P, dtype=K.vec3, device=d), Cgo=wp.zeros(P, dtype=K.mat33, device=d))
            self._rate_flat = dict(gmo=self.gmo.flatten(), gvo=self.gvo.flatten(),
                                   a_gmo=self._rate_adj["gmo"].flatten(), a_gvo=self._rate_adj["gvo"].flatten())
        # the solver's own buffers (`_using` swaps a tape's in): a taped adjoint's scratch outputs
        self._own = {k: getattr(self, k) for k in self._TAPED + ("_flat",)}
        # the second lane (sim/lanes.py: set by a rollout that replays its frames on two lanes) and, while a
        # frame is captured on two lanes, its recorder (the substeps then issue lane A's launches and keep lane B's)
        self.lanes = None
        self._rec = None

    # ------------------------------------------------------------------ the grid box
    @property
    def box_volume(self) -> int:
        return int(np.prod(np.subtract(self.box_hi, self.box_lo)))

    @property
    def n_grid_threads(self) -> int:
        """Threads of a launch of the grid kernels (read at launch / capture; any count covers the grid
        or the box): the box's nodes on a GPU with the box on, else the whole grid in runs of `chunk`."""
        if self.grid_box and not self.contig:
            return self.box_volume
        return (self.n_nodes + self.chunk - 1) // self.chunk

    @property
    def grid_kernel(self):
        """The grid update: over the box (kernels.grid_update_box) or, with the box off, over the whole
        grid without decoding or testing a box per node (kernels.grid_update); bitwise the same."""
        return self.K.grid_update_box if self.grid_box else self.K.grid_update

    def set_box(self, lo=None, hi=None) -> None:
        """Run the grid kernels over nodes lo .. hi - 1 per axis (clipped to the grid; None: the whole
        grid). Not during a graph capture: it writes a device array the captured kernels read."""
        lo = np.zeros(3, int) if lo is None else np.clip(np.asarray(lo, int), 0, np.asarray(self.res) - 3)
        hi = np.asarray(self.res) if hi is None else np.clip(np.asarray(hi, int), lo + 3, self.res)
        if (tuple(int(v) for v in lo), tuple(int(v) for v in hi)) == (self.box_lo, self.box_hi):
            return
        self.box_lo, self.box_hi = tuple(int(v) for v in lo), tuple(int(v) for v in hi)
        self.box.assign(np.array([self.box_lo, np.subtract(self.box_hi, self.box_lo)], dtype=np.int32))

    def full_box(self) -> bool:
        return self.box_lo == (0, 0, 0) and self.box_hi == self.res

    def clear_all(self) -> None:
        """Zero the whole grid and its adjoint (after a pass whose particles left the box, which
        scattered into nodes outside it that the box's clears do not reach)."""
        for a in self._flat.values():
            a.zero_()
        for a in (self._adj_flat or {}).values():
            a.zero_()

    def _box_args(self):
        return [self.box, self.n_grid_threads, self.contig, self.res3]

    # ------------------------------------------------------------------ substep tapes
    # what a substep computes from its input state that its adjoint reads: the grid (mass, momentum,
    # the pins' mass and momentum, the updated velocity) and the particles' A, vg, Cg
    _TAPED = ("A", "vg", "Cg") + SCATTERED + ("gv",)

    def tape_bytes(self, n_substeps: int) -> int:
        """Bytes of a tape of n_substeps substeps (`new_tape`)."""
        b = 4 if self.model.dtype == "float32" else 8
        return int(n_substeps) * b * (21 * self.model.n_particles + 12 * self.n_nodes)

    def new_tape(self, n_substeps: int) -> list:
        """n_substeps `SubstepSave`s (namespaces of the `_TAPED` arrays and the grid's flat views), rows of
        one array per field."""
        K, d = self.K, self.device
        P = self.model.n_particles
        types = dict(A=(K.mat33, P), vg=(K.vec3, P), Cg=(K.mat33, P), gm=(K.T, self.res), gmv=(K.vec3, self.res),
                     gpm=(K.T, self.res), gpmv=(K.vec3, self.res), gsm=(K.T, self.res), gv=(K.vec3, self.res))
        rows = {k: wp.zeros((n_substeps,) + (shape if isinstance(shape, tuple) else (shape,)), dtype=t, device=d)
                for k, (t, shape) in types.items()}
        out = []
        for s in range(n_substeps):
            sv = SimpleNamespace(**{k: a[s] for k, a in rows.items()})
            sv._flat = {k: getattr(sv, k).flatten() for k in SCATTERED + ("gv",)}
            out.append(sv)
        return out

    @contextmanager
    def _using(self, save):
        """Run the kernels on a save's arrays (None: the solver's own)."""
        if save is None:
            yield
            return
        keep = {k: getattr(self, k) for k in self._TAPED + ("_flat",)}
        for k in self._TAPED + ("_flat",):
            setattr(self, k, getattr(save, k))
        try:
            yield
        finally:
            for k, v in keep.items():
                setattr(self, k, v)

    # ------------------------------------------------------------------ argument lists
    def _stress_args(self, s: SimState, p: SimParams):
        return [s.F, s.Fv, s.C, self.dev["mass"], self.dev["volume"], p.E, p.nu, p.eff, self.flags, self.material,
                self.inv_dx, self.dt]

    def _ground_args(self, s: SimState, p: SimParams, S=None):
        S = S or (lambda a: a)
        return [S(s.x), S(s.v), S(s.C), S(self.dev["volume"]), p.eff, self.flags, self.dt, self.ground_k, GROUND_BETA]

    def _scatter_v(self, s: SimState, p: SimParams):
        """The velocity p2g scatters: the state's, or with the particles' ground its push and friction added
        (kernels.ground_impulse into self.vgr)."""
        if self.vgr is None:
            return s.v
        wp.launch(self.K.ground_impulse, s.x.shape[0], self._ground_args(s, p), [self.vgr], device=self.device,
                  record_tape=False, block_dim=self.block_dim)
        return self.vgr

    def _scatter_args(self, s: SimState, frame: int, c: ControlArrays, v=None):
        return [s.x, s.v if v is None else v, self.A, self.dev["mass"], c.pin_id, c.pin_active, c.pin_pos, c.pin_kind,
                frame, self.fps, self.lo,
                self.inv_dx, self.res3]     # p2g_scatter: + whether the box is on, the box, dt, F (and box_flag, clamped out)

    # where `_grid_args` puts the grid kernel's thread count (the lanes' `_grid_args_lane` rewrites it)
    GRID_NTHR = 28

    def _grid_args(self, frame: int, substep: int, p: SimParams, c: ControlArrays):
        alpha = (substep + 1) / self.S
        f = self._flat
        return [f["gm"], f["gmv"], f["gpm"], f["gpmv"], f["gsm"], p.eff, self.flags, self.gravity, self.dt, self.lo,
                self.dx, self.band, self.pin_gain, self.pin_floor, self.sup_gain, self.sup_floor, c.n_col, c.col_shape,
                c.col_active, c.col_pos, c.col_geom, c.col_radius, c.col_mu, frame, alpha, self.fps, self.res3, self.box,
                self.n_grid_threads, self.contig, self.m_eps, self.blend_r]

    def _update_args(self, s: SimState, frame: int, p: SimParams, c: ControlArrays):
        return [s.x, s.F, s.Fv, self.vg, self.Cg, p.E, p.nu, p.eff, self.flags, c.pin_id, c.pin_active, c.pin_pos,
                frame, self.fps, self.dt]

    @staticmethod
    def _outs(s: SimState):
        return [s.x, s.v, s.C, s.F, s.Fv]

    # ------------------------------------------------------------------ forward
    def grid(self, s: SimState, frame: int, substep: int, params=None, ctrl=None, clear: bool = True,
             gather: bool = True):
        """Stress, p2g and the grid update of substep ``substep`` of frame ``frame`` (fills self.gv),
        then the gather of the grid velocity and its gradient at the particles (self.vg, self.Cg;
        ``gather=False``: not gathered, `step`'s fused update does it). ``clear=False``: the caller
        has already zeroed the grid's scatter targets."""
        K, d = self.K, self.device
        p = params or self.params
        c = ctrl or self.ctrl
        P = s.x.shape[0]
        if clear:
            self._clear_grid()
        v = self._scatter_v(s, p)
        if self.fused_kernels:
            sa = self._stress_args(s, p)     # F, Fv, C, mass, vol, E, nu, eff, flags, material, inv_dx, dt
            wp.launch(K.p2g_fused, P, [sa[0], sa[1], sa[2], sa[4], sa[5], sa[6], sa[7], sa[8], sa[9], sa[11],
                                       s.x, v, self.dev["mass"], c.pin_id, c.pin_active, c.pin_pos, c.pin_kind,
                                       frame, self.fps, self.lo, self.inv_dx, self.res3, int(self.grid_box), self.box],
                      [self.A, self.gm, self.gmv, self.gpm, self.gpmv, self.gsm, self.box_flag, self.clamped], device=d,
                      record_tape=False, block_dim=self.block_dim)
        else:
            wp.launch(K.p2g_stress, P, self._stress_args(s, p), [self.A], device=d, record_tape=False,
                      block_dim=self.block_dim)
            wp.launch(K.p2g_scatter, P, self._scatter_args(s, frame, c, v) + [int(self.grid_box), self.box, self.dt, s.F],
                      [self.gm, self.gmv, self.gpm, self.gpmv, self.gsm, self.box_flag, self.clamped], device=d,
                      record_tape=False,
                      block_dim=self.block_dim)
        wp.launch(self.grid_kernel, self.n_grid_threads, self._grid_args(frame, substep, p, c), [self._flat["gv"]],
                  device=d, record_tape=False, block_dim=self.block_dim)
        if gather:
            wp.launch(K.g2p_gather, P, [s.x, self.gv, self.lo, self.inv_dx, self.res3], [self.vg, self.Cg],
                      device=d, record_tape=False, block_dim=self.block_dim)

    def _clear_grid(self):
        if self.fused_zero or self.grid_box:
            f = self._flat
            wp.launch(self.K.zero_grid, self.n_grid_threads, self._box_args() + [f[k] for k in SCATTERED],
                      device=self.device, record_tape=False, block_dim=self.block_dim)
        else:
            for k in SCATTERED:
                getattr(self, k).zero_()

    def step(self, s_in: SimState, s_out: SimState, frame: int, substep: int, params=None, ctrl=None, save=None):
        """Advance one substep: s_out <- step(s_in). s_in and s_out must be different states. `save`: a
        `SubstepSave` that receives the substep's grid and particle buffers (for `step_adjoint`)."""
        if save is not None:
            with self._using(save):
                return self.step(s_in, s_out, frame, substep, params, ctrl)
        p = params or self.params
        c = ctrl or self.ctrl
        if self._rec is not None:
            return self._step_lanes(s_in, s_out, frame, substep, p, c)
        if self.fused_kernels:
            self.grid(s_in, frame, substep, p, c, gather=False)
            ua = self._update_args(s_in, frame, p, c)    # x, F, Fv, vg, Cg, E, nu, eff, flags, pins, frame, fps, dt
            wp.launch(self.K.g2p_fused, s_in.x.shape[0], [s_in.x, self.gv, self.lo, self.inv_dx, self.res3,
                                                          ua[1], ua[2]] + ua[5:], self._outs(s_out),
                      device=self.device, record_tape=False, block_dim=self.block_dim)
        else:
            self.grid(s_in, frame, substep, p, c)
            wp.launch(self.K.g2p_update, s_in.x.shape[0], self._update_args(s_in, frame, p, c), self._outs(s_out),
                      device=self.device, record_tape=False, block_dim=self.block_dim)
        if self.rate_f > 0:
            self._rate_step(s_in, s_out, frame, c)

    # ------------------------------------------------------------------ rate transfer
    def _rate_old(self, s: SimState):
        """The grid's velocity before the substep's forces (p2g of m v + m C d over the grid's mass, which
        `grid` has scattered) gathered at the particles: self.vgo."""
        K, d = self.K, self.device
        P = s.x.shape[0]
        wp.launch(K.zero_vec3, self.n_nodes, [self._rate_flat["gmo"]], device=d, record_tape=False,
                  block_dim=self.block_dim)
        wp.launch(K.p2g_scatter_old, P, [s.x, s.v, s.C, self.dev["mass"], self.lo, self.inv_dx, self.res3],
                  [self.gmo], device=d, record_tape=False, block_dim=self.block_dim)
        wp.launch(K.grid_old, self.n_nodes, [self._flat["gm"], self._rate_flat["gmo"], self.m_eps],
                  [self._rate_flat["gvo"]], device=d, record_tape=False, block_dim=self.block_dim)
        wp.launch(K.g2p_gather, P, [s.x, self.gvo, self.lo, self.inv_dx, self.res3], [self.vgo, self.Cgo],
                  device=d, record_tape=False, block_dim=self.block_dim)

    def _rate_step(self, s_in: SimState, s_out: SimState, frame: int, c: ControlArrays):
        self._rate_old(s_in)
        wp.launch(self.K.rate_update, s_in.x.shape[0], [s_in.v, self.vgo, c.pin_id, c.pin_active, frame, self.rate_f],
                  [s_out.v], device=self.device, record_tape=False, block_dim=self.block_dim)

    # ------------------------------------------------------------------ adjoint
    def _alloc_adj(self):
        if self._adj_grid is None:
            K, d = self.K, self.device
            P = self.model.n_particles
            self._adj_grid = dict(
                gm=wp.zeros(self.res, dtype=K.T, device=d), gmv=wp.zeros(self.res, dtype=K.vec3, device=d),
                gpm=wp.zeros(self.res, dtype=K.T, device=d), gpmv=wp.zeros(self.res, dtype=K.vec3, device=d),
                gsm=wp.zeros(self.res, dtype=K.T, device=d), gv=wp.zeros(self.res, dtype=K.vec3, device=d))
            self._adj_flat = {k: a.flatten() for k, a in self._adj_grid.items()}
            self._adj_part = dict(A=wp.zeros(P, dtype=K.mat33, device=d), vg=wp.zeros(P, dtype=K.vec3, device=d),
                                  Cg=wp.zeros(P, dtype=K.mat33, device=d))
        return self._adj_grid

    def step_adjoint(self, s_in: SimState, s_out: SimState, adj_in: SimState, adj_out: SimState,
                     frame: int, substep: int, adj_params: SimParams, adj_ctrl: ControlAdjoint,
                     params=None, ctrl=None, clear_adj_in: bool = False, save=None):
        """Reverse one substep: given adj_out (dL/d s_out), ACCUMULATE dL/d s_in into adj_in and the
        parameter / trajectory gradients into adj_params / adj_ctrl. s_out is only written (it may
        hold anything). The substep's grid is recomputed from s_in first, or read from ``save`` (the
        `SubstepSave` its forward `step` filled from this s_in; left as it was). ``clear_adj_in``:
        zero adj_in first (so it receives dL/d s_in itself), in the same launch as the substep's own
        adjoint buffers."""
        if save is not None:
            with self._using(save):
                return self._step_adjoint(s_in, s_out, adj_in, adj_out, frame, substep, adj_params, adj_ctrl,
                                          params, ctrl, clear_adj_in, taped=True)
        return self._step_adjoint(s_in, s_out, adj_in, adj_out, frame, substep, adj_params, adj_ctrl, params, ctrl,
                                  clear_adj_in, taped=False)

    def _zero_particle_adj(self, P: int, adj_in: SimState, clear_adj_in: bool) -> None:
        """Zero the substep's per-particle adjoint buffers (A, vg, Cg), and adj_in with them when asked
        (one launch with fused zeroing)."""
        ap = self._adj_part
        if self.fused_zero:
            wp.launch(self.K.zero_particle_adj, P, [ap["A"], ap["vg"], ap["Cg"], int(clear_adj_in), adj_in.x, adj_in.v,
                                                    adj_in.C, adj_in.F, adj_in.Fv], device=self.device, record_tape=False,
                      block_dim=self.block_dim)
            return
        if clear_adj_in:
            adj_in.zero_()
        for a in ap.values():
            a.zero_()

    def _step_adjoint(self, s_in, s_out, adj_in, adj_out, frame, substep, adj_params, adj_ctrl, params, ctrl,
                      clear_adj_in, taped):
        K, d = self.K, self.device
        p = params or self.params
        c = ctrl or self.ctrl
        if self._rec is not None:
            return self._step_adjoint_lanes(s_in, s_out, adj_in, adj_out, frame, substep, adj_params, adj_ctrl, p, c,
                                            clear_adj_in, taped)
        P = s_in.x.shape[0]
        ag = self._alloc_adj()
        af = self._adj_flat
        ap = self._adj_part
        if taped:
            # the grid and A, vg, Cg are the save's: only the adjoint buffers are cleared
            for a in ag.values():
                a.zero_()
            self._zero_particle_adj(P, adj_in, clear_adj_in)
        elif self.fused_zero or self.grid_box:
            # the scatter targets and the grid adjoints in one launch over the box, then the grid
            f = self._flat
            wp.launch(K.zero_grid_adj, self.n_grid_threads,
                      self._box_args() + [f[k] for k in SCATTERED] + [af[k] for k in SCATTERED + ("gv",)], device=d,
                      record_tape=False, block_dim=self.block_dim)
            self.grid(s_in, frame, substep, p, c, clear=False)
            self._zero_particle_adj(P, adj_in, clear_adj_in)
        else:
            if clear_adj_in:
                adj_in.zero_()
            self.grid(s_in, frame, substep, p, c)
            for a in ag.values():
                a.zero_()
            for a in ap.values():
                a.zero_()
        if self.rate_f > 0:
            # the rate transfer's grid (from s_in and the grid's mass), then its update's adjoint first (it ran last)
            self._rate_old(s_in)
            ra = self._rate_adj
            rf = self._rate_flat
            for a in (rf["a_gmo"], rf["a_gvo"]):
                wp.launch(K.zero_vec3, self.n_nodes, [a], device=d, record_tape=False, block_dim=self.block_dim)
            wp.launch(K.zero_vec3, P, [ra["vgo"]], device=d, record_tape=False, block_dim=self.block_dim)
            wp.launch(K.rate_update_adj, P, [c.pin_id, c.pin_active, frame, self.rate_f, adj_out.v],
                      [adj_in.v, ra["vgo"]], device=d, record_tape=False, block_dim=self.block_dim)
            # gather of the old grid velocity -> adj x, adj old grid velocity (its C part unused: zero adjoint)
            wp.launch(K.g2p_gather_adj, P, [s_in.x, self.gvo, self.lo, self.inv_dx, self.res3, ra["vgo"], ra["Cgo"]],
                      [adj_in.x, ra["gvo"]], device=d, record_tape=False, block_dim=self.block_dim)
            # old velocity = momentum / mass -> adj old momentum, adj grid mass (before p2g_scatter_adj reads it)
            wp.launch(K.grid_old_adj, self.n_nodes, [self._flat["gm"], rf["gmo"], self.m_eps, rf["a_gvo"]],
                      [af["gm"], rf["a_gmo"]], device=d, record_tape=False, block_dim=self.block_dim)
            wp.launch(K.p2g_scatter_old_adj, P, [s_in.x, s_in.v, s_in.C, self.dev["mass"], self.lo, self.inv_dx,
                                                 self.res3, ra["gmo"]],
                      [adj_in.x, adj_in.v, adj_in.C], device=d, record_tape=False, block_dim=self.block_dim)
        # particle update (Warp autodiff): -> adj x, F, Fv, vg, Cg, E, nu, effects, pins
        adj_upd = [adj_in.x, adj_in.F, adj_in.Fv, ap["vg"], ap["Cg"], adj_params.E, adj_params.nu, adj_params.eff, 0,
                   None, None, adj_ctrl.pin_pos, 0, 0.0, 0.0]
        wp.launch(K.g2p_update, P, self._update_args(s_in, frame, p, c), self._outs(s_out), adj_upd,
                  self._outs(adj_out), adjoint=True, device=d, record_tape=False, block_dim=self.block_dim)
        if self.rate_f > 0:
            # the generated adjoint rewrote s_out from its forward (APIC's v): put the rate term back, so that s_out
            # holds what the forward wrote (a rollout's stored states are read again after an adjoint ran over them)
            wp.launch(K.rate_update, P, [s_in.v, self.vgo, c.pin_id, c.pin_active, frame, self.rate_f], [s_out.v],
                      device=d, record_tape=False, block_dim=self.block_dim)
        # gather (hand-written adjoint) -> adj x, adj grid velocity
        wp.launch(K.g2p_gather_adj, P, [s_in.x, self.gv, self.lo, self.inv_dx, self.res3, ap["vg"], ap["Cg"]],
                  [adj_in.x, ag["gv"]], device=d, record_tape=False, block_dim=self.block_dim)
        # grid update (Warp autodiff) -> adj grid mass / momentum, effects, colliders
        adj_grid = [af[k] for k in SCATTERED] + [adj_params.eff, 0, None, 0.0, None, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0,
                                                 None, None, adj_ctrl.col_pos, None, None, None, 0, 0.0, 0.0, None, None,
                                                 0, 0, 0.0, 0.0]
        # (a taped adjoint replays the forward's outputs into scratch: the tape stays as its forward wrote it)
        gv_out = self._own["_flat"]["gv"] if taped else self._flat["gv"]
        wp.launch(self.grid_kernel, self.n_grid_threads, self._grid_args(frame, substep, p, c), [gv_out],
                  adj_grid, [af["gv"]], adjoint=True, device=d, record_tape=False, block_dim=self.block_dim)
        # scatter (hand-written adjoint) -> adj x, v, A, pins; with the particles' ground, adj of the scattered
        # velocity, then the ground's (Warp autodiff; its velocity recomputed from s_in: tapes do not keep it)
        v = self._scatter_v(s_in, p)
        if self.vgr is not None:
            self._a_vgr.zero_()
        wp.launch(K.p2g_scatter_adj, P, self._scatter_args(s_in, frame, c, v) + [ag[k] for k in SCATTERED],
                  [adj_in.x, adj_in.v if self.vgr is None else self._a_vgr, ap["A"], adj_ctrl.pin_pos],
                  device=d, record_tape=False, block_dim=self.block_dim)
        if self.vgr is not None:
            wp.launch(K.ground_impulse, P, self._ground_args(s_in, p), [self.vgr],
                      [adj_in.x, adj_in.v, adj_in.C, None, adj_params.eff, 0, 0.0, 0.0, 0.0], [self._a_vgr], adjoint=True,
                      device=d, record_tape=False, block_dim=self.block_dim)
        # stress: equilibrium branch by hand -> adj F, C, E, nu; Maxwell branch (Warp autodiff) -> adj Fv, nu, E_v
        wp.launch(K.p2g_stress_adj, P, [s_in.F, self.dev["mass"], self.dev["volume"], p.E, p.nu, self.material,
                                        self.inv_dx, self.dt, ap["A"]],
                  [adj_in.F, adj_in.C, adj_params.E, adj_params.nu], device=d, record_tape=False,
                  block_dim=self.block_dim)
        if self.flags & F_VISCO:
            wp.launch(K.p2g_stress_visco, P, [s_in.Fv, self.dev["volume"], p.nu, p.eff, self.inv_dx, self.dt],
                      [self._own["A"] if taped else self.A], [adj_in.Fv, None, adj_params.nu, adj_params.eff, 0.0, 0.0],
                      [ap["A"]], adjoint=True,
                      device=d, record_tape=False, block_dim=self.block_dim)

    # ------------------------------------------------------------------ two lanes (sim/lanes.py)
    def _half(self, lane: int):
        """(particle count, slicer) of lane `lane`: per-particle arrays as views of its range."""
        lo, hi = self.lanes.ranges[lane]
        part = self.lanes.part
        return hi - lo, (lambda a: part(a, lane))

    def _grid_lanes(self, s: SimState, frame: int, substep: int, p, c) -> None:
        """`grid` on two lanes: each lane's p2g of its particles into its own grid | each lane sums the two grids
        and runs the grid update over its own nodes (`_grid_args_lane`) | each lane's gather at its particles."""
        R, L, K = self._rec, self.lanes, self.K
        bd = self.block_dim
        for lane in (0, 1):
            n, S = self._half(lane)
            grid = [getattr(self if lane == 0 else L, k) for k in SCATTERED]
            R.zero(lane, *grid)
            R.launch(lane, K.p2g_stress, n, [S(s.F), S(s.Fv), S(s.C), S(self.dev["mass"]), S(self.dev["volume"]),
                                             S(p.E), S(p.nu), p.eff, self.flags, self.material, self.inv_dx, self.dt],
                     [S(self.A)], block_dim=bd)
            if self.vgr is not None:
                R.launch(lane, K.ground_impulse, n, self._ground_args(s, p, S), [S(self.vgr)], block_dim=bd)
            R.launch(lane, K.p2g_scatter, n, [S(s.x), S(s.v if self.vgr is None else self.vgr), S(self.A), S(self.dev["mass"]), S(c.pin_id), c.pin_active,
                                              c.pin_pos, c.pin_kind, frame, self.fps, self.lo, self.inv_dx, self.res3, 0, self.box,
                                              self.dt, S(s.F)],
                     grid + [self.box_flag if lane == 0 else L.box_flag, S(self.clamped)], block_dim=bd)
        R.barrier()
        f, LK = self._flat, L.LK
        for lane in (0, 1):
            a, b, args = self._grid_args_lane(lane, frame, substep, p, c)
            N = L.nodes
            R.launch(lane, LK.add_grid, b - a, [N(f[k], lane) for k in SCATTERED]
                     + [N(L.flat[k], lane) for k in SCATTERED], block_dim=bd)
            R.launch(lane, self.grid_kernel, args[self.GRID_NTHR], args, [N(f["gv"], lane)], block_dim=bd)
        R.barrier()
        for lane in (0, 1):
            n, S = self._half(lane)
            R.launch(lane, K.g2p_gather, n, [S(s.x), self.gv, self.lo, self.inv_dx, self.res3], [S(self.vg), S(self.Cg)],
                     block_dim=bd)

    def _grid_args_lane(self, lane: int, frame: int, substep: int, p, c):
        """(first node, end node, grid_update's arguments) of lane `lane`'s nodes: a run of whole x slabs, the flat
        grid arrays sliced to it and the grid's corner moved by its first slab (the kernel places a node at
        lo + (i, j, k) dx, and the slab offset is all a slice changes)."""
        a, b = self.lanes.node_ranges[lane]
        args = self._grid_args(frame, substep, p, c)
        assert args[self.GRID_NTHR] == self.n_grid_threads, "GRID_NTHR is not the thread count's place in _grid_args"
        ng = len(SCATTERED)
        for i in range(ng):
            args[i] = self.lanes.nodes(args[i], lane)
        i0 = self.lanes.slab0[lane]
        if i0:
            args[ng + 4] = self.K.vec3(float(self.lo[0]) + i0 * self.dx, float(self.lo[1]), float(self.lo[2]))
        args[self.GRID_NTHR] = max((b - a + self.chunk - 1) // self.chunk, 1)
        return a, b, args

    def _update_args_lane(self, s: SimState, frame: int, p, c, S):
        return [S(s.x), S(s.F), S(s.Fv), S(self.vg), S(self.Cg), S(p.E), S(p.nu), p.eff, self.flags, S(c.pin_id),
                c.pin_active, c.pin_pos, frame, self.fps, self.dt]

    def _step_lanes(self, s_in, s_out, frame, substep, p, c) -> None:
        R = self._rec
        R.enter("step")
        self._grid_lanes(s_in, frame, substep, p, c)
        for lane in (0, 1):
            n, S = self._half(lane)
            R.launch(lane, self.K.g2p_update, n, self._update_args_lane(s_in, frame, p, c, S),
                     [S(a) for a in self._outs(s_out)], block_dim=self.block_dim)

    def _step_adjoint_lanes(self, s_in, s_out, adj_in, adj_out, frame, substep, adj_params, adj_ctrl, p, c,
                            clear_adj_in, taped) -> None:
        """`_step_adjoint` on two lanes (the CPU's choices: memsets, no box, no rate transfer): each lane's
        particle update and gather adjoints over its particles (lane B's grid-velocity, effect and pin adjoints
        into its own buffers) | each lane sums the grid-velocity adjoint and runs the grid update's adjoint over its
        own nodes (lane B's effect / collider adjoints into its own buffers) | each lane's scatter and stress
        adjoints over its particles. Lane B's effect / pin / collider adjoints are folded in at the frame's end
        (`lanes_fold`)."""
        R, L, K = self._rec, self.lanes, self.K
        bd = self.block_dim
        R.enter("adj")
        ag = self._alloc_adj()
        af = self._adj_flat
        ap = self._adj_part
        L.check_adj(adj_params, adj_ctrl)
        if not taped:
            self._grid_lanes(s_in, frame, substep, p, c)
        for lane in (0, 1):
            n, S = self._half(lane)
            if clear_adj_in:
                R.zero(lane, *(S(a) for a in self._outs(adj_in)))
            R.zero(lane, S(ap["A"]), S(ap["vg"]), S(ap["Cg"]), ag["gv"] if lane == 0 else L.a_gv)
            a_eff = adj_params.eff if lane == 0 else L.a_eff
            a_pin = adj_ctrl.pin_pos if lane == 0 else L.a_pin
            adj_upd = [S(adj_in.x), S(adj_in.F), S(adj_in.Fv), S(ap["vg"]), S(ap["Cg"]), S(adj_params.E),
                       S(adj_params.nu), a_eff, 0, None, None, a_pin, 0, 0.0, 0.0]
            R.launch(lane, K.g2p_update, n, self._update_args_lane(s_in, frame, p, c, S), [S(a) for a in self._outs(s_out)],
                     adj_inputs=adj_upd, adj_outputs=[S(a) for a in self._outs(adj_out)], adjoint=True, block_dim=bd)
            R.launch(lane, K.g2p_gather_adj, n, [S(s_in.x), self.gv, self.lo, self.inv_dx, self.res3, S(ap["vg"]),
                                                 S(ap["Cg"])], [S(adj_in.x), ag["gv"] if lane == 0 else L.a_gv],
                     block_dim=bd)
        R.barrier()
        gv_out = self._own["_flat"]["gv"] if taped else self._flat["gv"]
        for lane in (0, 1):
            a, b, args = self._grid_args_lane(lane, frame, substep, p, c)
            N = L.nodes
            R.launch(lane, self.K.add_vec3, b - a, [N(af["gv"], lane), N(L.a_gv_flat, lane)], block_dim=bd)
            R.zero(lane, *(N(af[k], lane) for k in SCATTERED))
            adj_grid = [N(af[k], lane) for k in SCATTERED] + [
                adj_params.eff if lane == 0 else L.a_eff, 0, None, 0.0, None, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, None, None,
                adj_ctrl.col_pos if lane == 0 else L.a_col, None, None, None, 0, 0.0, 0.0, None, None, 0, 0, 0.0, 0.0]
            R.launch(lane, self.grid_kernel, args[self.GRID_NTHR], args, [N(gv_out, lane)], adj_inputs=adj_grid,
                     adj_outputs=[N(af["gv"], lane)], adjoint=True, block_dim=bd)
        R.barrier()
        A_fwd = self._own["A"] if taped else self.A
        for lane in (0, 1):
            n, S = self._half(lane)
            a_eff = adj_params.eff if lane == 0 else L.a_eff
            a_pin = adj_ctrl.pin_pos if lane == 0 else L.a_pin
            v, a_v = s_in.v, adj_in.v
            if self.vgr is not None:     # the particles' ground: recomputed (tapes do not keep it), then its adjoint
                v, a_v = self.vgr, self._a_vgr
                R.launch(lane, K.ground_impulse, n, self._ground_args(s_in, p, S), [S(v)], block_dim=bd)
                R.zero(lane, S(a_v))
            R.launch(lane, K.p2g_scatter_adj, n, [S(s_in.x), S(v), S(self.A), S(self.dev["mass"]), S(c.pin_id),
                                                  c.pin_active, c.pin_pos, c.pin_kind, frame, self.fps, self.lo,
                                                  self.inv_dx, self.res3] + [ag[k] for k in SCATTERED],
                     [S(adj_in.x), S(a_v), S(ap["A"]), a_pin], block_dim=bd)
            if self.vgr is not None:
                R.launch(lane, K.ground_impulse, n, self._ground_args(s_in, p, S), [S(v)],
                         adj_inputs=[S(adj_in.x), S(adj_in.v), S(adj_in.C), None, a_eff, 0, 0.0, 0.0, 0.0],
                         adj_outputs=[S(a_v)], adjoint=True, block_dim=bd)
            R.launch(lane, K.p2g_stress_adj, n, [S(s_in.F), S(self.dev["mass"]), S(self.dev["volume"]), S(p.E), S(p.nu),
                                                 self.material, self.inv_dx, self.dt, S(ap["A"])],
                     [S(adj_in.F), S(adj_in.C), S(adj_params.E), S(adj_params.nu)], block_dim=bd)
            if self.flags & F_VISCO:
                R.launch(lane, K.p2g_stress_visco, n, [S(s_in.Fv), S(self.dev["volume"]), S(p.nu), p.eff, self.inv_dx,
                                                       self.dt], [S(A_fwd)],
                         adj_inputs=[S(adj_in.Fv), None, S(adj_params.nu), a_eff, 0.0, 0.0], adj_outputs=[S(ap["A"])],
                         adjoint=True, block_dim=bd)

    def lanes_fold(self, adj_params, adj_ctrl) -> None:
        """At the end of a frame's adjoint captured on two lanes: lane B's effect-parameter, pin- and collider-
        trajectory adjoints added into adj_params / adj_ctrl by lane A (then zeroed). Nothing otherwise."""
        R = self._rec
        if R is None:
            return
        R.sync()
        L, bd = self.lanes, self.block_dim
        R.launch(0, L.LK.add_T, adj_params.eff.shape[0], [adj_params.eff, L.a_eff], block_dim=bd)
        R.zero(0, L.a_eff)
        for mine, theirs in ((adj_ctrl.pin_pos, L.a_pin), (adj_ctrl.col_pos, L.a_col)):
            if theirs.size:
                R.launch(0, self.K.add_vec3, theirs.size, [mine.flatten(), theirs.flatten()], block_dim=bd)
                R.zero(0, theirs)

    # ------------------------------------------------------------------ checks
    def check(self, s: SimState, row: int, status: wp.array):
        """Count non-finite and out-of-domain particles of state s into status[row], and the particles whose
        stencil was clamped at a substep since the last check (`clamped`, cleared here; no host sync)."""
        if self._rec is not None:
            self._rec.sync()
        wp.launch(self.K.check, s.x.shape[0], [s.x, s.v, s.F, self.lo, self.inv_dx, self.res3, row], [status, self.clamped],
                  device=self.device, record_tape=False, block_dim=self.block_dim)

    def new_status(self, n_rows: int) -> wp.array:
        return wp.zeros((n_rows, N_STATUS), dtype=wp.int32, device=self.device)

    def reset_status(self, status: wp.array) -> None:
        """Before a pass: its status rows and the particles' clamp marks (a replay's p2g leaves them) cleared."""
        status.zero_()
        self.clamped.zero_()

    def bad_particle_note(self, p: int, state: dict | None) -> str:
        """Where non-finite particle p stood at the start of its bad frame (`state`: that frame's numpy x, v, F):
        its speed (and cells a substep), J = det F and largest stretch, the nearest other particle in cells (a lone
        particle: none within its stencil's reach, 1.5 cells) and the nearest face of the grid's valid box; "" when
        the state is not at hand or the particle was already non-finite then."""
        if state is None:
            return ""
        try:
            m, g = self.model, self.model.grid
            x = np.asarray(state["x"], dtype=np.float64)
            xp = x[p]
            v = np.asarray(state["v"], dtype=np.float64)[p]
            F = np.asarray(state["F"], dtype=np.float64)[p].reshape(3, 3)
            if not (np.isfinite(xp).all() and np.isfinite(v).all() and np.isfinite(F).all()):
                return ""
            J = float(np.linalg.det(F))
            sv = np.linalg.svd(F, compute_uv=False)
            near = self._nearest_other_cells(p, state)
            lo, hi = np.asarray(g.valid_lower, float), np.asarray(g.valid_upper, float)
            d = np.concatenate([xp - lo, hi - xp]) / g.dx
            i = int(np.argmin(d))
            spd = float(np.linalg.norm(v))
            lone = " (a lone particle: none within its stencil's 1.5 cells)" if near > 1.5 else ""
            return (f"; particle {p} at the frame's start: speed {spd:.3g} m/s ({spd * m.dt / g.dx:.3g} cells a "
                    f"substep), J {J:.3g}, stretch {sv.max():.3g} / {sv.min():.3g}, nearest other particle "
                    f"{near:.2f} cells{lone}, {d[i]:.1f} cells inside the {'-+'[i // 3]}{'xyz'[i % 3]} face")
        except Exception:  # noqa: BLE001 - a courtesy; the error stands without it
            return ""

    def raise_on_status(self, status: wp.array, frames=None, positions=None, states=None):
        """Raise SimulationError for the first frame whose status row reports a problem: "left the grid" (kind
        "domain") where a particle's stencil was clamped at the grid's edge during the frame or a particle ended it
        outside the valid box, whether or not the state then went non-finite (a clamped stencil's weights go
        negative and the state blows up within ~a cell: that is the grid's size, not the step); "non-finite"
        (kind "unstable", the step) where no particle walked out of the grid (kernels.mark_clamped). `positions(r)`: the particles' (P, 3)
        positions at the start of bad row r's frame (to name the face), or None; `states(r)`: that frame's start
        {"x", "v", "F"} (a non-finite particle's speed, J, neighbours and walls in the message: `bad_particle_note`)."""
        st = status.numpy()
        m = self.model
        if not getattr(m, "stencil_check", True):      # as before #24: the frame's end only (the synthetic truths)
            st = st.copy()
            st[:, 4:] = 0
        bad = np.nonzero((st[:, 0] > 0) | (st[:, 1] > 0) | (st[:, 4] > 0))[0]
        if bad.size == 0:
            return
        r = int(bad[0])
        frame = r + 1 if frames is None else int(frames[r])
        # (a particle outside at the frame's end beside non-finite ones, with no clamp mark, flew out of a state
        # already blowing up: the step)
        if st[r, 4] > 0 or (st[r, 1] > 0 and st[r, 0] == 0):
            raise self._left_grid_error(st[r], r, frame, positions, states)
        if not getattr(m, "stencil_check", True):
            raise SimulationError(
                f"state became non-finite ({st[r, 0]} particles, e.g. particle {st[r, 2]})", frame=frame,
                advice=(f"the substep dt = {m.dt:.3g} s ({m.substeps} per frame) is too large for the stiffness "
                        f"or speed reached: raise substeps per frame, lower E_max = {m.E_max:g} Pa (and nu_max "
                        f"= {m.nu_max:g}), or slow the trajectory; or particles swung past the grid's edge "
                        f"(a free end about a support), which blows up the same way: enlarge the domain"),
                kind="unstable")
        note = self.bad_particle_note(int(st[r, 2]), None if states is None else states(r))
        raise SimulationError(
            f"state became non-finite ({st[r, 0]} particles, e.g. particle {st[r, 2]}; none had walked out of "
            f"the grid{note})", frame=frame,
            advice=(f"the substep dt = {m.dt:.3g} s ({m.substeps} per frame) is too large for the stiffness "
                    f"or speed reached: raise substeps per frame, lower E_max = {m.E_max:g} Pa (and nu_max "
                    f"= {m.nu_max:g}), or slow the trajectory"),
            kind="unstable")

    def _left_grid_error(self, row, r: int, frame: int, positions, states=None) -> SimulationError:
        """The "left the grid" error of status row `row` (index r): how many, how far past, which face; and, given
        the frame's start state, whether the particle had come off the object alone (no other particle within its
        stencil's 1.5 cells: a particle flung off, which no domain holds; #24 dev_0255)."""
        m, g = self.model, self.model.grid
        n_clamped, past, p = int(row[4]), (int(row[5]) - 1) / 1000.0, int(row[6])
        if n_clamped == 0:                       # seen outside only at the frame's end
            n_clamped, p, past = int(row[1]), int(row[3]), None
        face, face_name = "", ""
        if positions is not None:
            try:
                x = np.asarray(positions(r), dtype=np.float64)[p]
                lo, hi = g.valid_lower, g.valid_upper
                d = np.concatenate([lo - x, x - hi])          # > 0: past that face
                if np.all(np.isfinite(d)):
                    i = int(np.argmax(d))
                    face_name = f"{'-+'[i // 3]}{'xyz'[i % 3]}"
                    face = f", nearest the {face_name} face"
                    if past is None:
                        past = max(float(d[i]) / g.dx, 0.0)
            except Exception:  # noqa: BLE001 - the face is a courtesy; the error stands without it
                face, face_name = "", ""
        how = "" if past is None else f" by up to {past:.2f} cells ({1e3 * past * g.dx:.1f} mm)"
        lone, near = "", self._nearest_other_cells(p, states(r) if states is not None else None)
        if near is not None and near > 1.5:
            lone = f", alone: it had come off the object (no other particle within {near:.1f} cells)"
        nf = f"; {int(row[0])} went non-finite after it" if row[0] > 0 else ""
        lo, hi = g.valid_lower, g.valid_upper
        return SimulationError(
            f"left the grid domain ({n_clamped} particles past the edge of the grid's valid box{how}, e.g. particle {p}"
            f"{face}{lone}{nf}; valid box [{', '.join(f'{v:.3g}' for v in lo)}] - [{', '.join(f'{v:.3g}' for v in hi)}] m)",
            frame=frame,
            advice=(("a particle flung off the object alone leaves any grid: a stray fill particle (re-run init: "
                     "its fill drops lattice points with no neighbour) or a violent snap (a stretched part released: "
                     "a lower E or a gentler pull); " if lone else "")
                    + "enlarge the grid: give the object more room (init --padding, or a GridSpec with a larger box); the "
                    "simulation's automatic domain covers the object's reach about its supports, the hand's path and a "
                    "fall after a release (simulation.grid_covering); or check the trajectory, the ground and gravity"),
            kind="domain", face=face_name)

    def _nearest_other_cells(self, p: int, state: dict | None) -> float | None:
        """Particle p's distance to its nearest other (finite) particle at `state`'s positions, in cells; None
        without a state."""
        if state is None:
            return None
        try:
            x = np.asarray(state["x"], dtype=np.float64)
            ok = np.isfinite(x).all(axis=1)
            if not ok[p]:
                return None
            ok[p] = False
            return float(np.sqrt(((x[ok] - x[p]) ** 2).sum(1).min()) / self.model.grid.dx) if ok.any() else float("inf")
        except Exception:  # noqa: BLE001 - a courtesy
            return None

    # ------------------------------------------------------------------ convenience
    def simulate(self, n_frames: int, state: SimState | None = None, check: bool = True) -> dict[str, np.ndarray]:
        """Forward rollout without gradients; returns per-frame numpy arrays x, v, F (frame 0 = start)."""
        m = self.model
        if state is None:
            state = SimState.rest(m, block_dim=self.block_dim)
        start = SimState.zeros(m.n_particles, m.dtype, m.device)
        start.assign(state)
        for _ in range(2):          # the second time on the whole grid, if the particles left the grid box
            a, b = SimState.zeros(m.n_particles, m.dtype, m.device), SimState.zeros(m.n_particles, m.dtype, m.device)
            a.assign(start)
            self.box_flag.zero_()
            status = self.new_status(n_frames)
            self.clamped.zero_()
            frames = {"x": [a.x.numpy().copy()], "v": [a.v.numpy().copy()], "F": [a.F.numpy().copy()]}
            for k in range(n_frames):
                for s in range(self.S):
                    self.step(a, b, k, s)
                    a, b = b, a
                self.check(a, k, status)
                frames["x"].append(a.x.numpy().copy())
                frames["v"].append(a.v.numpy().copy())
                frames["F"].append(a.F.numpy().copy())
            if self.full_box() or int(self.box_flag.numpy()[0]) == 0:
                break
            self.set_box(None)
            self.clear_all()
        if check:
            self.raise_on_status(status, positions=lambda r: frames["x"][r],
                                 states=lambda r: {k: frames[k][r] for k in ("x", "v", "F")})
        if a is not state:
            state.assign(a)
        return {k: np.stack(v) for k, v in frames.items()}
