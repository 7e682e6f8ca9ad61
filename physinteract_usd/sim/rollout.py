"""Checkpointed differentiable rollout and its torch.autograd.Function.

Forward: the rollout runs on two ping-pong states (no tape, no per-substep allocation) and copies
the particle state into a checkpoint at the end of every frame; one reduction kernel per frame
records non-finite or out-of-domain particles, read once after the rollout (one host sync).

Backward, frame by frame from the last: restore the frame's checkpoint, replay its substeps
storing the particle states (S+1 states of P particles; no grid is stored), then run the substeps'
adjoints in reverse, each recomputing its grid from the stored particle state (`MPMSolver.
step_adjoint`). The adjoint of the frame's first state carries into the previous frame. Memory:
checkpoints (T+1 frames x P particles) + S+1 replay states + one grid and its adjoint, whatever
the number of substeps.

A forward that gradients will flow back through (`_SimulateFn`) keeps every substep's particle
state instead, when they fit in STORE_STATES_BYTES (T x (S+1) states of P particles): its backward
then runs the adjoints at once, without the replay (a forward's worth of work per backward, ~18%
of a CPU fit's iteration on the demo, docs/benchmarks/cpu.md). A backward whose stored states a
later forward overwrote replays into them as above.

With `TAPE_GRID` (the CPU's default) a stored frame also keeps each substep's grid and gathered /
affine particle buffers (`MPMSolver.new_tape`, within TAPE_BYTES): its adjoints then read them instead
of recomputing the substep's grid (p2g, grid update and gather: ~30% of a CPU backward). Bitwise the
same gradients (tests/test_sim_tape.py).

Each frame's forward and backward is captured once into a graph (CUDA graph on a GPU, Warp's CPU
graph on the CPU) and replayed on later calls, so the inner loop has no Python work. With
`FRAME_GRAPHS` (the default on CUDA) one graph serves every frame of the same *shape*: the frame index
is a device-side counter the graph advances, and what it indexes goes through fixed windows
(sim/frame_graphs.py), so a capture issues one frame's launches from Python, not T frames' (issue #26).

Torch entry points: `Rollout(model, control)(E, nu, effects=..., trajectories=...)` (keeps its
buffers and graphs between calls: use it in a fit loop) and `simulate(model, control, ...)`.
"""

from __future__ import annotations

import atexit
import copy
import itertools
import math
import os
import sys
from types import SimpleNamespace
from typing import Mapping

import numpy as np
import torch
import warp as wp

from .. import stopping
from ..devices import torch_device
from ..errors import SimulationError
from . import lanes as lanes_mod
from .control import Control, ControlArrays
from .effects import N_PARAMS, PARAMETERS, SLOTS, canonical
from .solver import ControlAdjoint, MPMSolver, SimParams
from .state import SimState

_TORCH_DTYPE = {"float32": torch.float32, "float64": torch.float64}
# A rollout keeps substep states for its backward up to this size: every frame's when they fit, else
# as many frames' as fit (the others are replayed from their checkpoints, into one frame's replay
# buffer, counted in the budget). None (default): 1 GiB on the CPU; on a GPU STORE_STATES_GPU_FRACTION
# of its memory, at most what is free less STORE_STATES_GPU_HEADROOM of it (at least 4 GiB) when they are allocated
# (the paper fit's 21k particles x 45 frames x 421 states are ~53 GB: without this every backward
# replayed its whole forward, ~20% of an iteration)
STORE_STATES_BYTES: int | None = None
STORE_STATES_GPU_FRACTION = 0.5
STORE_STATES_GPU_HEADROOM = 0.1
# Substep tapes (`MPMSolver.new_tape`): a forward for a backward keeps, for its stored frames, each substep's
# grid and A / vg / Cg, and the backward reads them instead of recomputing them. None (default): on the CPU
# (where the recompute is ~30% of the backward, docs/benchmarks/cpu.md) with the grid box and frame graphs
# off (their defaults there); True / False force it (not with the grid box, frame graphs or fused kernels:
# those keep the recompute). PHYSINTERACT_TAPE_GRID=0 / 1 in the environment sets it for a process (the A/B timing)
TAPE_GRID: bool | None = (None if os.environ.get("PHYSINTERACT_TAPE_GRID", "") == ""
                          else os.environ["PHYSINTERACT_TAPE_GRID"] not in ("0", "false", "False"))
# what the tapes may take, beside the stored states (STORE_STATES_BYTES): frames 0 .. n - 1 of the stored
# ones get one, as many as fit (the demo: 1,769 particles, a 9,720-node grid, 13 frames x ~130 substeps of
# 0.58 MB: ~1 GB). None: 1.5 GiB
TAPE_BYTES: int | None = None
# A forward without gradients runs its launches eagerly this many times before its graphs are
# captured: a rollout at a new rung is often used once (a start-search probe), and capturing T
# graphs for one replay costs more than launching them (CPU, the sample at grid 12: 3.5 s to
# capture and replay a probe's forward against 1.0 s eager; on CUDA the capture's launches cost what
# eager ones do, plus the instantiation and the replay after them).
EAGER_FORWARDS = 1
# the grid box (`MPMSolver.grid_box`): the nodes the particles' stencils reached in this rollout's
# forwards so far (the rest shape and the contacts' reach before the first) plus this many cells on
# each side. A pass whose particles leave the box (every p2g checks) is redone on the whole grid.
BOX_MARGIN = 4
# one captured graph per frame shape (sim/frame_graphs.py) instead of one per frame: the forward, the stored
# forward, the replay and the adjoint each capture one frame's launches (two shapes where only some frames'
# states are stored) instead of T frames'. True / False force it; None (default): on CUDA devices (where a
# capture's launches cost what eager ones do); the CPU keeps per-frame graphs (the windows' copies are pure
# overhead where a graph replays without launch costs). Bitwise the same results (tests/test_frame_graphs.py).
# PHYSINTERACT_FRAME_GRAPHS=0 / 1 in the environment sets it for a process (the CLI's before / after timing)
FRAME_GRAPHS: bool | None = (None if os.environ.get("PHYSINTERACT_FRAME_GRAPHS", "") == ""
                             else os.environ["PHYSINTERACT_FRAME_GRAPHS"] not in ("0", "false", "False"))
# PHYSINTERACT_SIM_STATS=1 in the environment: at exit, one line per rollout on stderr (its size, the
# grid box's share of the grid, passes redone, frames whose states were stored, forwards / backwards run)
_STATS: dict | None = {} if os.environ.get("PHYSINTERACT_SIM_STATS") else None   # rollout no. -> line (no references)


_ROLLOUT_NO = itertools.count()
# frame-shape bodies run once (outside a capture) in this process: `Rollout._warm_key`
_WARM_SHAPES: set = set()


def _print_stats() -> None:
    for line in (_STATS or {}).values():
        print(line, file=sys.stderr)


if _STATS is not None:
    atexit.register(_print_stats)


def _torch_device(model) -> torch.device:
    return torch_device(model.device)


class Checkpoints:
    """Per-frame particle states (T+1 frames): Warp arrays (T+1, P) with torch views."""

    def __init__(self, model, n_frames: int):
        from .kernels import get_kernels
        K = get_kernels(model.dtype)
        P = model.n_particles
        types = {"x": K.vec3, "v": K.vec3, "C": K.mat33, "F": K.mat33, "Fv": K.mat33}
        self.w = {k: wp.zeros((n_frames + 1, P), dtype=t, device=model.device) for k, t in types.items()}
        self.t = {k: wp.to_torch(a, requires_grad=False) for k, a in self.w.items()}

    def frame(self, k: int) -> SimState:
        return SimState(*(self.w[f][k] for f in SimState.FIELDS))

    def states(self) -> list[SimState]:
        """Every row as a SimState (views of the arrays)."""
        return [self.frame(k) for k in range(self.w["x"].shape[0])]


class Rollout:
    """A differentiable rollout of ``control.n_frames`` frames of ``model`` under ``control``.

    Call it with torch tensors:

        x, F = rollout(E, nu, effects={"damping": {"coefficient": c}}, trajectories={0: traj})

    E (P,) [Pa], nu (P,); ``effects``: {effect: {parameter: value}} (tensors or floats; effects
    must be enabled in the model; missing values take the model's defaults); ``trajectories``:
    {contact index: (T+1, 3)} or a list aligned with ``control.contacts`` (None: the contact's own);
    ``v0``: optional initial velocity (P, 3) or (3,); ``F0``: optional initial deformation gradient (P, 3, 3) (the
    model's rest positions then start prestressed: a scan of an object already hanging in its supports, its stress
    holding it up; default the identity). Returns x (T+1, P, 3) and F (T+1, P, 3, 3), frame 0 = the start,
    differentiable w.r.t. all the inputs.

    The rollout keeps its buffers (checkpoints, replay states, one grid and its adjoint) between
    calls. With ``graphs=True`` (default) each frame's forward and backward is captured once into a
    graph (CUDA graph on a GPU, Warp's CPU graph on the CPU) and replayed on later calls: no
    per-substep Python work. ``graphs=False`` launches every kernel from Python (same results).
    """

    def __init__(self, model, control: Control | None = None, n_frames: int | None = None, graphs: bool = True):
        if control is None:
            control = Control([], n_frames=n_frames or 1)
        self.model = model
        self.control = control
        self.T = control.n_frames
        self.S = model.substeps
        self.P = model.n_particles
        self.ctrl = ControlArrays(model, control)
        self.params = SimParams(model)
        self.solver = MPMSolver(model, self.ctrl, self.params)
        m = model
        K = self.solver.K
        self._pp = [SimState.zeros(self.P, m.dtype, m.device) for _ in range(2)]
        self._replay: list[SimState] | None = None
        self._adj = [SimState.zeros(self.P, m.dtype, m.device) for _ in range(2)]
        self.adj_params = SimParams.zeros_like(self.params)
        self.adj_ctrl = ControlAdjoint(self.ctrl)
        self.status = self.solver.new_status(self.T)
        self.v0 = wp.zeros(self.P, dtype=K.vec3, device=m.device)
        # frame 0's F: the identity, or a call's `F0` (always copied in at the start, so a frame graph captured with
        # one holds for the other)
        self.F0 = wp.zeros(self.P, dtype=K.mat33, device=m.device)
        self._identity_F0()
        self.ck = Checkpoints(m, self.T)
        self.grad_x = wp.zeros((self.T + 1, self.P), dtype=K.vec3, device=m.device)
        self.grad_F = wp.zeros((self.T + 1, self.P), dtype=K.mat33, device=m.device)
        self.graphs = bool(graphs)
        # one graph per frame shape (FRAME_GRAPHS): read when a rollout is built
        self.frame_graphs = (wp.get_device(m.device).is_cuda if FRAME_GRAPHS is None else bool(FRAME_GRAPHS))
        self._fw = None                # the frame windows (`_windows`), built at the first capture
        self._arena = None             # the stored states as (frames, S + 1, P) arrays per field (frame graphs)
        self._fwd_graphs: dict[int, object] = {}
        self._bwd_graphs: dict[int, object] = {}
        self._warm: set = set()
        # every substep's state of every frame (a forward for a backward, when they fit), and which
        # forward they hold (`states_generation`: counts the forwards that stored states)
        self._states: list[list[SimState]] | None = None
        self._tapes: list[list] = []      # substep tapes of stored frames 0 .. len - 1 (TAPE_GRID)
        self.states_generation = 0
        self._fwd_store_graphs: dict[int, object] = {}
        self._eager_forwards_left = EAGER_FORWARDS     # forwards without gradients before capturing
        self._replay_graphs: dict[int, object] = {}
        self._adj_graphs: dict[int, object] = {}
        self.box_redos = 0             # passes redone on the whole grid because particles left the box
        self.n_forwards = self.n_backwards = 0
        self._stats_key = next(_ROLLOUT_NO)
        self._reach = None             # (lo, hi) grid nodes the stencils reached in the forwards so far
        if self.solver.grid_box:
            self._initial_box()

    # ------------------------------------------------------------------ the grid box
    def _node_span(self, lo_x, hi_x):
        """Grid nodes (lo, hi exclusive) the stencils of particles in [lo_x, hi_x] (m) touch."""
        g = self.model.grid
        lo = np.floor((np.asarray(lo_x) - g.lower) / g.dx - 0.5).astype(int)
        hi = np.floor((np.asarray(hi_x) - g.lower) / g.dx - 0.5).astype(int) + 3
        return lo, hi

    def _initial_box(self) -> None:
        """Before any forward: the rest shape, widened on both sides of each axis by as far as any
        contact's trajectory moves along it (from its first frame: what is pulled aside may swing
        back past rest), plus BOX_MARGIN cells. Only a guess: the forwards check it, and the box
        after the first forward is that forward's reach (+ the margin), which may be smaller."""
        x0 = np.asarray(self.model.x0, dtype=np.float64)
        r = np.zeros(3)
        for c in self.control.contacts:
            t = getattr(c, "trajectory", None)
            if t is None:
                continue
            t = t.detach().double().cpu().numpy() if torch.is_tensor(t) else np.asarray(t, dtype=np.float64)
            r = np.maximum(r, np.abs(t - t[:1]).max(0))
        lo_x, hi_x = x0.min(0) - r, x0.max(0) + r
        lo, hi = self._node_span(lo_x, hi_x)
        self.solver.set_box(lo - BOX_MARGIN, hi + BOX_MARGIN)

    def _update_box(self) -> None:
        """After a forward that stayed finite: the box of every forward's reach so far + BOX_MARGIN."""
        x = self.ck.t["x"].reshape(-1, 3)
        ext = torch.stack([x.amin(0), x.amax(0)]).double().cpu().numpy()     # one host sync
        if not np.all(np.isfinite(ext)):
            return
        lo, hi = self._node_span(ext[0], ext[1])
        if self._reach is not None:
            lo, hi = np.minimum(lo, self._reach[0]), np.maximum(hi, self._reach[1])
        self._reach = (lo, hi)
        self.solver.set_box(lo - BOX_MARGIN, hi + BOX_MARGIN)

    def _left_box(self) -> bool:
        """Whether the pass just run had particles whose stencil left the grid box (one host sync);
        if so the box becomes the whole grid, cleared, for the pass to be redone."""
        sol = self.solver
        if not sol.grid_box or int(sol.box_flag.numpy()[0]) == 0:
            return False
        self.box_redos += 1
        sol.set_box(None)
        sol.clear_all()
        sol.box_flag.zero_()
        return True

    def _frame_positions(self, r: int) -> np.ndarray:
        """The particles' positions at the start of frame r of the last forward (a left-the-grid error's face)."""
        return self.ck.t["x"][r].detach().double().cpu().numpy()

    def _frame_state(self, r: int) -> dict:
        """The particles' x, v, F at the start of frame r of the last forward (a non-finite error's particle)."""
        return {k: self.ck.t[k][r].detach().double().cpu().numpy() for k in ("x", "v", "F")}

    # ------------------------------------------------------------------ one frame, forward / backward
    def _forward_frame(self, k: int) -> None:
        sol = self.solver
        a, b = self._pp
        if k == 0:
            sol.reset_status(self.status)
            sol.box_flag.zero_()
            self._set_start(a)
            self.ck.frame(0).assign(a)
        else:
            a.assign(self.ck.frame(k))
        for s in range(self.S):
            sol.step(a, b, k, s)
            a, b = b, a
        sol.check(a, k, self.status)
        self.ck.frame(k + 1).assign(a)

    def _forward_frame_stored(self, k: int) -> None:
        """`_forward_frame`, keeping every substep's state in `self._states[k]` (frames past the
        stored ones: `_forward_frame`)."""
        if k >= len(self._states):
            return self._forward_frame(k)
        sol = self.solver
        st = self._states[k]
        if k == 0:
            sol.reset_status(self.status)
            sol.box_flag.zero_()
            self._set_start(st[0])
            self.ck.frame(0).assign(st[0])
        else:
            st[0].assign(self.ck.frame(k))
        tape = self._tapes[k] if k < len(self._tapes) else None
        for s in range(self.S):
            sol.step(st[s], st[s + 1], k, s, save=None if tape is None else tape[s])
        sol.check(st[self.S], k, self.status)
        self.ck.frame(k + 1).assign(st[self.S])

    def _replay_into(self, st: list, k: int, tape=None) -> None:
        st[0].assign(self.ck.frame(k))
        if tape is not None:         # every substep: the last one's grid is read by its adjoint
            for s in range(self.S):
                self.solver.step(st[s], st[s + 1], k, s, save=tape[s])
            return
        for s in range(self.S - 1):  # the last substep's output is never read by the adjoints
            self.solver.step(st[s], st[s + 1], k, s)

    def _backward_frame(self, k: int) -> None:
        self._replay_into(self._replay, k)
        self._adjoint_frame(self._replay, k)

    def _replay_frame_stored(self, k: int) -> None:
        if k < len(self._states):       # frames past the stored ones replay in `_adjoint_frame_stored`
            self._replay_into(self._states[k], k, self._tapes[k] if k < len(self._tapes) else None)

    def _adjoint_frame_stored(self, k: int) -> None:
        if k >= len(self._states):
            return self._backward_frame(k)
        self._adjoint_frame(self._states[k], k, self._tapes[k] if k < len(self._tapes) else None)

    def _adjoint_frame(self, st: list, k: int, tape=None) -> None:
        sol = self.solver
        K = sol.K
        d = self.model.device
        carry, other = self._adj
        wp.launch(K.add_vec3, self.P, [carry.x, self.grad_x[k + 1]], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)
        wp.launch(K.add_mat33, self.P, [carry.F, self.grad_F[k + 1]], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)
        for s in reversed(range(self.S)):
            sol.step_adjoint(st[s], st[s + 1], other, carry, k, s, self.adj_params, self.adj_ctrl, clear_adj_in=True,
                             save=None if tape is None else tape[s])
            carry, other = other, carry
        sol.lanes_fold(self.adj_params, self.adj_ctrl)
        if carry is not self._adj[0]:
            self._adj[0].assign(carry)

    def _ensure_graphs(self, graphs: dict, fn) -> None:
        """Capture fn(k) for every frame (once). Capturing may execute the work (CPU graphs), so the
        callers reset their accumulators after this and then replay the graphs in order."""
        if self.graphs and self.frame_graphs:
            return self._ensure_shape_graphs(graphs)
        if not self.graphs or len(graphs) == self.T:
            return
        try:
            if id(graphs) not in self._warm:      # load modules, allocate lazily built buffers: not in a capture
                fn(0)
                self._warm.add(id(graphs))
            lanes = self._lanes()
            for k in range(self.T):
                if k not in graphs:
                    if lanes is not None:
                        graphs[k] = self._capture_lanes(lanes, fn, k)
                        continue
                    with wp.ScopedCapture(device=self.model.device) as cap:
                        fn(k)
                    graphs[k] = cap.graph
        except Exception as e:  # noqa: BLE001  (capture unsupported here: fall back to launches)
            import warnings
            warnings.warn(f"graph capture failed ({e}); running without graphs", RuntimeWarning, stacklevel=3)
            self.graphs = False
            graphs.clear()

    def _lanes(self):
        """The solver's second lane (sim/lanes.py) when this rollout's per-frame graphs run on two lanes, else None."""
        sol = self.solver
        if self.frame_graphs or not lanes_mod.wanted(sol):
            return None
        if sol.lanes is None:
            sol.lanes = lanes_mod.Lanes(sol)
        return sol.lanes

    def _capture_lanes(self, lanes, fn, k: int):
        """Frame k's two graphs: fn(k) captured with the solver issuing lane A's launches (and keeping lane B's),
        then lane B's captured alone (Warp 1.19's CPU capture records without executing; were a capture to execute,
        its barriers count one lane: `arm(1)`). Nothing may be allocated in here: on the CPU an allocation's memset
        inside a capture is recorded into the graph and runs again at every replay (lanes.Lanes makes its buffers
        first)."""
        sol = self.solver
        rec = lanes_mod.Recorder(lanes)
        lanes.arm(1)
        sol._rec = rec
        try:
            with wp.ScopedCapture(device=self.model.device) as cap:
                fn(k)
                rec.sync()
        finally:
            sol._rec = None
        lanes.arm(1)
        with wp.ScopedCapture(device=self.model.device) as cap_b:
            rec.replay_b()
        return lanes_mod.LanePair(cap.graph, cap_b.graph)

    def _frame(self, graphs: dict, fn, k: int) -> None:
        if self.graphs and self.frame_graphs:
            key = self._shape(graphs, k)[0]
            if key is not None:
                wp.capture_launch(graphs[key])
        elif self.graphs:
            g = graphs[k]
            if isinstance(g, lanes_mod.LanePair):
                self.solver.lanes.replay(g)
            else:
                wp.capture_launch(g)
        else:
            fn(k)

    # ------------------------------------------------------------------ one graph per frame shape
    def _windows(self) -> SimpleNamespace:
        """The fixed arrays a frame-shape graph runs on (sim/frame_graphs.py): the frame counter, the
        contacts' and their adjoints' rows k, k + 1, the status row, and S + 1 states (a stored frame's
        substep states, or the replay buffer)."""
        if self._fw is None:
            from .frame_graphs import get_frame_kernels
            m, c = self.model, self.ctrl
            d = m.device
            K = self.solver.K
            npin, ncol = c.pin_pos.shape[0], c.col_pos.shape[0]
            wctrl = copy.copy(c)
            wctrl.pin_active = wp.zeros((npin, 1), dtype=wp.int32, device=d)
            wctrl.pin_pos = wp.zeros((npin, 2), dtype=K.vec3, device=d)
            wctrl.col_active = wp.zeros((ncol, 1), dtype=wp.int32, device=d)
            wctrl.col_pos = wp.zeros((ncol, 2), dtype=K.vec3, device=d)
            wadj = copy.copy(self.adj_ctrl)
            wadj.pin_pos = wp.zeros((npin, 2), dtype=K.vec3, device=d)
            wadj.col_pos = wp.zeros((ncol, 2), dtype=K.vec3, device=d)
            # the S + 1 substep states are allocated only for the bodies that use them (`_window_states`):
            # a forward-only rollout (synth, simulate) at a fine step would otherwise hold (S + 1) x P
            # states it never reads (107 GB for the suite's balloon truth at grid 128)
            self._fw = SimpleNamespace(FK=get_frame_kernels(m.dtype), ctr=wp.zeros(1, dtype=int, device=d),
                                       ctrl=wctrl, adj=wadj, status=self.solver.new_status(1),
                                       states=None, st=None)
        return self._fw

    def _window_states(self) -> SimpleNamespace:
        """The window with its S + 1 substep states (allocated on first use, before any capture:
        `_ensure_shape_graphs` calls it for every body but the plain forward)."""
        fw = self._windows()
        if fw.states is None:
            fw.states = Checkpoints(self.model, self.S)
            fw.st = fw.states.states()
        return fw

    def _warm_key(self, key: str) -> tuple:
        """What a frame-shape body's warm-up run (module loads) holds for: the process, per device, dtype,
        body and the solver's kernel choices (the bodies allocate nothing: their buffers are built before; the
        rate transfer's kernels are a Warp module of their own, loaded by a warm-up run, never in a capture)."""
        sol = self.solver
        return (str(self.model.device), self.model.dtype, key, sol.fused_kernels, sol.fused_zero, sol.grid_box,
                int(sol.flags), sol.rate_f > 0, sol.block_dim)

    def _shape(self, graphs: dict, k: int):
        """(key, body) of the graph that runs frame k of this graph set (key None: nothing to run)."""
        n = len(self._states) if self._states is not None else 0
        if graphs is self._fwd_graphs:
            return "forward", self._sf_forward
        if graphs is self._fwd_store_graphs:
            return ("forward_stored", self._sf_forward_stored) if k < n else ("forward", self._sf_forward)
        if graphs is self._replay_graphs:
            return ("replay", self._sf_replay) if k < n else (None, None)
        if graphs is self._adj_graphs:
            return ("adjoint_stored", self._sf_adjoint_stored) if k < n else ("backward", self._sf_backward)
        return "backward", self._sf_backward

    def _ensure_shape_graphs(self, graphs: dict) -> None:
        """Capture each frame shape's body once (a frame that has it at the counter). A body is run once
        before its first capture (module loads, lazily built buffers); running and (on the CPU)
        capturing execute work, so the callers reset what they accumulate after this."""
        fw = self._windows()
        first: dict = {}
        for k in range(self.T):
            key, body = self._shape(graphs, k)
            if key is not None and key not in graphs and key not in first:
                first[key] = (k, body)
        if any(key != "forward" for key in first):
            self._window_states()
        try:
            for key, (k, body) in first.items():
                wkey = self._warm_key(key)
                if wkey not in _WARM_SHAPES:
                    fw.ctr.fill_(k)
                    body()
                    _WARM_SHAPES.add(wkey)
                fw.ctr.fill_(k)
                with wp.ScopedCapture(device=self.model.device) as cap:
                    body()
                graphs[key] = cap.graph
        except Exception as e:  # noqa: BLE001  (capture unsupported here: fall back to launches)
            import warnings
            warnings.warn(f"graph capture failed ({e}); running without graphs", RuntimeWarning, stacklevel=3)
            self.graphs = False
            graphs.clear()

    def _identity_F0(self) -> None:
        self.F0.assign(np.tile(np.eye(3, dtype=self.model.np_dtype), (self.P, 1, 1)))
        self.has_F0 = False

    def _set_start(self, a: SimState) -> None:
        """Frame 0's state into `a`: the rest (positions, `v0`, F = Fv = I, C = 0), F = `F0` where a call gave one."""
        a.set_rest(self.model, self.v0, self.solver.block_dim)
        wp.copy(a.F, self.F0)

    def _rest_prelude(self) -> None:
        """Frame 0's own work before the frame graphs (eager: a few launches per forward)."""
        fw = self._windows()
        a = self._pp[0]
        self.solver.reset_status(self.status)
        self.solver.box_flag.zero_()
        self._set_start(a)
        self.ck.frame(0).assign(a)
        fw.ctr.zero_()

    def _begin(self, fw, d) -> None:
        c = self.ctrl
        wp.launch(fw.FK.frame_begin, 1, [fw.ctr, c.pin_active, c.pin_pos, c.col_active, c.col_pos, self.status],
                  [fw.ctrl.pin_active, fw.ctrl.pin_pos, fw.ctrl.col_active, fw.ctrl.col_pos, fw.status],
                  device=d, record_tape=False, block_dim=self.solver.block_dim)

    def _ck_arrays(self):
        return [self.ck.w[f] for f in SimState.FIELDS]

    @staticmethod
    def _fields(s: SimState):
        return [getattr(s, f) for f in SimState.FIELDS]

    def _sf_forward(self) -> None:
        """`_forward_frame` of the frame at the counter (frames > 0; frame 0's start: `_rest_prelude`)."""
        fw, sol, d = self._windows(), self.solver, self.model.device
        a, b = self._pp
        wp.launch(fw.FK.rows_to_state, self.P, [fw.ctr, 0] + self._ck_arrays(), self._fields(a), device=d,
                  record_tape=False, block_dim=self.solver.block_dim)
        self._begin(fw, d)
        for s in range(self.S):
            sol.step(a, b, 0, s, ctrl=fw.ctrl)
            a, b = b, a
        sol.check(a, 0, fw.status)
        wp.launch(fw.FK.state_to_rows, self.P, [fw.ctr, 1] + self._fields(a), self._ck_arrays(), device=d,
                  record_tape=False, block_dim=self.solver.block_dim)
        wp.launch(fw.FK.frame_end, 1, [fw.ctr, 1, fw.status], [self.status], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)

    def _sf_forward_stored(self) -> None:
        fw, sol, d = self._window_states(), self.solver, self.model.device
        st = fw.st
        wp.launch(fw.FK.rows_to_state, self.P, [fw.ctr, 0] + self._ck_arrays(), self._fields(st[0]), device=d,
                  record_tape=False, block_dim=self.solver.block_dim)
        self._begin(fw, d)
        for s in range(self.S):
            sol.step(st[s], st[s + 1], 0, s, ctrl=fw.ctrl)
        sol.check(st[self.S], 0, fw.status)
        wp.launch(fw.FK.state_to_rows, self.P, [fw.ctr, 1] + self._fields(st[self.S]), self._ck_arrays(), device=d,
                  record_tape=False, block_dim=self.solver.block_dim)
        self._window_to_arena(fw, d)
        wp.launch(fw.FK.frame_end, 1, [fw.ctr, 1, fw.status], [self.status], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)

    def _window_to_arena(self, fw, d) -> None:
        wp.launch(fw.FK.window_to_arena, (self.S + 1, self.P), [fw.ctr] + [fw.states.w[f] for f in SimState.FIELDS],
                  [self._arena[f] for f in SimState.FIELDS], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)

    def _sf_replay_into_window(self, fw, d) -> None:
        st = fw.st
        wp.launch(fw.FK.rows_to_state, self.P, [fw.ctr, 0] + self._ck_arrays(), self._fields(st[0]), device=d,
                  record_tape=False, block_dim=self.solver.block_dim)
        self._begin(fw, d)
        for s in range(self.S - 1):
            self.solver.step(st[s], st[s + 1], 0, s, ctrl=fw.ctrl)

    def _sf_replay(self) -> None:
        """`_replay_frame_stored` of the frame at the counter (a stored frame); the counter stays."""
        fw, d = self._window_states(), self.model.device
        self._sf_replay_into_window(fw, d)
        self._window_to_arena(fw, d)

    def _sf_adjoint(self, fw, d) -> None:
        """`_adjoint_frame` on the window's states for the frame at the counter, which it steps back."""
        sol = self.solver
        st = fw.st
        c, ac = self.ctrl, self.adj_ctrl
        wp.launch(fw.FK.frame_begin, 1, [fw.ctr, c.pin_active, c.pin_pos, c.col_active, c.col_pos, self.status],
                  [fw.ctrl.pin_active, fw.ctrl.pin_pos, fw.ctrl.col_active, fw.ctrl.col_pos, fw.status],
                  device=d, record_tape=False, block_dim=self.solver.block_dim)
        wp.launch(fw.FK.adj_begin, 1, [fw.ctr, ac.pin_pos, ac.col_pos], [fw.adj.pin_pos, fw.adj.col_pos], device=d,
                  record_tape=False, block_dim=self.solver.block_dim)
        carry, other = self._adj
        wp.launch(fw.FK.add_row_vec3, self.P, [fw.ctr, 1, self.grad_x, carry.x], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)
        wp.launch(fw.FK.add_row_mat33, self.P, [fw.ctr, 1, self.grad_F, carry.F], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)
        for s in reversed(range(self.S)):
            sol.step_adjoint(st[s], st[s + 1], other, carry, 0, s, self.adj_params, fw.adj, ctrl=fw.ctrl,
                             clear_adj_in=True)
            carry, other = other, carry
        if carry is not self._adj[0]:
            self._adj[0].assign(carry)
        wp.launch(fw.FK.adj_end, 1, [fw.ctr, -1, fw.adj.pin_pos, fw.adj.col_pos], [ac.pin_pos, ac.col_pos], device=d,
                  record_tape=False, block_dim=self.solver.block_dim)

    def _sf_adjoint_stored(self) -> None:
        fw, d = self._window_states(), self.model.device
        wp.launch(fw.FK.arena_to_window, (self.S + 1, self.P), [fw.ctr] + [self._arena[f] for f in SimState.FIELDS],
                  [fw.states.w[f] for f in SimState.FIELDS], device=d, record_tape=False,
                  block_dim=self.solver.block_dim)
        self._sf_adjoint(fw, d)

    def _sf_backward(self) -> None:
        """`_backward_frame` of the frame at the counter: replay into the window, then its adjoints."""
        fw, d = self._window_states(), self.model.device
        self._sf_replay_into_window(fw, d)
        self._sf_adjoint(fw, d)

    # ------------------------------------------------------------------ warp-level passes
    def _frame_bytes(self) -> int:
        """The bytes of one frame's substep states (S + 1 states of x, v, C, F, Fv)."""
        return (self.S + 1) * 33 * (4 if self.model.dtype == "float32" else 8) * self.P

    def store_budget(self) -> int:
        """Bytes the stored substep states may take (STORE_STATES_BYTES; see there)."""
        if STORE_STATES_BYTES is not None:
            return int(STORE_STATES_BYTES)
        dev = wp.get_device(self.model.device)
        if not dev.is_cuda:
            return 1 << 30
        headroom = max(4 << 30, STORE_STATES_GPU_HEADROOM * dev.total_memory)
        return int(max(0, min(STORE_STATES_GPU_FRACTION * dev.total_memory, dev.free_memory - headroom)))

    def states_fit(self) -> bool:
        """Whether every substep's state of every frame fits in the budget (`store_budget`; with frame
        graphs beside the window of one frame's states they run on)."""
        extra = 1 if (self.graphs and self.frame_graphs) else 0
        return (self.T + extra) * self._frame_bytes() <= self.store_budget()

    def frames_to_store(self) -> int:
        """How many frames' substep states a forward for a backward keeps: all when they fit, else as
        many as fit beside the replay buffer of the others (frames 0 .. n - 1; the rest replay)."""
        if self.states_fit():
            return self.T
        return int(max(0, min(self.T - 1, self.store_budget() // self._frame_bytes() - 1)))

    def drop_states(self) -> None:
        """Free the stored substep states (and the graphs that use them); a later forward for a
        backward allocates them again."""
        if self._states is None:
            return
        for g in (self._fwd_store_graphs, self._replay_graphs, self._adj_graphs):
            self._warm.discard(id(g))
            g.clear()
        self._states = None
        self._tapes = []
        self._arena = None
        self.states_generation += 1

    def tape_on(self) -> bool:
        """Whether stored frames keep substep tapes (TAPE_GRID; never with the grid box, frame graphs or the
        fused kernels, whose forward gathers in the particle update: no vg / Cg to keep)."""
        if self.solver.grid_box or self.solver.fused_kernels or (self.graphs and self.frame_graphs):
            return False
        return wp.get_device(self.model.device).is_cpu if TAPE_GRID is None else bool(TAPE_GRID)

    def frames_to_tape(self, n_stored: int) -> int:
        """How many of the n_stored frames get a substep tape (TAPE_BYTES)."""
        if not self.tape_on() or n_stored <= 0:
            return 0
        budget = (3 << 29) if TAPE_BYTES is None else int(TAPE_BYTES)
        return int(max(0, min(n_stored, budget // max(self.solver.tape_bytes(self.S), 1))))

    def _alloc_arena(self, n: int) -> dict:
        K = self.solver.K
        types = {"x": K.vec3, "v": K.vec3, "C": K.mat33, "F": K.mat33, "Fv": K.mat33}
        return {f: wp.zeros((n, self.S + 1, self.P), dtype=t, device=self.model.device) for f, t in types.items()}

    def run_forward(self, store: bool = False, start: int = 0) -> int | None:
        """Rollout from rest (with self.v0) into self.ck; raises SimulationError if a frame's state
        is non-finite or left the domain (one host sync, after the last frame). `store`: keep every
        substep's state for `run_backward` (when they fit); returns the stored states' generation
        (None: not stored). `start` > 0: frames 0 .. start of self.ck are already there (another
        forward's, of this model and a control that agrees with this one's before frame `start`:
        `forward_from`); only frames start .. T - 1 are simulated, eagerly, without stored states."""
        start = int(start)
        if start:
            if store or not 0 < start < self.T:
                raise ValueError(f"run_forward: start {start} needs 0 < start < {self.T} and no stored states")
            return self._run_forward_from(start)
        gen = None
        self.n_forwards += 1
        if store and self._states is None:
            n = self.frames_to_store()
            if n > 0:
                # one (S + 1, P) array per field and frame, each state a row of them (a paper fit's
                # ~19k states x 5 fields would otherwise be ~95k allocations); with frame graphs one
                # (n, S + 1, P) arena per field, whose row k the graph addresses through its counter
                if self.graphs and self.frame_graphs:
                    self._arena = self._alloc_arena(n)
                    self._states = [[SimState(*(self._arena[f][k][s] for f in SimState.FIELDS))
                                     for s in range(self.S + 1)] for k in range(n)]
                else:
                    self._states = [Checkpoints(self.model, self.S).states() for _ in range(n)]
                    self._tapes = [self.solver.new_tape(self.S) for _ in range(self.frames_to_tape(n))]
        if store and self._states is not None:
            self.states_generation += 1
            gen = self.states_generation
            graphs, fn = self._fwd_store_graphs, self._forward_frame_stored
        else:
            graphs, fn = self._fwd_graphs, self._forward_frame
        # (with frame graphs a capture costs two frames' launches, not T + 1: no one-off forward runs eagerly)
        eager = (graphs is self._fwd_graphs and not graphs and self._eager_forwards_left > 0
                 and not self.frame_graphs)
        if eager:       # EAGER_FORWARDS: a one-off forward does not pay a capture
            self._eager_forwards_left -= 1
        else:
            self._ensure_graphs(graphs, fn)
        shapes = self.graphs and self.frame_graphs and not eager
        for _ in range(2):                     # the second time on the whole grid, if the box was left
            if shapes:
                self._rest_prelude()
            for k in range(self.T):
                stopping.check("forward")          # SIGINT / SIGTERM act within one frame's work
                if eager:
                    fn(k)
                else:
                    self._frame(graphs, fn, k)
            if not self._left_box():
                break
        if eager:
            self._warm.add(id(graphs))         # its modules are loaded: the capture needs no warm-up frame
        self.solver.raise_on_status(self.status, positions=self._frame_positions, states=self._frame_state)
        if self.solver.grid_box:
            self._update_box()
        self._record_stats()
        return gen

    def _run_forward_from(self, start: int) -> None:
        """`run_forward(start=...)`: frames start .. T - 1 launched eagerly (a one-off forward; no graph
        is captured or replayed: with frame-shape graphs the frame counter would start at 0)."""
        self.n_forwards += 1
        sol = self.solver
        for _ in range(2):                     # the second time on the whole grid, if the box was left
            sol.reset_status(self.status)
            sol.box_flag.zero_()
            for k in range(start, self.T):
                stopping.check("forward")
                self._forward_frame(k)
            if not self._left_box():
                break
        self.solver.raise_on_status(self.status, positions=self._frame_positions, states=self._frame_state)
        if self.solver.grid_box:
            self._update_box()
        self._record_stats()

    def checkpoints(self) -> dict:
        """Copies of the last forward's per-frame states {"x", "v", "C", "F", "Fv"}: (T + 1, P, ...)
        tensors, what `forward_from` starts from."""
        _warp_sync(self.model)
        return {k: _wclone(t) for k, t in self.ck.t.items()}

    def forward_from(self, start: int, states: dict, E=None, nu=None, effects: Mapping | None = None,
                     trajectories=None, v0=None, F0=None):
        """x (T+1, P, 3), F (T+1, P, 3, 3) without gradients of the rollout whose frames 0 .. `start`
        are `states` (`checkpoints()` of a forward of this model under a control that agrees with this
        one's before frame `start`: the same inputs, contacts that differ only from frame `start`, e.g.
        a grasp or release frame moved to >= start); frames start .. T - 1 are simulated. Bitwise the
        whole forward's frames when that holds (tests/test_sim_rollout.py); `start` 0, or a rollout on frame-shape
        graphs (CUDA's default, whose counter starts at frame 0): the whole forward, `__call__`."""
        if int(start) <= 0 or (self.graphs and self.frame_graphs):
            with torch.no_grad():
                return self(E, nu, effects=effects, trajectories=trajectories, v0=v0, F0=F0)
        with torch.no_grad():
            args = self._inputs(E, nu, effects, trajectories, v0, F0)
            _torch_sync(self.model)
            self._load_inputs(*args)
            rows = int(start) + 1
            for k, t in self.ck.t.items():
                _wcopy(t[:rows], states[k][:rows])
            self.run_forward(start=int(start))
            _warp_sync(self.model)
            x, F = _wclone(self.ck.t["x"]), _wclone(self.ck.t["F"])
        return x.view(self.T + 1, self.P, 3), F.view(self.T + 1, self.P, 3, 3)

    def _record_stats(self) -> None:
        if _STATS is None:
            return
        sol = self.solver
        _STATS[self._stats_key] = (
            f"sim stats: {self.P} particles, {self.T} frames x {self.S} substeps, grid {sol.res}: box "
            f"{sol.box_volume:,} of {sol.n_nodes:,} nodes ({sol.box_volume / sol.n_nodes:.1%}, "
            f"{'on' if sol.grid_box else 'off'}), passes redone {self.box_redos}; states stored for "
            f"{0 if self._states is None else len(self._states)} of {self.T} frames; forwards {self.n_forwards}, "
            f"backwards {self.n_backwards}")

    def run_backward(self, generation: int | None = None) -> SimState:
        """From self.ck (the forward's checkpoints) and self.grad_x / self.grad_F (dL/dx, dL/dF per
        frame), fill self.adj_params / self.adj_ctrl; returns the adjoint of the initial state.
        `generation`: what `run_forward(store=True)` returned; the stored states are used as they
        are while no later forward stored over them (else they are replayed from self.ck)."""
        m = self.model
        self.n_backwards += 1
        shapes = self.graphs and self.frame_graphs
        if not shapes and self._replay is None and (self._states is None or len(self._states) < self.T):
            self._replay = [SimState.zeros(self.P, m.dtype, m.device) for _ in range(self.S + 1)]
        self.solver._alloc_adj()
        stored = self._states is not None
        fresh = stored and generation is not None and generation == self.states_generation
        if stored:
            self._ensure_graphs(self._adj_graphs, self._adjoint_frame_stored)
            if not fresh:
                self._ensure_graphs(self._replay_graphs, self._replay_frame_stored)
        else:
            self._ensure_graphs(self._bwd_graphs, self._backward_frame)
        if not self.graphs and self._replay is None and (self._states is None or len(self._states) < self.T):
            self._replay = [SimState.zeros(self.P, m.dtype, m.device) for _ in range(self.S + 1)]   # capture failed
        shapes = self.graphs and self.frame_graphs
        self.solver.box_flag.zero_()
        for _ in range(2):                     # the second time on the whole grid, if the box was left
            self.adj_params.zero_()
            self.adj_ctrl.zero_()
            self._adj[0].zero_()
            if shapes:
                self._windows().ctr.fill_(self.T - 1)
            for k in reversed(range(self.T)):
                stopping.check("backward")
                if not stored:
                    self._frame(self._bwd_graphs, self._backward_frame, k)
                    continue
                if not fresh:
                    self._frame(self._replay_graphs, self._replay_frame_stored, k)
                self._frame(self._adj_graphs, self._adjoint_frame_stored, k)
            if not self._left_box():
                break
            if stored and fresh:
                self._ensure_graphs(self._replay_graphs, self._replay_frame_stored)
            fresh = False      # the adjoints rewrite the stored states from their (wrong) grids: replay them
        if stored:     # a replay (or a graph's warm-up run) may have overwritten the stored states
            self.states_generation += 1 if not fresh else 0
        self._record_stats()
        return self._adj[0]

    # ------------------------------------------------------------------ torch
    def __call__(self, E=None, nu=None, effects: Mapping | None = None, trajectories=None, v0=None, F0=None):
        return _SimulateFn.apply(self, *self._inputs(E, nu, effects, trajectories, v0, F0))

    def _inputs(self, E, nu, effects, trajectories, v0, F0=None):
        """The call's inputs as the torch op takes them (E, nu, eff, pin_pos, col_pos, v0, F0), checked (F0 None:
        the identity, and no gradient for it)."""
        m = self.model
        td = _TORCH_DTYPE[m.dtype]
        dev = _torch_device(m)

        def as_t(v, default):
            if v is None:
                v = default
            if not torch.is_tensor(v):
                v = torch.as_tensor(np.asarray(v, dtype=np.float64))
            return v.to(device=dev, dtype=td)

        E = as_t(E, m.E).expand(self.P)
        nu = as_t(nu, m.nu).expand(self.P)
        eff = self._effect_vector(effects, td, dev)
        pin_pos, col_pos = self._trajectories(trajectories, td, dev)
        v0 = torch.zeros(self.P, 3, dtype=td, device=dev) if v0 is None else as_t(v0, None).expand(self.P, 3)
        lim = torch.cat([torch.stack([E.detach().max(), E.detach().min(), nu.detach().max(), nu.detach().min()]),
                         eff.detach()]).cpu().double()          # one host sync per call
        if not bool(torch.isfinite(lim[:4]).all()):
            raise SimulationError("got non-finite E or nu", frame=0, advice="check the material parameters")
        ev = lim[4:]
        bad = []
        for e in m.effects.enabled:
            for p_ in PARAMETERS[e]:
                v = float(ev[SLOTS[(e, p_)]])
                ok = {"coefficient": v >= 0, "yieldStress": v > 0, "height": math.isfinite(v),
                      "friction": v >= 0, "modulus": v >= 0, "relaxationTime": v > 0}[p_]
                if not ok or math.isnan(v):
                    bad.append(f"{e}.{p_} = {v:g}")
        if bad:
            raise SimulationError("got effect parameters outside their domain: " + ", ".join(bad), frame=0,
                                  advice="c, friction, modulus >= 0; yieldStress, relaxationTime > 0 (fit them "
                                         "through exp / softplus)")
        if float(lim[0]) > m.E_max * (1.0 + 1e-5):
            raise SimulationError(
                f"E up to {float(lim[0]):.4g} Pa exceeds E_max = {m.E_max:.4g} Pa, where the substep was chosen "
                "(CFL)", frame=0,
                advice="clamp E in the fit, or build the model with a larger E_max (more substeps)")
        if float(lim[1]) <= 0 or float(lim[2]) >= 0.5 or float(lim[3]) <= -1.0:
            raise SimulationError("E must be > 0 and nu in (-1, 0.5)", frame=0, advice="clamp the material parameters")
        if float(lim[2]) > m.nu_max + 1e-6:
            raise SimulationError(
                f"nu up to {float(lim[2]):.4g} exceeds nu_max = {m.nu_max:.4g}, where the substep was chosen (CFL)",
                frame=0, advice="clamp nu in the fit, or build the model with a larger nu_max")
        if F0 is not None:
            F0 = as_t(F0, None)
            if tuple(F0.shape) != (self.P, 3, 3):
                raise ValueError(f"F0 must be (P, 3, 3) = ({self.P}, 3, 3), got {tuple(F0.shape)}")
            F0 = F0.contiguous()
        return E.contiguous(), nu.contiguous(), eff, pin_pos, col_pos, v0.contiguous(), F0

    def _effect_vector(self, effects, td, dev) -> torch.Tensor:
        m = self.model
        base = m.effect_vector()
        entries: list = [torch.tensor(base[i], dtype=td, device=dev) for i in range(N_PARAMS)]
        for eff, ps in (effects or {}).items():
            if eff not in PARAMETERS:
                raise KeyError(f"unknown effect {eff!r}")
            if eff not in m.effects:
                raise ValueError(f"effect {eff!r} is off in this model; enable it (SimModel.create(effects=...) "
                                 "or model.replace(effects=...)) to give it parameters")
            for p, v in ps.items():
                slot = SLOTS[(eff, canonical(eff, p))]
                entries[slot] = (v if torch.is_tensor(v) else torch.tensor(float(v))).to(device=dev, dtype=td).reshape(())
        return torch.stack(entries)

    def _trajectories(self, trajectories, td, dev):
        c = self.control
        given: dict[int, object] = {}
        if trajectories is not None:
            if isinstance(trajectories, Mapping):
                given = dict(trajectories)
            else:
                given = {i: t for i, t in enumerate(trajectories) if t is not None}
        for i in given:
            if c.contacts[i].type == "fixed":
                raise ValueError(f"contact {i} is fixed: it has no trajectory")

        def row(i):
            t = given.get(i, c.contacts[i].trajectory)
            t = t if torch.is_tensor(t) else torch.as_tensor(np.asarray(t, dtype=np.float64))
            t = t.to(device=dev, dtype=td)
            if tuple(t.shape) != (self.T + 1, 3):
                raise ValueError(f"trajectory of contact {i} must have shape ({self.T + 1}, 3), got {tuple(t.shape)}")
            return t

        zeros = torch.zeros(self.T + 1, 3, dtype=td, device=dev)
        pins = [row(i) if c.contacts[i].type != "fixed" else zeros for i in c.pins] or [zeros]
        cols = [row(i) for i in c.colliders] or [zeros]
        return torch.stack(pins), torch.stack(cols)

    def _load_inputs(self, E, nu, eff, pin_pos, col_pos, v0, F0=None):
        K = self.solver.K
        wp.copy(self.params.E, wp.from_torch(E.detach().contiguous(), dtype=K.T))
        wp.copy(self.params.nu, wp.from_torch(nu.detach().contiguous(), dtype=K.T))
        wp.copy(self.params.eff, wp.from_torch(eff.detach().contiguous(), dtype=K.T))
        wp.copy(self.ctrl.pin_pos, wp.from_torch(pin_pos.detach().contiguous(), dtype=K.vec3))
        wp.copy(self.ctrl.col_pos, wp.from_torch(col_pos.detach().contiguous(), dtype=K.vec3))
        wp.copy(self.v0, wp.from_torch(v0.detach().contiguous(), dtype=K.vec3))
        if F0 is not None:
            wp.copy(self.F0, wp.from_torch(F0.detach().contiguous(), dtype=K.mat33))
        elif self.has_F0:              # back to the identity after a call with F0
            self._identity_F0()
        self.has_F0 = F0 is not None


class _SimulateFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, ro: Rollout, E, nu, eff, pin_pos, col_pos, v0, F0=None):
        _torch_sync(ro.model)              # the inputs torch produced are complete
        ro._load_inputs(E, nu, eff, pin_pos, col_pos, v0, F0)
        ctx.generation = ro.run_forward(store=any(ctx.needs_input_grad))
        _warp_sync(ro.model)               # Warp's work is complete before torch reads it
        saved = {k: _wclone(t) for k, t in ro.ck.t.items()}
        ctx.ro = ro
        ctx.has_F0 = F0 is not None
        ctx.save_for_backward(E, nu, eff, pin_pos, col_pos, v0, saved["x"], saved["v"], saved["C"], saved["F"],
                              saved["Fv"], *((F0,) if F0 is not None else ()))
        x, F = saved["x"], saved["F"]
        return x.view(ro.T + 1, ro.P, 3), F.view(ro.T + 1, ro.P, 3, 3)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gx, gF):
        ro: Rollout = ctx.ro
        E, nu, eff, pin_pos, col_pos, v0, x, v, C, F, Fv, *rest = ctx.saved_tensors
        F0 = rest[0] if ctx.has_F0 else None
        gx = None if gx is None else gx.detach().to(x.dtype).contiguous()
        gF = None if gF is None else gF.detach().to(x.dtype).contiguous()
        _torch_sync(ro.model)
        for k, t in zip(("x", "v", "C", "F", "Fv"), (x, v, C, F, Fv)):   # another forward may have run
            _wcopy(ro.ck.t[k], t)
        for buf, g in ((ro.grad_x, gx), (ro.grad_F, gF)):
            if g is None:
                buf.zero_()
            else:
                _wcopy(wp.to_torch(buf, requires_grad=False), g)
        ro._load_inputs(E, nu, eff, pin_pos, col_pos, v0, F0)
        adj0 = ro.run_backward(ctx.generation)
        _warp_sync(ro.model)
        gE = wp.to_torch(ro.adj_params.E).clone()
        gnu = wp.to_torch(ro.adj_params.nu).clone()
        geff = wp.to_torch(ro.adj_params.eff).clone()
        gpin = wp.to_torch(ro.adj_ctrl.pin_pos).clone()
        gcol = wp.to_torch(ro.adj_ctrl.col_pos).clone()
        gv0 = wp.to_torch(adj0.v).clone()
        gF0 = None
        if ctx.has_F0:      # through the frames, and frame 0's own F (the output's first row is F0 itself)
            gF0 = wp.to_torch(adj0.F).clone().view(ro.P, 3, 3)
            if gF is not None:
                gF0 = gF0 + gF.view(ro.T + 1, ro.P, 3, 3)[0].to(gF0.dtype)
        # effects that are off do not depend on their parameters
        on = torch.zeros(N_PARAMS, dtype=torch.bool)
        for e in ro.model.effects.enabled:
            for p in PARAMETERS[e]:
                on[SLOTS[(e, p)]] = True
        geff = torch.where(on.to(geff.device), geff, torch.zeros_like(geff))
        return None, gE, gnu, geff, gpin, gcol, gv0, gF0


# Bulk copies go through Warp: torch's intra-op thread pool makes a clone of a few 100 kB take
# milliseconds on a 2-core machine (measured: 8 ms with 2 threads vs 7 us with 1).
def _wcopy(dst: torch.Tensor, src: torch.Tensor) -> None:
    wp.copy(wp.from_torch(dst.detach().reshape(-1)), wp.from_torch(src.detach().reshape(-1)))


def _wclone(t: torch.Tensor) -> torch.Tensor:
    out = torch.empty_like(t)
    _wcopy(out, t)
    return out


# On CUDA, Warp runs on its own stream (graph capture needs a non-default stream; torch's default
# stream is the legacy one): the hand-over points sync the host, once per call (not per substep).
def _torch_sync(model) -> None:
    if str(model.device).startswith("cuda"):
        torch.cuda.synchronize(torch.device(str(model.device)))


def _warp_sync(model) -> None:
    if str(model.device).startswith("cuda"):
        wp.synchronize_device(model.device)


def simulate(model, control: Control | None = None, E=None, nu=None, effects=None, trajectories=None, v0=None,
             n_frames: int | None = None, graphs: bool = False, F0=None):
    """One-off differentiable rollout (allocates its buffers; in a loop, reuse a `Rollout`).
    Returns x (T+1, P, 3), F (T+1, P, 3, 3) as torch tensors."""
    return Rollout(model, control, n_frames=n_frames, graphs=graphs)(E, nu, effects=effects, trajectories=trajectories,
                                                                     v0=v0, F0=F0)


def effect_inputs(model, requires_grad: bool = True, dtype=torch.float64) -> dict:
    """The enabled effects' default parameters as leaf tensors {effect: {parameter: tensor}}."""
    out = {}
    for e in model.effects.enabled:
        out[e] = {p: torch.tensor(model.effects.params[e][p], dtype=dtype, requires_grad=requires_grad)
                  for p in PARAMETERS[e]}
    return out


__all__ = ["Rollout", "simulate", "Checkpoints", "effect_inputs"]
