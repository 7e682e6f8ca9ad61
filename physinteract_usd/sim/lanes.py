"""Two lanes: the CPU's second core inside one rollout's substeps (#26, docs/benchmarks/cpu.md).

Warp 1.19 runs a CPU kernel's threads one after another on the calling thread, and a frame's captured
CPU graph replays in one C++ loop (one ctypes call, which releases the GIL). With lanes on, a rollout
captures each frame twice: lane A's graph (the frame as before, its particle kernels over particles
0 .. h - 1) and lane B's (the same substeps' particle kernels over h .. P - 1), and replays them at once,
lane A on the calling thread and lane B on a worker thread. The lanes meet at barriers (a one-thread
kernel that spins on a shared counter, `barrier`), two a substep, where one needs the other's work:

- forward substep: both lanes p2g their half into their own grid (Warp's CPU atomics are plain adds,
  not thread-safe) | each lane adds lane B's grid into lane A's over its own nodes (a run of whole x slabs) and
  runs the grid update there | both gather and update their half;
- adjoint substep: both run the particle update's and the gather's adjoints over their half (lane B's
  grid-velocity, effect-parameter and pin-trajectory adjoints into buffers of its own) | each lane sums the
  grid-velocity adjoint and runs the grid update's adjoint over its nodes (lane B's effect and collider adjoints
  into its own buffers) | both run the scatter's and stress's adjoints over their half; at a frame's end lane A
  folds lane B's parameter / pin / collider adjoints in.

Results equal the one-lane run's up to float summation order (the two grids summed instead of one in
particle order; lane B's nodes placed from its first slab's corner): tests/test_sim_lanes.py. Only the CPU's per-frame graphs use lanes; eager launches,
CUDA (its launches and graphs) and the GPU's frame-shape graphs are untouched.

`LANES`: None (default) decides once per process (`auto_lanes`: two lanes where >= 2 cores are the process's
and one of them sits idle); PHYSINTERACT_SIM_LANES=1 (off) / 2 (on) in the environment sets it for a process.
"""


import ctypes
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import warp as wp

from ..errors import SimulationError
from .kernels import SCATTERED

LANES: int | None = int(os.environ["PHYSINTERACT_SIM_LANES"]) if os.environ.get("PHYSINTERACT_SIM_LANES") else None
# where LANES is None: True, two lanes where this process may run on >= 2 cores and the machine has a core to spare
# (`spare_cores`: measured once per process, at its first two-lane-capable capture); False (default): one lane.
# Off by default: on the demo's fit -8.7% at best, +2-9% in the profiled demo runs (docs/benchmarks/cpu.md session
# 19; the rollout benchmark's replays -31%, but a two-lane capture costs ~2.7x a one-lane one)
AUTO = False
# fewest particles for which lanes are worth their barriers (two per substep)
MIN_PARTICLES = 256
# the idle share of the machine's cores (besides this process's own busy thread) that counts as a core to spare
SPARE_MIN = 0.6
_AUTO: int | None = None       # the process's decision (1 or 2), once made

_BARRIER_SNIPPET = r"""
int* c = ctr.data;
int want = c[2] * n;
__atomic_fetch_add(c, 1, __ATOMIC_ACQ_REL);
long long spins = 0;
typedef wp::int32 (*yield_fn_t)();
yield_fn_t yf = (yield_fn_t)yield_fn;
while (__atomic_load_n(c, __ATOMIC_ACQUIRE) < want) {
    if (__atomic_load_n(c + 1, __ATOMIC_RELAXED) != 0) break;
    ++spins;
    if (spins < 2000 || yf == 0) {
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
    } else {
        yf();
    }
    if (spins > 40000000LL) { __atomic_store_n(c + 1, 1, __ATOMIC_RELEASE); break; }
}
"""


def _yield_address() -> int:
    """The address of libc's sched_yield (0 where there is none: the barrier only spins)."""
    try:
        libc = ctypes.CDLL(None)
        return int(ctypes.cast(libc.sched_yield, ctypes.c_void_p).value or 0)
    except (OSError, AttributeError):
        return 0


YIELD_ADDRESS = _yield_address()

_CACHE: dict = {}
_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None


def get_kernels(dtype: str) -> SimpleNamespace:
    """The lanes' kernels (a Warp module of their own: the substep's modules and their cache keys unchanged)."""
    with _LOCK:
        if dtype not in _CACHE:
            _CACHE[dtype] = _build(dtype)
    return _CACHE[dtype]


def _build(dtype: str) -> SimpleNamespace:
    T = wp.float64 if dtype == "float64" else wp.float32
    vec3 = wp.vec3d if dtype == "float64" else wp.vec3f
    module = f"physinteract_sim_lanes_{dtype}"
    wp.get_module(module).options["enable_backward"] = False

    @wp.func_native(_BARRIER_SNIPPET)
    def lane_wait(ctr: wp.array(dtype=wp.int32), n: int, yield_fn: wp.uint64): ...

    @wp.kernel(module=module, enable_backward=False)
    def barrier(ctr: wp.array(dtype=wp.int32), n: int, yield_fn: wp.uint64):
        lane_wait(ctr, n, yield_fn)

    @wp.kernel(module=module, enable_backward=False)
    def add_T(a: wp.array(dtype=T), b: wp.array(dtype=T)):
        i = wp.tid()
        a[i] = a[i] + b[i]

    @wp.kernel(module=module, enable_backward=False)
    def add_grid(m: wp.array(dtype=T), mv: wp.array(dtype=vec3), pm: wp.array(dtype=T), pmv: wp.array(dtype=vec3),
                 sm: wp.array(dtype=T),
                 bm: wp.array(dtype=T), bmv: wp.array(dtype=vec3), bpm: wp.array(dtype=T), bpmv: wp.array(dtype=vec3),
                 bsm: wp.array(dtype=T)):
        # lane B's five scatter targets added into lane A's, one launch (each launch costs a capture ~0.3 ms)
        i = wp.tid()
        m[i] = m[i] + bm[i]
        mv[i] = mv[i] + bmv[i]
        pm[i] = pm[i] + bpm[i]
        pmv[i] = pmv[i] + bpmv[i]
        sm[i] = sm[i] + bsm[i]

    return SimpleNamespace(barrier=barrier, add_T=add_T, add_grid=add_grid, module=module)


def free_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _cpu_times():
    with open("/proc/stat") as f:
        v = [int(t) for t in f.readline().split()[1:]]
    return v[3] + (v[4] if len(v) > 4 else 0), sum(v)      # idle + iowait, total


def spare_cores(interval: float = 0.1) -> float:
    """How many of the machine's cores sat idle over `interval` seconds (from /proc/stat; the calling thread
    sleeps meanwhile, so a process whose one busy thread calls this sees its own core as idle: subtract it).
    Where /proc/stat is missing: the cores this process may use, less one."""
    try:
        i0, t0 = _cpu_times()
        time.sleep(interval)
        i1, t1 = _cpu_times()
    except (OSError, ValueError, IndexError):
        return float(free_cores() - 1)
    n = os.cpu_count() or 1
    return n * (i1 - i0) / max(t1 - t0, 1) - 1.0


def auto_lanes() -> int:
    """The default lane count (LANES None): 2 where AUTO, >= 2 cores are this process's (os.sched_getaffinity)
    and at least SPARE_MIN of a core sits idle beside it; else 1. Decided once per process, so that a fit's
    rollouts all run alike (two lanes sum the grid in another order: float32 results differ in the last bits)."""
    global _AUTO
    if _AUTO is None:
        _AUTO = 2 if (AUTO and free_cores() >= 2 and spare_cores() >= SPARE_MIN) else 1
    return _AUTO


def wanted(solver) -> bool:
    """Whether a rollout on this solver replays its frames on two lanes: on the CPU only, with the CPU's
    kernel choices (separate transfers, memsets, no grid box, no rate transfer), >= MIN_PARTICLES
    particles, and LANES = 2 (LANES None: `auto_lanes`)."""
    if not (wp.get_device(solver.device).is_cpu and not solver.fused_kernels and not solver.fused_zero
            and not solver.grid_box and solver.rate_f == 0 and solver.model.n_particles >= MIN_PARTICLES):
        return False
    n = LANES if LANES is not None else auto_lanes()
    return int(n) >= 2


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="physinteract-lane-b")
    return _POOL


class Lanes:
    """A solver's second lane: its particle range, its own scatter targets and adjoint accumulators, and
    the barrier counter ([arrivals, timed out, lanes running, -])."""

    def __init__(self, solver):
        self.sol = solver
        K = solver.K
        d = solver.device
        P = solver.model.n_particles
        self.LK = get_kernels(solver.model.dtype)
        wp.load_module(wp.get_module(self.LK.module), device=d)    # never inside a capture
        h = P // 2
        self.ranges = ((0, h), (h, P))
        self.ctr = wp.zeros(4, dtype=wp.int32, device=d)
        self._ctr_np = self.ctr.numpy()               # a view of the CPU array
        res = solver.res
        self.gm = wp.zeros(res, dtype=K.T, device=d)
        self.gmv = wp.zeros(res, dtype=K.vec3, device=d)
        self.gpm = wp.zeros(res, dtype=K.T, device=d)
        self.gpmv = wp.zeros(res, dtype=K.vec3, device=d)
        self.gsm = wp.zeros(res, dtype=K.T, device=d)
        self.box_flag = wp.zeros(1, dtype=wp.int32, device=d)
        self.flat = {k: getattr(self, k).flatten() for k in SCATTERED}
        # lane B's adjoint accumulators: the grid velocity's, the effect parameters' (N_PARAMS), the pins'
        # trajectories' (the shape of the solver's controls). Allocated here, never in a capture: on the CPU a
        # capture records an allocation's memset into the graph (it would run at every replay, racing the lane)
        self.a_gv = wp.zeros(res, dtype=K.vec3, device=d)
        self.a_gv_flat = self.a_gv.flatten()
        self.a_eff = wp.zeros(solver.params.eff.shape[0], dtype=K.T, device=d)
        self.a_pin = wp.zeros_like(solver.ctrl.pin_pos)
        self.a_col = wp.zeros_like(solver.ctrl.col_pos)
        # the grid's nodes split between the lanes at a whole x slab (flat index = (i * ny + j) * nz + k): each lane
        # sums and updates (and reverses the update of) its own nodes, its slab offset moved into the grid's corner
        ny, nz = res[1], res[2]
        i_mid = res[0] // 2
        self.node_ranges = ((0, i_mid * ny * nz), (i_mid * ny * nz, res[0] * ny * nz))
        self.slab0 = (0, i_mid)
        self._views: dict = {}        # (id(array), lane[, "n"]) -> (array, its view): `part`, `nodes`

    def part(self, a, lane: int):
        """Lane `lane`'s particles of per-particle array `a`: a view, made once per array (a capture slices
        thousands of arrays, and a Warp view costs ~25 us of Python)."""
        key = (id(a), lane)
        hit = self._views.get(key)
        if hit is None or hit[0] is not a:
            lo, hi = self.ranges[lane]
            hit = self._views[key] = (a, a[lo:hi])
        return hit[1]

    def nodes(self, a, lane: int):
        """Lane `lane`'s nodes of a flat grid array (`node_ranges`), made once per array."""
        key = (id(a), lane, "n")
        hit = self._views.get(key)
        if hit is None or hit[0] is not a:
            lo, hi = self.node_ranges[lane]
            hit = self._views[key] = (a, a[lo:hi])
        return hit[1]

    def check_adj(self, adj_params, adj_ctrl) -> None:
        """The adjoints a captured adjoint accumulates into match lane B's buffers (made before any capture)."""
        if (adj_params.eff.shape != self.a_eff.shape or adj_ctrl.pin_pos.shape != self.a_pin.shape
                or adj_ctrl.col_pos.shape != self.a_col.shape):
            raise RuntimeError("two lanes: the adjoint's parameter / pin shapes differ from the solver's controls")

    def arm(self, n_lanes: int) -> None:
        self._ctr_np[:] = (0, 0, n_lanes, 0)

    def timed_out(self) -> bool:
        return bool(self._ctr_np[1])

    def replay(self, pair) -> None:
        """Replay a frame's two graphs at once (lane B on the worker thread); a timed-out barrier (a lane
        that never came) raises."""
        self.a_eff.zero_()
        self.a_pin.zero_()
        self.a_col.zero_()
        self.arm(2)
        fut = _pool().submit(wp.capture_launch, pair.b)
        try:
            wp.capture_launch(pair.a)
        finally:
            fut.result()
        if self.timed_out():
            raise SimulationError("the simulator's two lanes lost each other (a barrier timed out)",
                                  advice="run with PHYSINTERACT_SIM_LANES=1", kind="unstable")


class LanePair:
    """A frame's two captured graphs (lane A's, lane B's)."""

    __slots__ = ("a", "b")

    def __init__(self, a, b):
        self.a, self.b = a, b


class Recorder:
    """While a rollout captures a frame on two lanes: lane A's launches run (are captured) as they are
    issued, lane B's are kept (`ops`) and captured after, in the same order, barriers included."""

    def __init__(self, lanes: Lanes):
        self.lanes = lanes
        self.ops: list = []
        self.n_barriers = 0
        self.kind = None          # the kind of the last lane op ("step", "adj"); None: synced
        self.pending = False      # lane ops issued since the last barrier

    def barrier(self) -> None:
        self.n_barriers += 1
        L = self.lanes
        args = (L.LK.barrier, 1, [L.ctr, self.n_barriers, wp.uint64(YIELD_ADDRESS)])
        wp.launch(*args, device=L.sol.device, record_tape=False)
        self.ops.append(("launch", args))
        self.pending = False

    def enter(self, kind: str) -> None:
        """Before a substep's lane ops: a barrier where lane A did other work since the last one (the
        frame's start, or a forward's substeps before an adjoint's)."""
        if self.kind != kind:
            self.barrier()
            self.kind = kind

    def sync(self) -> None:
        """Before lane A reads what both lanes wrote (the frame's check, its end)."""
        if self.pending:
            self.barrier()
        self.kind = None

    def launch(self, lane: int, kernel, dim, inputs, outputs=(), **kw) -> None:
        args = (kernel, dim, list(inputs), list(outputs))
        kw = dict(kw, device=self.lanes.sol.device, record_tape=False)
        if lane == 0:
            wp.launch(*args, **kw)
        else:
            self.ops.append(("launch_kw", (args, kw)))
        self.pending = True

    def zero(self, lane: int, *arrays) -> None:
        for a in arrays:
            if lane == 0:
                a.zero_()
            else:
                self.ops.append(("zero", a))

    def replay_b(self) -> None:
        """Issue lane B's kept ops (inside lane B's capture)."""
        d = self.lanes.sol.device
        for kind, a in self.ops:
            if kind == "launch":
                wp.launch(*a, device=d, record_tape=False)
            elif kind == "launch_kw":
                wp.launch(*a[0], **a[1])
            else:
                a.zero_()

