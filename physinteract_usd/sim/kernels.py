"""Warp kernels of the MLS-MPM simulator, generic over float32 / float64.

`get_kernels(dtype)` builds (once per dtype) a namespace of kernels in Warp modules per dtype
(``physinteract_sim_float32`` / ``physinteract_sim_float64``, the substep's kernels, and beside them
``..._adj``, ``..._rate``, ``..._cuda``, ``..._test``: `_build` says which is whose; Warp compiles a
module whole, at its first launch). One substep is five launches:

    p2g_stress(state_s)           -> A = -dt V0 (4/dx^2) tau + m C per particle (tau: Kirchhoff stress)
    p2g_scatter(state_s, A)       -> grid mass / momentum (+ mass and momentum of pinned particles, supports' mass)
    grid_update(grid)             -> grid velocity (gravity, damping, pins, ground, moving colliders)
    g2p_gather(state_s, grid v)   -> v, C at the particles (APIC)
    g2p_update(state_s, v, C)     -> state_{s+1} (x, F, plasticity, Maxwell branch, pinned particles)

Every kernel reads its inputs and writes separate outputs, so the reverse pass can launch
adjoints directly after recomputing the grid of a substep from the stored particle state. The
grid update, the particle update and the Maxwell branch's stress (p2g_stress_visco) use Warp's
generated adjoints (`wp.launch(..., adjoint=True)`); the equilibrium stress and the two transfers
have hand-written adjoints (p2g_stress_adj; p2g_scatter_adj, g2p_gather_adj: gathers / scatters of
the grid adjoints), and the kernels they reverse are compiled without backward code.

Functions of F whose textbook derivative goes through the SVD carry hand-written adjoints
(`wp.func_grad`), finite at repeated singular values (F = I at rest):
- the polar rotation R(F): computed by Higham's scaled Newton iteration, adjoint
  adj_F = R [y]x with (tr(S) I - S) y = axial(R^T adj_R - adj_R^T R), S = R^T F;
- the Hencky-strain functions (plastic return mapping, Maxwell relaxation and stress), written as
  isotropic matrix functions G(F) = U diag(g(sigma)) V^T, whose adjoint uses

    diag:      dG^_ii = sum_j dg_i/dsigma_j dF^_jj
    off-diag:  dG^_ij = (a + b)/2 dF^_ij + (a - b)/2 dF^_ji,
               a = (g_i - g_j)/(sigma_i - sigma_j),  b = (g_i + g_j)/(sigma_i + sigma_j)

  with a in closed form (no 0/0 when singular values coincide) instead of the derivatives of U
  and V, which blow up there (1/(sigma_i^2 - sigma_j^2)).
"""



import atexit
import math
import threading
from types import SimpleNamespace

import warp as wp

# flags (bit mask passed to the kernels at run time: one compiled kernel serves every combination)
F_DAMPING = 1
F_PLASTICITY = 2
F_GROUND = 4
F_VISCO = 8
F_GROUND_PENALTY = 16   # the ground acts at the particles (ground_impulse), not at the grid nodes (SimModel.ground_contact)
# the particle ground's push (kernels.ground_impulse): an acceleration GROUND_K g u / sp at depth u for a particle of
# spacing sp (a Winkler floor of modulus GROUND_K rho g: a column of height H sinks H / GROUND_K, whatever the grid and
# the substep, so a truth and its coarser fit sink alike), at most GROUND_BETA u / dt^2 (stability: the share of the
# depth one substep's push would remove). Stiffer brakes a roll, softer sinks deeper: tests/test_rolling_ball.py, docs/sim.md
GROUND_K = 100.0
GROUND_BETA = 0.05

# slots of the effect parameter vector (see effects.py)
I_DAMP_C = 0
I_YIELD = 1
I_GROUND_H = 2
I_GROUND_MU = 3
I_VISCO_E = 4
I_VISCO_TAU = 5
N_EFFECT_PARAMS = 6

# constitutive models
M_FIXED_COROTATED = 0
M_NEO_HOOKEAN = 1

# collider shapes (non-adherent contacts)
S_SPHERE = 0
S_CAPSULE = 1
S_PLANE = 2

MAX_COLLIDERS = 4  # non-adherent contacts per scene (unrolled in the grid kernel)

# the grid's scatter targets (p2g's outputs, zeroed per substep): mass, momentum, the pinned particles' mass and
# momentum, the mass of those a support (a fixed contact) holds (its share picks the support's pin rule)
SCATTERED = ("gm", "gmv", "gpm", "gpmv", "gsm")

# status columns written by the check kernel, per frame
ST_NONFINITE = 0
ST_OUTSIDE = 1
ST_NONFINITE_P = 2
ST_OUTSIDE_P = 3
# a particle whose quadratic stencil was clamped to the grid's last nodes at some substep of the frame (it
# passed the valid box mid-frame: its B-spline weights are evaluated outside their support, a wrong state
# that blows up within ~a cell; #24): how many, the farthest past (in 1/1000 cells), one of them
ST_CLAMPED = 4
ST_CLAMPED_PAST = 5
ST_CLAMPED_P = 6
N_STATUS = 7

_CACHE = {}


_BUILD_LOCK = threading.Lock()
_PRELOAD: dict = {}    # dtype -> the thread compiling its modules (`preload`)


def get_kernels(dtype: str) -> SimpleNamespace:
    """The kernels for ``dtype`` in {"float32", "float64"} (built once, then cached). Where `preload`
    is compiling them on another thread, waits for it first: whatever launches a kernel asked for
    them here, so no module is compiled twice at once."""
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be float32 or float64, not {dtype!r}")
    t = _PRELOAD.get(dtype)
    if t is not None and t is not threading.current_thread():
        t.join()
        _PRELOAD.pop(dtype, None)
    if dtype not in _CACHE:
        with _BUILD_LOCK:
            if dtype not in _CACHE:
                _CACHE[dtype] = _build(dtype)
    return _CACHE[dtype]


def preload(device, dtype: str = "float32", backward: bool = True) -> None:
    """Compile (or load from Warp's kernel cache) the modules a rollout on the CPU launches, on a
    background thread, while the caller does other work (a fit reads its stage and extracts the
    interaction first); the next `get_kernels(dtype)` waits for it. The substep's module, then with
    ``backward`` the hand-written adjoints', one after the other on one thread (Warp's compiler calls
    release the GIL; two compiling threads beside the caller cost ~20% more CPU on a busy 2-core
    machine): on a fresh machine the first fit compiles ~10 s of CPU work before its first substep
    (docs/benchmarks/cpu.md, #26). A failure here is left to the launch that needs the module; a
    no-op on CUDA (the same preload there, with the CUDA context on the thread, measured no gain on the
    H200: 22.3 s with and without, docs/benchmarks/gpu.md session 17; removed) and when a preload or the
    kernels already ran."""
    if not str(device).startswith("cpu") or dtype in _CACHE or dtype in _PRELOAD:
        return

    def run():
        try:
            K = get_kernels(dtype)
            names = [K.modules.core] + ([K.modules.adj] if backward else [])
            wp.force_load(device=device, modules=[wp.get_module(n) for n in names], max_workers=0)
        except Exception:    # noqa: BLE001  (the launch that needs the module compiles it again and raises)
            pass

    t = threading.Thread(target=run, name=f"physinteract-preload-{dtype}", daemon=True)
    _PRELOAD[dtype] = t
    t.start()
    atexit.register(t.join)    # never leave the process while the compiler runs on that thread


def _build(name: str) -> SimpleNamespace:  # noqa: C901  (one closure per dtype)
    if name == "float64":
        T = wp.float64
        vec3 = wp.vec3d
        mat33 = wp.mat33d
    else:
        T = wp.float32
        vec3 = wp.vec3f
        mat33 = wp.mat33f
    # Warp compiles a module whole, at its first launch: the kernels are split by who launches them, so a
    # run compiles only what it uses (a fresh machine's first fit compiled every kernel of one module,
    # ~40% of them never launched on the CPU; docs/benchmarks/cpu.md, #26). `modules` names them all.
    module = f"physinteract_sim_{name}"             # every forward substep (+ generated adjoints)
    module_adj = f"physinteract_sim_{name}_adj"     # the hand-written adjoints: a backward
    module_rate = f"physinteract_sim_{name}_rate"   # the rate transfer (SimModel.transfer_tau > 0)
    module_cuda = f"physinteract_sim_{name}_cuda"   # fused transfers, grid box, fused zeroing (CUDA defaults)
    module_test = f"physinteract_sim_{name}_test"   # eval_matfuncs (the gradient tests')
    for m in (module_adj, module_rate):             # forward-only kernels: no adjoint code to build
        wp.get_module(m).options["enable_backward"] = False
    SIG_EPS = 1.0e-6
    POLAR_MAX_IT = 30
    POLAR_MIN_DET = 1.0e-4
    POLAR_TOL2 = 1.0e-16 if name == "float64" else 1.0e-8
    SQRT_2_3 = math.sqrt(2.0 / 3.0)

    # ------------------------------------------------------------------ scalar helpers
    @wp.func
    def expm1_over_x(x: T):
        # h(x) = (exp(x) - 1) / x, smooth through 0
        if wp.abs(x) < T(1.0e-2):
            return T(1.0) + x * (T(0.5) + x * (T(1.0 / 6.0) + x * (T(1.0 / 24.0) + x * T(1.0 / 120.0))))
        return (wp.exp(x) - T(1.0)) / x

    @wp.func
    def safe_den(d: T):
        # keep |d| >= eps with its sign (sums of singular values of an inverted F)
        if wp.abs(d) < T(SIG_EPS):
            if d < T(0.0):
                return T(-SIG_EPS)
            return T(SIG_EPS)
        return d

    @wp.func
    def logs(s: vec3):
        return vec3(wp.log(wp.max(s[0], T(SIG_EPS))), wp.log(wp.max(s[1], T(SIG_EPS))),
                    wp.log(wp.max(s[2], T(SIG_EPS))))

    @wp.func
    def iso_adjoint(U: mat33, s: vec3, V: mat33, adj_G: mat33, g: vec3, Jg: mat33, A: mat33):
        # adjoint of G = U diag(g(s)) V^T: Jg[i, j] = dg_i/ds_j, A[i, j] = (g_i - g_j)/(s_i - s_j)
        Gh = wp.transpose(U) * adj_G * V
        R = mat33()
        for i in range(3):
            for j in range(3):
                if i == j:
                    R[i, i] = Jg[0, i] * Gh[0, 0] + Jg[1, i] * Gh[1, 1] + Jg[2, i] * Gh[2, 2]
                else:
                    b = (g[i] + g[j]) / safe_den(s[i] + s[j])
                    a = A[i, j]
                    R[i, j] = T(0.5) * (a + b) * Gh[i, j] + T(0.5) * (a - b) * Gh[j, i]
        return U * R * wp.transpose(V)

    # ------------------------------------------------------------------ polar rotation
    # R of F = R S by Higham's scaled Newton iteration (cheaper than the SVD on the CPU; converged
    # to round-off), the SVD for inverted or degenerate F. The adjoint needs no SVD either:
    # dR = R [w]x with (tr(S) I - S) w = axial(R^T dF - dF^T R), so
    # adj_F = R [y]x with (tr(S) I - S) y = axial2(R^T adj_R).
    @wp.func
    def polar_R(F: mat33):
        X = F
        if wp.determinant(F) > T(POLAR_MIN_DET):
            for it in range(POLAR_MAX_IT):
                Xi = wp.inverse(X)
                g = wp.sqrt(wp.sqrt(wp.ddot(Xi, Xi) / wp.ddot(X, X)))
                Xn = T(0.5) * (g * X + (T(1.0) / g) * wp.transpose(Xi))
                dX = Xn - X
                X = Xn
                if wp.ddot(dX, dX) < T(POLAR_TOL2):
                    break
            # one more (unscaled) step: quadratic convergence takes the residual to round-off
            X = T(0.5) * (X + wp.transpose(wp.inverse(X)))
        else:
            U = mat33()
            s = vec3()
            V = mat33()
            wp.svd3(F, U, s, V)
            X = U * wp.transpose(V)
        return X

    @wp.func
    def polar_vjp(F: mat33, R: mat33, adj_R: mat33):
        # adj_F of R = polar(F), given adj_R
        S = wp.transpose(R) * F
        S = T(0.5) * (S + wp.transpose(S))
        A = wp.trace(S) * wp.identity(n=3, dtype=T) - S
        X = wp.transpose(R) * adj_R
        h = vec3(X[2, 1] - X[1, 2], X[0, 2] - X[2, 0], X[1, 0] - X[0, 1])
        out = mat33()
        if wp.abs(wp.determinant(A)) > T(1.0e-12):
            y = wp.inverse(A) * h
            out = R * mat33(T(0.0), -y[2], y[1], y[2], T(0.0), -y[0], -y[1], y[0], T(0.0))
        return out

    @wp.func_grad(polar_R)
    def adj_polar_R(F: mat33, adj_ret: mat33):
        wp.adjoint[F] += polar_vjp(F, polar_R(F), adj_ret)

    # ------------------------------------------------------------------ deviatoric Hencky strain
    @wp.func
    def dev_norm(F: mat33):
        # |dev(log sigma)|: the norm of the deviatoric Hencky strain
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        e = logs(s)
        em = (e[0] + e[1] + e[2]) / T(3.0)
        d = e - vec3(em, em, em)
        return wp.sqrt(wp.dot(d, d))

    @wp.func_grad(dev_norm)
    def adj_dev_norm(F: mat33, adj_ret: T):
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        e = logs(s)
        em = (e[0] + e[1] + e[2]) / T(3.0)
        d = e - vec3(em, em, em)
        n = wp.sqrt(wp.dot(d, d))
        if n > T(0.0):
            D = mat33()
            for i in range(3):
                D[i, i] = adj_ret * d[i] / (n * wp.max(s[i], T(SIG_EPS)))
            wp.adjoint[F] += U * D * wp.transpose(V)

    @wp.func
    def dev_scale(F: mat33, c: T):
        # U exp(mean(e) + c dev(e)) V^T, e = log sigma: scales the deviatoric Hencky strain by c
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        e = logs(s)
        em = (e[0] + e[1] + e[2]) / T(3.0)
        D = mat33()
        for i in range(3):
            D[i, i] = wp.exp(em + c * (e[i] - em))
        return U * D * wp.transpose(V)

    @wp.func_grad(dev_scale)
    def adj_dev_scale(F: mat33, c: T, adj_ret: mat33):
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        sc = vec3(wp.max(s[0], T(SIG_EPS)), wp.max(s[1], T(SIG_EPS)), wp.max(s[2], T(SIG_EPS)))
        e = logs(s)
        em = (e[0] + e[1] + e[2]) / T(3.0)
        g = vec3()
        for i in range(3):
            g[i] = wp.exp(em + c * (e[i] - em))
        Jg = mat33()
        A = mat33()
        for i in range(3):
            for j in range(3):
                dij = T(0.0)
                if i == j:
                    dij = T(1.0)
                Jg[i, j] = g[i] / sc[j] * ((T(1.0) - c) / T(3.0) + c * dij)
                if i != j:
                    L = e[i] - e[j]
                    A[i, j] = c * g[j] / sc[j] * expm1_over_x(c * L) / expm1_over_x(L)
        wp.adjoint[F] += iso_adjoint(U, s, V, adj_ret, g, Jg, A)
        Gh = wp.transpose(U) * adj_ret * V
        wp.adjoint[c] += Gh[0, 0] * g[0] * (e[0] - em) + Gh[1, 1] * g[1] * (e[1] - em) + Gh[2, 2] * g[2] * (e[2] - em)

    # ------------------------------------------------------------------ Maxwell branch stress
    @wp.func
    def maxwell_P(F: mat33, mu_v: T):
        # first Piola stress of the Hencky branch's deviatoric part: U diag(2 mu_v dev(e)_i / s_i) V^T
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        e = logs(s)
        em = (e[0] + e[1] + e[2]) / T(3.0)
        D = mat33()
        for i in range(3):
            D[i, i] = T(2.0) * mu_v * (e[i] - em) / wp.max(s[i], T(SIG_EPS))
        return U * D * wp.transpose(V)

    @wp.func_grad(maxwell_P)
    def adj_maxwell_P(F: mat33, mu_v: T, adj_ret: mat33):
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        sc = vec3(wp.max(s[0], T(SIG_EPS)), wp.max(s[1], T(SIG_EPS)), wp.max(s[2], T(SIG_EPS)))
        e = logs(s)
        em = (e[0] + e[1] + e[2]) / T(3.0)
        g = vec3()
        for i in range(3):
            g[i] = T(2.0) * mu_v * (e[i] - em) / sc[i]
        Jg = mat33()
        A = mat33()
        for i in range(3):
            for j in range(3):
                if i == j:
                    Jg[i, i] = T(2.0) * mu_v * ((T(2.0) / T(3.0)) / (sc[i] * sc[i]) - (e[i] - em) / (sc[i] * sc[i]))
                else:
                    Jg[i, j] = T(2.0) * mu_v * (T(-1.0) / T(3.0)) / (sc[i] * sc[j])
                    L = e[i] - e[j]
                    A[i, j] = T(2.0) * mu_v * (T(1.0) / expm1_over_x(L) - (e[j] - em)) / (sc[i] * sc[j])
        wp.adjoint[F] += iso_adjoint(U, s, V, adj_ret, g, Jg, A)
        Gh = wp.transpose(U) * adj_ret * V
        wp.adjoint[mu_v] += T(2.0) * (Gh[0, 0] * (e[0] - em) / sc[0] + Gh[1, 1] * (e[1] - em) / sc[1]
                                       + Gh[2, 2] * (e[2] - em) / sc[2])

    # ------------------------------------------------------------------ constitutive models
    @wp.func
    def lame(E: T, nu: T):
        mu = E / (T(2.0) * (T(1.0) + nu))
        lam = E * nu / ((T(1.0) + nu) * (T(1.0) - T(2.0) * nu))
        return mu, lam

    @wp.func
    def kirchhoff(F: mat33, mu: T, lam: T, material: int):
        # tau = P F^T of the equilibrium branch
        J = wp.determinant(F)
        I = wp.identity(n=3, dtype=T)
        if material == 1:
            Jc = wp.max(J, T(1.0e-6))
            return mu * (F * wp.transpose(F) - I) + (lam * wp.log(Jc)) * I
        R = polar_R(F)
        return (T(2.0) * mu) * (F - R) * wp.transpose(F) + (lam * (J - T(1.0)) * J) * I

    # ------------------------------------------------------------------ B-spline
    @wp.func
    def bw(i: int, f: T):
        if i == 0:
            return T(0.5) * (T(1.5) - f) * (T(1.5) - f)
        if i == 1:
            return T(0.75) - (f - T(1.0)) * (f - T(1.0))
        return T(0.5) * (f - T(0.5)) * (f - T(0.5))

    @wp.func
    def dbw(i: int, f: T):
        # d bw(i, f) / df
        if i == 0:
            return f - T(1.5)
        if i == 1:
            return T(-2.0) * (f - T(1.0))
        return f - T(0.5)

    @wp.func
    def cell_base(xp: vec3, res: wp.vec3i):
        return wp.vec3i(wp.clamp(int(wp.floor(xp[0] - T(0.5))), 0, res[0] - 3),
                        wp.clamp(int(wp.floor(xp[1] - T(0.5))), 0, res[1] - 3),
                        wp.clamp(int(wp.floor(xp[2] - T(0.5))), 0, res[2] - 3))

    @wp.func
    def mark_clamped(p: int, xp: vec3, walk: T, J: T, res: wp.vec3i, clamped: wp.array(dtype=int)):
        # a particle outside the valid box (0.5 <= xp < res - 1.5 in cells: where cell_base clamps nothing) that
        # walked there in a sane state (`walk`: its speed x dt in cells < 0.5, J = det F in (1/4, 4): not a state
        # already blowing up, whose particles fly out at many cells a substep or with F exploding: that is the
        # step's instability, not the grid's size; tests/test_sim_physics.py) marks how far past
        # it is, in 1/1000 cells + 1, in its own entry (the largest over the frame's substeps; the frame's check
        # counts and clears it): no atomics, no host sync
        past = T(-1.0)
        for d in range(3):
            past = wp.max(past, wp.max(T(0.5) - xp[d], xp[d] - (T(float(res[d])) - T(1.5))))
        if past >= T(0.0) and walk < T(0.5) and J > T(0.25) and J < T(4.0):
            clamped[p] = wp.max(clamped[p], int(wp.min(past, T(1.0e6)) * T(1000.0)) + 1)

    @wp.func
    def out_of_box(base: wp.vec3i, box: wp.array(dtype=wp.vec3i)):
        # whether a stencil (nodes base .. base + 2) leaves the grid box [box[0], box[0] + box[1])
        b0 = box[0]
        b1 = b0 + box[1]
        return (base[0] < b0[0] or base[1] < b0[1] or base[2] < b0[2]
                or base[0] + 3 > b1[0] or base[1] + 3 > b1[1] or base[2] + 3 > b1[2])

    @wp.func
    def box_span(tid: int, nthr: int, contig: int, box: wp.array(dtype=wp.vec3i), res: wp.vec3i):
        # the indices q that thread tid of nthr visits (decoded by box_node), as (start, stop, step).
        # contig != 0 (the CPU): a run of ceil(n / nthr) consecutive flat node indices of the whole grid,
        # the runs of the whole-grid kernels (grid_update), so that nodes are visited (and Warp's
        # generated adjoints accumulate, in reverse within a run) in the same order whatever the box:
        # the box is bitwise the whole grid; box_node says which are in the box. contig == 0 (a GPU):
        # a grid-stride loop over the box's nodes, row-major over its extent (coalesced; atomics add in
        # no fixed order there anyway). Either way any nthr covers the box: a graph captured with one
        # box stays valid when the (device-side) box changes.
        if contig != 0:
            n = res[0] * res[1] * res[2]
            run = (n + nthr - 1) / nthr
            start = tid * run
            return start, wp.min(start + run, n), 1
        e = box[1]
        return tid, e[0] * e[1] * e[2], nthr

    @wp.func
    def box_node(q: int, contig: int, box: wp.array(dtype=wp.vec3i), res: wp.vec3i):
        # index q of box_span -> node (i, j, k), its flat index in the grid, and whether it is in the box
        b0 = box[0]
        e = box[1]
        if contig != 0:
            i = q / (res[1] * res[2])
            j = (q / res[2]) % res[1]
            k = q % res[2]
            inside = (i >= b0[0] and j >= b0[1] and k >= b0[2]
                      and i < b0[0] + e[0] and j < b0[1] + e[1] and k < b0[2] + e[2])
            return i, j, k, q, inside
        i = b0[0] + q / (e[1] * e[2])
        j = b0[1] + (q / e[2]) % e[1]
        k = b0[2] + q % e[2]
        return i, j, k, (i * res[1] + j) * res[2] + k, True

    # ------------------------------------------------------------------ contact helpers
    @wp.func
    def soft_weight(phi: T, band: T):
        # 1 inside (phi <= -band/2), 0 outside (phi >= band/2), C1 smoothstep between
        if band <= T(0.0):
            if phi < T(0.0):
                return T(1.0)
            return T(0.0)
        t = wp.clamp(T(0.5) - phi / band, T(0.0), T(1.0))
        return t * t * (T(3.0) - T(2.0) * t)

    @wp.func
    def collide(v: vec3, vc: vec3, n: vec3, mu: T, w: T):
        # push-only contact with Coulomb friction, blended by the weight w
        vr = v - vc
        vn = wp.dot(vr, n)
        if vn < T(0.0):
            vt = vr - vn * n
            lt2 = wp.dot(vt, vt)
            lim = mu * vn
            vr_new = vec3()
            if lt2 > lim * lim:
                lt = wp.sqrt(lt2)
                vr_new = vt * (T(1.0) + lim / lt)
            return v + w * (vc + vr_new - v)
        return v

    # ------------------------------------------------------------------ kernels
    @wp.func
    def affine_A(p: int, F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33), C: wp.array(dtype=mat33),
                 mass: wp.array(dtype=T), vol: wp.array(dtype=T), E: wp.array(dtype=T), nu: wp.array(dtype=T),
                 eff: wp.array(dtype=T), flags: int, material: int, inv_dx: T, dt: T):
        # the MLS-MPM affine matrix: -dt V0 (4 / dx^2) tau + m C, tau the Kirchhoff stress
        nup = nu[p]
        mu, lam = lame(E[p], nup)
        tau = kirchhoff(F[p], mu, lam, material)
        if (flags & 8) != 0:
            mu_v = eff[4] / (T(2.0) * (T(1.0) + nup))
            Fvp = Fv[p]
            tau = tau + maxwell_P(Fvp, mu_v) * wp.transpose(Fvp)
        return (-dt * vol[p] * T(4.0) * inv_dx * inv_dx) * tau + mass[p] * C[p]

    @wp.kernel(module=module, enable_backward=False)
    def p2g_stress(F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33), C: wp.array(dtype=mat33),
                   mass: wp.array(dtype=T), vol: wp.array(dtype=T), E: wp.array(dtype=T), nu: wp.array(dtype=T),
                   eff: wp.array(dtype=T), flags: int, material: int, inv_dx: T, dt: T,
                   A: wp.array(dtype=mat33)):
        p = wp.tid()
        A[p] = affine_A(p, F, Fv, C, mass, vol, E, nu, eff, flags, material, inv_dx, dt)

    @wp.kernel(module=module_adj, enable_backward=False)
    def p2g_stress_adj(F: wp.array(dtype=mat33), mass: wp.array(dtype=T), vol: wp.array(dtype=T),
                       E: wp.array(dtype=T), nu: wp.array(dtype=T), material: int, inv_dx: T, dt: T,
                       adj_A: wp.array(dtype=mat33),
                       adj_F: wp.array(dtype=mat33), adj_C: wp.array(dtype=mat33), adj_E: wp.array(dtype=T),
                       adj_nu: wp.array(dtype=T)):
        # hand-written adjoint of the equilibrium part of p2g_stress (A = s tau(F) + m C):
        # accumulates into adj_F, adj_C, adj_E, adj_nu (the Maxwell branch: p2g_stress_visco)
        p = wp.tid()
        Ab = adj_A[p]
        s = -dt * vol[p] * T(4.0) * inv_dx * inv_dx
        tb = s * Ab                      # adjoint of tau
        e = E[p]
        n = nu[p]
        mu, lam = lame(e, n)
        Fp = F[p]
        J = wp.determinant(Fp)
        I = wp.identity(n=3, dtype=T)
        trt = wp.trace(tb)
        gF = mat33()
        gmu = T(0.0)
        glam = T(0.0)
        if material == 1:
            # tau = mu (F F^T - I) + lam log J I
            gF = mu * (tb * Fp + wp.transpose(tb) * Fp)
            gmu = wp.ddot(tb, Fp * wp.transpose(Fp) - I)
            if J > T(1.0e-6):
                gF = gF + (lam * trt) * wp.transpose(wp.inverse(Fp))
                glam = wp.log(J) * trt
        else:
            # tau = 2 mu (F - R) F^T + lam (J - 1) J I
            R = polar_R(Fp)
            gF = (T(2.0) * mu) * (tb * Fp + wp.transpose(tb) * Fp - wp.transpose(tb) * R)
            gF = gF + polar_vjp(Fp, R, (T(-2.0) * mu) * (tb * Fp))
            # dJ = <cof(F), dF>, cof(F) = J F^-T (written without the inverse: adjugate transposed)
            cof = mat33(Fp[1, 1] * Fp[2, 2] - Fp[1, 2] * Fp[2, 1], Fp[1, 2] * Fp[2, 0] - Fp[1, 0] * Fp[2, 2],
                        Fp[1, 0] * Fp[2, 1] - Fp[1, 1] * Fp[2, 0],
                        Fp[0, 2] * Fp[2, 1] - Fp[0, 1] * Fp[2, 2], Fp[0, 0] * Fp[2, 2] - Fp[0, 2] * Fp[2, 0],
                        Fp[0, 1] * Fp[2, 0] - Fp[0, 0] * Fp[2, 1],
                        Fp[0, 1] * Fp[1, 2] - Fp[0, 2] * Fp[1, 1], Fp[0, 2] * Fp[1, 0] - Fp[0, 0] * Fp[1, 2],
                        Fp[0, 0] * Fp[1, 1] - Fp[0, 1] * Fp[1, 0])
            gF = gF + (lam * (T(2.0) * J - T(1.0)) * trt) * cof
            gmu = T(2.0) * wp.ddot(tb, (Fp - R) * wp.transpose(Fp))
            glam = (J - T(1.0)) * J * trt
        adj_F[p] = adj_F[p] + gF
        adj_C[p] = adj_C[p] + mass[p] * Ab
        one_n = T(1.0) + n
        one_2n = T(1.0) - T(2.0) * n
        adj_E[p] = adj_E[p] + gmu / (T(2.0) * one_n) + glam * n / (one_n * one_2n)
        adj_nu[p] = adj_nu[p] - gmu * e / (T(2.0) * one_n * one_n) \
            + glam * e * (T(1.0) + T(2.0) * n * n) / (one_n * one_n * one_2n * one_2n)

    @wp.kernel(module=module)
    def p2g_stress_visco(Fv: wp.array(dtype=mat33), vol: wp.array(dtype=T), nu: wp.array(dtype=T),
                         eff: wp.array(dtype=T), inv_dx: T, dt: T, A: wp.array(dtype=mat33)):
        # the Maxwell branch's part of p2g_stress, launched (as an adjoint) only when it is on
        p = wp.tid()
        mu_v = eff[4] / (T(2.0) * (T(1.0) + nu[p]))
        Fvp = Fv[p]
        A[p] = (-dt * vol[p] * T(4.0) * inv_dx * inv_dx) * (maxwell_P(Fvp, mu_v) * wp.transpose(Fvp))

    @wp.func
    def pin_velocity(p: int, pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int),
                     pin_pos: wp.array2d(dtype=vec3), frame: int, fps: T):
        # (pinned?, prescribed velocity) of particle p in frame ``frame``
        cid = pin_id[p]
        if cid >= 0:
            if pin_active[cid, frame] != 0:
                return 1, (pin_pos[cid, frame + 1] - pin_pos[cid, frame]) * fps
        return 0, vec3()

    @wp.func
    def pin_support(p: int, pinned: int, pin_id: wp.array(dtype=int), pin_kind: wp.array(dtype=int)):
        # 1 where particle p is held this frame by a support (a fixed contact: its mass also goes to the
        # grid's support mass, which picks the support's pin rule at a node: node_velocity)
        if pinned != 0:
            return pin_kind[pin_id[p]]
        return 0

    @wp.kernel(module=module, enable_backward=False)
    def p2g_scatter(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), A: wp.array(dtype=mat33),
                    mass: wp.array(dtype=T),
                    pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int), pin_pos: wp.array2d(dtype=vec3),
                    pin_kind: wp.array(dtype=int),
                    frame: int, fps: T, lo: vec3, inv_dx: T, res: wp.vec3i, box_on: int, box: wp.array(dtype=wp.vec3i),
                    dt: T, F: wp.array(dtype=mat33), gm: wp.array3d(dtype=T), gmv: wp.array3d(dtype=vec3),
                    gpm: wp.array3d(dtype=T), gpmv: wp.array3d(dtype=vec3), gsm: wp.array3d(dtype=T),
                    box_flag: wp.array(dtype=int), clamped: wp.array(dtype=int)):
        p = wp.tid()
        m = mass[p]
        dx = T(1.0) / inv_dx
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        if box_on != 0 and out_of_box(base, box):
            wp.atomic_add(box_flag, 0, 1)
        mark_clamped(p, xp, wp.length(v[p]) * dt * inv_dx, wp.determinant(F[p]), res, clamped)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        mv = m * v[p]
        Ap = A[p]
        pinned, pv = pin_velocity(p, pin_id, pin_active, pin_pos, frame, fps)
        support = pin_support(p, pinned, pin_id, pin_kind)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = bw(i, fx[0]) * bw(j, fx[1]) * bw(k, fx[2])
                    d = (vec3(T(float(i)), T(float(j)), T(float(k))) - fx) * dx
                    wp.atomic_add(gmv, base[0] + i, base[1] + j, base[2] + k, w * (mv + Ap * d))
                    wp.atomic_add(gm, base[0] + i, base[1] + j, base[2] + k, w * m)
                    if pinned != 0:
                        wp.atomic_add(gpm, base[0] + i, base[1] + j, base[2] + k, w * m)
                        wp.atomic_add(gpmv, base[0] + i, base[1] + j, base[2] + k, (w * m) * pv)
                        if support != 0:
                            wp.atomic_add(gsm, base[0] + i, base[1] + j, base[2] + k, w * m)

    @wp.kernel(module=module_cuda, enable_backward=False)
    def p2g_fused(F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33), C: wp.array(dtype=mat33),
                  vol: wp.array(dtype=T), E: wp.array(dtype=T), nu: wp.array(dtype=T),
                  eff: wp.array(dtype=T), flags: int, material: int, dt: T,
                  x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), mass: wp.array(dtype=T),
                  pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int), pin_pos: wp.array2d(dtype=vec3),
                  pin_kind: wp.array(dtype=int),
                  frame: int, fps: T, lo: vec3, inv_dx: T, res: wp.vec3i, box_on: int, box: wp.array(dtype=wp.vec3i),
                  A: wp.array(dtype=mat33), gm: wp.array3d(dtype=T), gmv: wp.array3d(dtype=vec3),
                  gpm: wp.array3d(dtype=T), gpmv: wp.array3d(dtype=vec3), gsm: wp.array3d(dtype=T),
                  box_flag: wp.array(dtype=int), clamped: wp.array(dtype=int)):
        # p2g_stress and p2g_scatter in one launch (A is still stored: the backward's scatter adjoint
        # reads it). The scatter's loop is p2g_scatter's, written out again: as a wp.func taking the
        # grid arrays it ran ~1.8x slower on the CPU backend. The two must stay the same arithmetic
        # (tests/test_fused_kernels.py compares them bit for bit).
        p = wp.tid()
        Ap = affine_A(p, F, Fv, C, mass, vol, E, nu, eff, flags, material, inv_dx, dt)
        A[p] = Ap
        m = mass[p]
        dx = T(1.0) / inv_dx
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        if box_on != 0 and out_of_box(base, box):
            wp.atomic_add(box_flag, 0, 1)
        mark_clamped(p, xp, wp.length(v[p]) * dt * inv_dx, wp.determinant(F[p]), res, clamped)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        mv = m * v[p]
        pinned, pv = pin_velocity(p, pin_id, pin_active, pin_pos, frame, fps)
        support = pin_support(p, pinned, pin_id, pin_kind)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = bw(i, fx[0]) * bw(j, fx[1]) * bw(k, fx[2])
                    d = (vec3(T(float(i)), T(float(j)), T(float(k))) - fx) * dx
                    wp.atomic_add(gmv, base[0] + i, base[1] + j, base[2] + k, w * (mv + Ap * d))
                    wp.atomic_add(gm, base[0] + i, base[1] + j, base[2] + k, w * m)
                    if pinned != 0:
                        wp.atomic_add(gpm, base[0] + i, base[1] + j, base[2] + k, w * m)
                        wp.atomic_add(gpmv, base[0] + i, base[1] + j, base[2] + k, (w * m) * pv)
                        if support != 0:
                            wp.atomic_add(gsm, base[0] + i, base[1] + j, base[2] + k, w * m)

    @wp.kernel(module=module_adj, enable_backward=False)
    def p2g_scatter_adj(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), A: wp.array(dtype=mat33),
                        mass: wp.array(dtype=T),
                        pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int),
                        pin_pos: wp.array2d(dtype=vec3), pin_kind: wp.array(dtype=int),
                        frame: int, fps: T, lo: vec3, inv_dx: T, res: wp.vec3i,
                        adj_gm: wp.array3d(dtype=T), adj_gmv: wp.array3d(dtype=vec3),
                        adj_gpm: wp.array3d(dtype=T), adj_gpmv: wp.array3d(dtype=vec3), adj_gsm: wp.array3d(dtype=T),
                        adj_x: wp.array(dtype=vec3), adj_v: wp.array(dtype=vec3), adj_A: wp.array(dtype=mat33),
                        adj_pin_pos: wp.array2d(dtype=vec3)):
        # hand-written adjoint of p2g_scatter (a gather of the grid adjoints): accumulates into
        # adj_x, adj_v, adj_A and adj_pin_pos
        p = wp.tid()
        m = mass[p]
        dx = T(1.0) / inv_dx
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        mv = m * v[p]
        Ap = A[p]
        AT = wp.transpose(Ap)
        pinned, pv = pin_velocity(p, pin_id, pin_active, pin_pos, frame, fps)
        support = pin_support(p, pinned, pin_id, pin_kind)
        g_v = vec3()
        g_A = mat33()
        g_fx = vec3()
        g_pv = vec3()
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    wi = bw(i, fx[0])
                    wj = bw(j, fx[1])
                    wk = bw(k, fx[2])
                    w = wi * wj * wk
                    gw = vec3(dbw(i, fx[0]) * wj * wk, wi * dbw(j, fx[1]) * wk, wi * wj * dbw(k, fx[2]))
                    d = (vec3(T(float(i)), T(float(j)), T(float(k))) - fx) * dx
                    a = adj_gmv[base[0] + i, base[1] + j, base[2] + k]
                    dLdw = wp.dot(a, mv + Ap * d) + adj_gm[base[0] + i, base[1] + j, base[2] + k] * m
                    g_v = g_v + (w * m) * a
                    g_A = g_A + w * wp.outer(a, d)
                    g_fx = g_fx - (dx * w) * (AT * a)
                    if pinned != 0:
                        e = adj_gpmv[base[0] + i, base[1] + j, base[2] + k]
                        dLdw = dLdw + m * (adj_gpm[base[0] + i, base[1] + j, base[2] + k] + wp.dot(e, pv))
                        if support != 0:
                            dLdw = dLdw + m * adj_gsm[base[0] + i, base[1] + j, base[2] + k]
                        g_pv = g_pv + (w * m) * e
                    g_fx = g_fx + dLdw * gw
        adj_v[p] = adj_v[p] + g_v
        adj_A[p] = adj_A[p] + g_A
        adj_x[p] = adj_x[p] + inv_dx * g_fx
        if pinned != 0:
            cid = pin_id[p]
            wp.atomic_add(adj_pin_pos, cid, frame + 1, fps * g_pv)
            wp.atomic_sub(adj_pin_pos, cid, frame, fps * g_pv)

    @wp.func
    def apply_collider(vel: vec3, xn: vec3, c: int, frame: int, alpha: T, fps: T, band: T,
                       col_shape: wp.array(dtype=int), col_pos: wp.array2d(dtype=vec3),
                       col_geom: wp.array(dtype=vec3), col_radius: wp.array(dtype=T), col_mu: wp.array(dtype=T),
                       blend_r: T):
        p0 = col_pos[c, frame]
        p1 = col_pos[c, frame + 1]
        cen = p0 + alpha * (p1 - p0)
        shape = col_shape[c]
        phi = T(0.0)
        nrm = vec3()
        if shape == 2:
            nrm = col_geom[c]
            phi = wp.dot(xn - cen, nrm)
        else:
            q = cen
            if shape == 1:
                ax = col_geom[c]
                t = wp.clamp(wp.dot(xn - cen, ax) / wp.dot(ax, ax), T(-1.0), T(1.0))
                q = cen + t * ax
            d = xn - q
            dist2 = wp.dot(d, d)
            phi = T(1.0e30)
            if dist2 > T(1.0e-24):
                dist = wp.sqrt(dist2)
                nrm = d / dist
                phi = dist - col_radius[c]
        wc = rate_weight(soft_weight(phi, band), blend_r)
        if wc > T(0.0):
            return collide(vel, (p1 - p0) * fps, nrm, col_mu[c], wc)
        return vel

    @wp.func
    def rate_weight(w: T, r: T):
        # a blend weight w that acts once per reference step, for a step r reference steps long:
        # the same rate per unit time (1 - (1 - w)^r), so the result does not depend on the substep
        if w >= T(1.0):
            return T(1.0)
        if w <= T(0.0):
            return T(0.0)
        return T(1.0) - wp.exp(r * wp.log(T(1.0) - w))

    @wp.func
    def node_velocity(m: T, mv: vec3, pm: T, pmv: vec3, sm: T, xn: vec3,
                      eff: wp.array(dtype=T), flags: int, gravity: vec3, dt: T, band: T, pin_gain: T, pin_floor: T,
                      sup_gain: T, sup_floor: T,
                      n_col: int, col_shape: wp.array(dtype=int), col_active: wp.array2d(dtype=int),
                      col_pos: wp.array2d(dtype=vec3), col_geom: wp.array(dtype=vec3),
                      col_radius: wp.array(dtype=T), col_mu: wp.array(dtype=T),
                      frame: int, alpha: T, fps: T, blend_r: T):
        vel = mv / m + dt * gravity
        if (flags & 1) != 0:
            vel = vel * wp.exp(-eff[0] * dt)
        if pm > T(0.0):
            # the pin rule: a grasp's (pin_gain, pin_floor), a support's (sup_gain, sup_floor), mixed by the
            # share of the node's pinned mass that supports hold (sm / pm; 0 or 1 but where both reach a node)
            gain = pin_gain
            floor = pin_floor
            if sm > T(0.0):
                ks = sm / pm
                gain = gain + ks * (sup_gain - gain)
                floor = floor + ks * (sup_floor - floor)
            wpin = rate_weight(wp.clamp(gain * (pm / m - floor), T(0.0), T(1.0)), blend_r)
            vel = vel * (T(1.0) - wpin) + (wpin / pm) * pmv
        if (flags & 20) == 4:     # the ground at the nodes (F_GROUND without F_GROUND_PENALTY)
            wg = rate_weight(soft_weight(xn[1] - eff[2], band), blend_r)
            if wg > T(0.0):
                vel = collide(vel, vec3(), vec3(T(0.0), T(1.0), T(0.0)), eff[3], wg)
        for c in range(MAX_COLLIDERS):
            if c < n_col:
                if col_active[c, frame] != 0:
                    vel = apply_collider(vel, xn, c, frame, alpha, fps, band, col_shape, col_pos, col_geom,
                                         col_radius, col_mu, blend_r)
        return vel

    @wp.kernel(module=module)
    def grid_update(gm: wp.array(dtype=T), gmv: wp.array(dtype=vec3),
                    gpm: wp.array(dtype=T), gpmv: wp.array(dtype=vec3), gsm: wp.array(dtype=T),
                    eff: wp.array(dtype=T), flags: int, gravity: vec3, dt: T, lo: vec3, dx: T, band: T,
                    pin_gain: T, pin_floor: T, sup_gain: T, sup_floor: T, n_col: int, col_shape: wp.array(dtype=int),
                    col_active: wp.array2d(dtype=int),
                    col_pos: wp.array2d(dtype=vec3), col_geom: wp.array(dtype=vec3),
                    col_radius: wp.array(dtype=T), col_mu: wp.array(dtype=T),
                    frame: int, alpha: T, fps: T, res: wp.vec3i, box: wp.array(dtype=wp.vec3i), nthr: int,
                    contig: int, m_eps: T, blend_r: T,
                    gv: wp.array(dtype=vec3)):
        # the whole grid (the grid box off: the CPU's default), in runs of ceil(n / nthr) consecutive nodes
        # per thread (the CPU pays per thread; one node per thread on CUDA); a node's index is decoded only
        # where there is mass. Iterations are independent. box and contig are not read (grid_update_box's
        # arguments: one argument list for both).
        n = gm.shape[0]
        run = (n + nthr - 1) / nthr
        t0 = wp.tid() * run
        for t in range(t0, wp.min(t0 + run, n)):
            m = gm[t]
            vel = vec3()
            # nodes that only graze a particle's stencil edge (mass far below a particle's) are
            # left empty: their velocity mv / m has an adjoint ~1/m that overflows to inf * 0 = NaN
            if m > m_eps:
                i = t / (res[1] * res[2])
                j = (t / res[2]) % res[1]
                k = t % res[2]
                xn = lo + vec3(T(float(i)), T(float(j)), T(float(k))) * dx
                vel = node_velocity(m, gmv[t], gpm[t], gpmv[t], gsm[t], xn, eff, flags, gravity, dt, band,
                                    pin_gain, pin_floor, sup_gain, sup_floor, n_col, col_shape, col_active, col_pos,
                                    col_geom, col_radius, col_mu, frame, alpha, fps, blend_r)
            gv[t] = vel

    @wp.kernel(module=module_cuda)
    def grid_update_box(gm: wp.array(dtype=T), gmv: wp.array(dtype=vec3),
                        gpm: wp.array(dtype=T), gpmv: wp.array(dtype=vec3), gsm: wp.array(dtype=T),
                        eff: wp.array(dtype=T), flags: int, gravity: vec3, dt: T, lo: vec3, dx: T, band: T,
                        pin_gain: T, pin_floor: T, sup_gain: T, sup_floor: T, n_col: int, col_shape: wp.array(dtype=int),
                        col_active: wp.array2d(dtype=int),
                        col_pos: wp.array2d(dtype=vec3), col_geom: wp.array(dtype=vec3),
                        col_radius: wp.array(dtype=T), col_mu: wp.array(dtype=T),
                        frame: int, alpha: T, fps: T, res: wp.vec3i, box: wp.array(dtype=wp.vec3i), nthr: int,
                        contig: int, m_eps: T, blend_r: T,
                        gv: wp.array(dtype=vec3)):
        # grid_update over the nodes of the grid box (`box_span`; on the CPU the same runs of the whole
        # grid as grid_update's, nodes outside the box skipped: bitwise grid_update where the box holds
        # every node with mass): nodes outside the box are neither read nor written.
        start, stop, step = box_span(wp.tid(), nthr, contig, box, res)
        for q in range(start, stop, step):
            i, j, k, t, inside = box_node(q, contig, box, res)
            if inside:
                m = gm[t]
                vel = vec3()
                if m > m_eps:
                    xn = lo + vec3(T(float(i)), T(float(j)), T(float(k))) * dx
                    vel = node_velocity(m, gmv[t], gpm[t], gpmv[t], gsm[t], xn, eff, flags, gravity, dt, band,
                                        pin_gain, pin_floor, sup_gain, sup_floor, n_col, col_shape, col_active,
                                        col_pos, col_geom, col_radius, col_mu, frame, alpha, fps, blend_r)
                gv[t] = vel

    @wp.func
    def gather_particle(p: int, x: wp.array(dtype=vec3), gv: wp.array3d(dtype=vec3), lo: vec3, inv_dx: T,
                        res: wp.vec3i):
        # APIC: v = sum w g, C = (4 / dx^2) sum w g (x_i - x_p)^T
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        nv = vec3()
        B = mat33()
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = bw(i, fx[0]) * bw(j, fx[1]) * bw(k, fx[2])
                    e = vec3(T(float(i)), T(float(j)), T(float(k))) - fx
                    g = gv[base[0] + i, base[1] + j, base[2] + k]
                    nv = nv + w * g
                    B = B + w * wp.outer(g, e)
        return nv, (T(4.0) * inv_dx) * B

    @wp.kernel(module=module, enable_backward=False)
    def g2p_gather(x: wp.array(dtype=vec3), gv: wp.array3d(dtype=vec3), lo: vec3, inv_dx: T, res: wp.vec3i,
                   vg: wp.array(dtype=vec3), Cg: wp.array(dtype=mat33)):
        p = wp.tid()
        nv, nC = gather_particle(p, x, gv, lo, inv_dx, res)
        vg[p] = nv
        Cg[p] = nC

    @wp.kernel(module=module_adj, enable_backward=False)
    def g2p_gather_adj(x: wp.array(dtype=vec3), gv: wp.array3d(dtype=vec3), lo: vec3, inv_dx: T, res: wp.vec3i,
                       adj_vg: wp.array(dtype=vec3), adj_Cg: wp.array(dtype=mat33),
                       adj_x: wp.array(dtype=vec3), adj_gv: wp.array3d(dtype=vec3)):
        # hand-written adjoint of g2p_gather: scatters into adj_gv, accumulates into adj_x
        p = wp.tid()
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        a = adj_vg[p]
        Cb = (T(4.0) * inv_dx) * adj_Cg[p]
        CbT = wp.transpose(Cb)
        g_fx = vec3()
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    wi = bw(i, fx[0])
                    wj = bw(j, fx[1])
                    wk = bw(k, fx[2])
                    w = wi * wj * wk
                    gw = vec3(dbw(i, fx[0]) * wj * wk, wi * dbw(j, fx[1]) * wk, wi * wj * dbw(k, fx[2]))
                    e = vec3(T(float(i)), T(float(j)), T(float(k))) - fx
                    g = gv[base[0] + i, base[1] + j, base[2] + k]
                    Ce = Cb * e
                    wp.atomic_add(adj_gv, base[0] + i, base[1] + j, base[2] + k, w * (a + Ce))
                    g_fx = g_fx + (wp.dot(a, g) + wp.dot(g, Ce)) * gw - w * (CbT * g)
        adj_x[p] = adj_x[p] + inv_dx * g_fx

    @wp.kernel(module=module)
    def ground_impulse(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), C: wp.array(dtype=mat33),
                       vol: wp.array(dtype=T), eff: wp.array(dtype=T), flags: int, dt: T, k_g: T, beta: T,
                       vout: wp.array(dtype=vec3)):
        # the ground at the particles (F_GROUND_PENALTY): a particle whose centre lies less than half its spacing r above
        # the plane y = h (depth u > 0) is pushed up by dt k_g u / (2 r) (the Winkler floor GROUND_K: k_g = GROUND_K g),
        # at most beta u / dt (GROUND_BETA: stability), and its contact point's tangential velocity
        # (v + C (0, -r, 0): APIC's field at the particle's foot) is cut by Coulomb's mu times that push, to zero at
        # most. The result is the velocity p2g scatters (the push reaches the grid, so F sees it). The normal push
        # depends on position only: a rolling body's contact is symmetric and a rolling contact point does not slip,
        # so neither brakes a roll (the grid nodes' projection does: docs/sim.md).
        p = wp.tid()
        nv = v[p]
        if (flags & 20) == 20:
            r = T(0.5) * wp.pow(vol[p], T(1.0 / 3.0))
            u = eff[2] + r - x[p][1]
            if u > T(0.0):
                Cp = C[p]
                dvn = wp.min(k_g * dt / (T(2.0) * r), beta / dt) * u
                nv = nv + vec3(T(0.0), dvn, T(0.0))
                vc = nv - r * vec3(Cp[0, 1], Cp[1, 1], Cp[2, 1])
                vt = vec3(vc[0], T(0.0), vc[2])
                lt2 = wp.dot(vt, vt)
                lim = eff[3] * dvn
                if lt2 > lim * lim:
                    nv = nv - vt * (lim / wp.sqrt(lt2))
                else:
                    nv = nv - vt
        vout[p] = nv

    @wp.func
    def update_particle(p: int, x: wp.array(dtype=vec3), F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33),
                        vgp: vec3, nC: mat33,
                        E: wp.array(dtype=T), nu: wp.array(dtype=T), eff: wp.array(dtype=T), flags: int,
                        pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int),
                        pin_pos: wp.array2d(dtype=vec3), frame: int, fps: T, dt: T,
                        x1: wp.array(dtype=vec3), v1: wp.array(dtype=vec3), C1: wp.array(dtype=mat33),
                        F1: wp.array(dtype=mat33), Fv1: wp.array(dtype=mat33)):
        I = wp.identity(n=3, dtype=T)
        Fn = (I + dt * nC) * F[p]
        if (flags & 2) != 0:
            mu, lam = lame(E[p], nu[p])
            kY = T(SQRT_2_3) * eff[1] / (T(2.0) * mu)
            nrm = dev_norm(Fn)
            if nrm > kY:
                Fn = dev_scale(Fn, kY / nrm)
        Fvn = Fv[p]
        if (flags & 8) != 0:
            a = wp.exp(-dt / eff[5])
            Fvn = dev_scale((I + dt * nC) * Fvn, a)
        nv = vgp
        pinned, pv = pin_velocity(p, pin_id, pin_active, pin_pos, frame, fps)
        if pinned != 0:
            nv = pv
        v1[p] = nv
        C1[p] = nC
        F1[p] = Fn
        Fv1[p] = Fvn
        x1[p] = x[p] + dt * nv

    @wp.kernel(module=module)
    def g2p_update(x: wp.array(dtype=vec3), F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33),
                   vg: wp.array(dtype=vec3), Cg: wp.array(dtype=mat33),
                   E: wp.array(dtype=T), nu: wp.array(dtype=T), eff: wp.array(dtype=T), flags: int,
                   pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int), pin_pos: wp.array2d(dtype=vec3),
                   frame: int, fps: T, dt: T,
                   x1: wp.array(dtype=vec3), v1: wp.array(dtype=vec3), C1: wp.array(dtype=mat33),
                   F1: wp.array(dtype=mat33), Fv1: wp.array(dtype=mat33)):
        p = wp.tid()
        update_particle(p, x, F, Fv, vg[p], Cg[p], E, nu, eff, flags, pin_id, pin_active, pin_pos, frame, fps, dt,
                        x1, v1, C1, F1, Fv1)

    @wp.kernel(module=module_cuda, enable_backward=False)
    def g2p_fused(x: wp.array(dtype=vec3), gv: wp.array3d(dtype=vec3), lo: vec3, inv_dx: T, res: wp.vec3i,
                  F: wp.array(dtype=mat33), Fv: wp.array(dtype=mat33),
                  E: wp.array(dtype=T), nu: wp.array(dtype=T), eff: wp.array(dtype=T), flags: int,
                  pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int), pin_pos: wp.array2d(dtype=vec3),
                  frame: int, fps: T, dt: T,
                  x1: wp.array(dtype=vec3), v1: wp.array(dtype=vec3), C1: wp.array(dtype=mat33),
                  F1: wp.array(dtype=mat33), Fv1: wp.array(dtype=mat33)):
        # g2p_gather and g2p_update in one launch, forward only (the same arithmetic; the gathered
        # velocity and its gradient stay in registers: the backward recomputes them with g2p_gather)
        p = wp.tid()
        nv, nC = gather_particle(p, x, gv, lo, inv_dx, res)
        update_particle(p, x, F, Fv, nv, nC, E, nu, eff, flags, pin_id, pin_active, pin_pos, frame, fps, dt,
                        x1, v1, C1, F1, Fv1)

    @wp.kernel(module=module, enable_backward=False)
    def check(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), F: wp.array(dtype=mat33),
              lo: vec3, inv_dx: T, res: wp.vec3i, row: int, status: wp.array2d(dtype=int),
              clamped: wp.array(dtype=int)):
        p = wp.tid()
        c = clamped[p]
        if c > 0:       # its stencil was clamped at a substep of this frame (mark_clamped)
            wp.atomic_add(status, row, 4, 1)
            wp.atomic_max(status, row, 5, c)
            wp.atomic_max(status, row, 6, p)
            clamped[p] = 0
        xq = x[p]
        ok = wp.isfinite(xq) and wp.isfinite(v[p]) and wp.isfinite(F[p])
        if not ok:
            wp.atomic_add(status, row, 0, 1)
            wp.atomic_max(status, row, 2, p)
        else:
            xp = (xq - lo) * inv_dx
            inside = True
            for d in range(3):
                if xp[d] < T(0.5) or xp[d] >= T(float(res[d])) - T(1.5):
                    inside = False
            if not inside:
                wp.atomic_add(status, row, 1, 1)
                wp.atomic_max(status, row, 3, p)

    # fused zeroing: one launch clears what separate memsets did (each memset is a node of the
    # substep's graph; at small sizes a substep is bound by the number of nodes, not their bytes)
    @wp.func
    def clear_scatter_node(t: int, gm: wp.array(dtype=T), gmv: wp.array(dtype=vec3), gpm: wp.array(dtype=T),
                           gpmv: wp.array(dtype=vec3), gsm: wp.array(dtype=T)):
        # one node of the grid's scatter targets: mass, momentum, pinned mass and momentum, supports' mass
        gm[t] = T(0.0)
        gmv[t] = vec3()
        gpm[t] = T(0.0)
        gpmv[t] = vec3()
        gsm[t] = T(0.0)

    @wp.kernel(module=module_cuda, enable_backward=False)
    def zero_grid(box: wp.array(dtype=wp.vec3i), nthr: int, contig: int, res: wp.vec3i, gm: wp.array(dtype=T),
                  gmv: wp.array(dtype=vec3), gpm: wp.array(dtype=T), gpmv: wp.array(dtype=vec3),
                  gsm: wp.array(dtype=T)):
        # the grid's scatter targets (flat views) over the grid box, nthr threads (`box_span`)
        start, stop, step = box_span(wp.tid(), nthr, contig, box, res)
        for q in range(start, stop, step):
            i, j, k, t, inside = box_node(q, contig, box, res)
            if inside:
                clear_scatter_node(t, gm, gmv, gpm, gpmv, gsm)

    @wp.kernel(module=module_cuda, enable_backward=False)
    def zero_grid_adj(box: wp.array(dtype=wp.vec3i), nthr: int, contig: int, res: wp.vec3i, gm: wp.array(dtype=T),
                      gmv: wp.array(dtype=vec3), gpm: wp.array(dtype=T),
                      gpmv: wp.array(dtype=vec3), gsm: wp.array(dtype=T), a_gm: wp.array(dtype=T),
                      a_gmv: wp.array(dtype=vec3), a_gpm: wp.array(dtype=T), a_gpmv: wp.array(dtype=vec3),
                      a_gsm: wp.array(dtype=T), a_gv: wp.array(dtype=vec3)):
        # the scatter targets and the six grid adjoints of a backward substep, over the grid box
        start, stop, step = box_span(wp.tid(), nthr, contig, box, res)
        for q in range(start, stop, step):
            i, j, k, t, inside = box_node(q, contig, box, res)
            if inside:
                clear_scatter_node(t, gm, gmv, gpm, gpmv, gsm)
                a_gm[t] = T(0.0)
                a_gmv[t] = vec3()
                a_gpm[t] = T(0.0)
                a_gpmv[t] = vec3()
                a_gsm[t] = T(0.0)
                a_gv[t] = vec3()

    @wp.kernel(module=module_cuda, enable_backward=False)
    def zero_particle_adj(a_A: wp.array(dtype=mat33), a_vg: wp.array(dtype=vec3), a_Cg: wp.array(dtype=mat33),
                          with_state: int, a_x: wp.array(dtype=vec3), a_v: wp.array(dtype=vec3),
                          a_C: wp.array(dtype=mat33), a_F: wp.array(dtype=mat33), a_Fv: wp.array(dtype=mat33)):
        # the particle-side adjoint buffers of a backward substep (and, with_state, the adjoint of
        # the substep's input state that it accumulates into)
        p = wp.tid()
        a_A[p] = mat33()
        a_vg[p] = vec3()
        a_Cg[p] = mat33()
        if with_state != 0:
            a_x[p] = vec3()
            a_v[p] = vec3()
            a_C[p] = mat33()
            a_F[p] = mat33()
            a_Fv[p] = mat33()

    @wp.kernel(module=module, enable_backward=False)
    def add_vec3(a: wp.array(dtype=vec3), b: wp.array(dtype=vec3)):
        p = wp.tid()
        a[p] = a[p] + b[p]

    @wp.kernel(module=module, enable_backward=False)
    def add_mat33(a: wp.array(dtype=mat33), b: wp.array(dtype=mat33)):
        p = wp.tid()
        a[p] = a[p] + b[p]

    @wp.kernel(module=module, enable_backward=False)
    def set_rest(x0: wp.array(dtype=vec3), v0: wp.array(dtype=vec3), x: wp.array(dtype=vec3),
                 v: wp.array(dtype=vec3), C: wp.array(dtype=mat33), F: wp.array(dtype=mat33),
                 Fv: wp.array(dtype=mat33)):
        p = wp.tid()
        x[p] = x0[p]
        v[p] = v0[p]
        C[p] = mat33()
        F[p] = wp.identity(n=3, dtype=T)
        Fv[p] = wp.identity(n=3, dtype=T)

    # test hooks: the custom-gradient matrix functions as standalone kernels
    @wp.kernel(module=module_test)
    def eval_matfuncs(F: wp.array(dtype=mat33), c: wp.array(dtype=T), W: wp.array(dtype=mat33),
                      out: wp.array2d(dtype=T)):
        p = wp.tid()
        out[p, 0] = wp.ddot(polar_R(F[p]), W[p])
        out[p, 1] = dev_norm(F[p])
        out[p, 2] = wp.ddot(dev_scale(F[p], c[p]), W[p])
        out[p, 3] = wp.ddot(maxwell_P(F[p], c[p]), W[p])
        mu, lam = lame(T(3.0), T(0.3))
        out[p, 4] = wp.ddot(kirchhoff(F[p], mu, lam, 0), W[p])
        out[p, 5] = wp.ddot(kirchhoff(F[p], mu, lam, 1), W[p])

    # ------------------------------------------------------------------ rate transfer (SimModel.transfer_tau)
    # The particle keeps f = exp(-dt / tau) of the velocity the grid could not carry:
    # v_p <- v_apic + f (v_p - v_old(x_p)), v_old the substep's grid velocity before its forces (p2g of the
    # stress-free momentum m v + m C d, divided by the node's mass), for particles no pin drives. Launched
    # only when tau > 0 (the solver's `rate_f`); tau off leaves the substep's launches as they were.
    @wp.kernel(module=module_rate, enable_backward=False)
    def p2g_scatter_old(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), C: wp.array(dtype=mat33),
                        mass: wp.array(dtype=T), lo: vec3, inv_dx: T, res: wp.vec3i, gmo: wp.array3d(dtype=vec3)):
        p = wp.tid()
        m = mass[p]
        dx = T(1.0) / inv_dx
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        mv = m * v[p]
        mC = m * C[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = bw(i, fx[0]) * bw(j, fx[1]) * bw(k, fx[2])
                    d = (vec3(T(float(i)), T(float(j)), T(float(k))) - fx) * dx
                    wp.atomic_add(gmo, base[0] + i, base[1] + j, base[2] + k, w * (mv + mC * d))

    @wp.kernel(module=module_rate, enable_backward=False)
    def p2g_scatter_old_adj(x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), C: wp.array(dtype=mat33),
                            mass: wp.array(dtype=T), lo: vec3, inv_dx: T, res: wp.vec3i,
                            adj_gmo: wp.array3d(dtype=vec3),
                            adj_x: wp.array(dtype=vec3), adj_v: wp.array(dtype=vec3), adj_C: wp.array(dtype=mat33)):
        # hand-written adjoint of p2g_scatter_old: accumulates into adj_x, adj_v, adj_C
        p = wp.tid()
        m = mass[p]
        dx = T(1.0) / inv_dx
        xp = (x[p] - lo) * inv_dx
        base = cell_base(xp, res)
        fx = xp - vec3(T(float(base[0])), T(float(base[1])), T(float(base[2])))
        mv = m * v[p]
        mC = m * C[p]
        mCT = wp.transpose(mC)
        g_v = vec3()
        g_C = mat33()
        g_fx = vec3()
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    wi = bw(i, fx[0])
                    wj = bw(j, fx[1])
                    wk = bw(k, fx[2])
                    w = wi * wj * wk
                    gw = vec3(dbw(i, fx[0]) * wj * wk, wi * dbw(j, fx[1]) * wk, wi * wj * dbw(k, fx[2]))
                    d = (vec3(T(float(i)), T(float(j)), T(float(k))) - fx) * dx
                    a = adj_gmo[base[0] + i, base[1] + j, base[2] + k]
                    g_v = g_v + (w * m) * a
                    g_C = g_C + (w * m) * wp.outer(a, d)
                    g_fx = g_fx - (dx * w) * (mCT * a) + wp.dot(a, mv + mC * d) * gw
        adj_v[p] = adj_v[p] + g_v
        adj_C[p] = adj_C[p] + g_C
        adj_x[p] = adj_x[p] + inv_dx * g_fx

    @wp.kernel(module=module_rate, enable_backward=False)
    def grid_old(gm: wp.array(dtype=T), gmo: wp.array(dtype=vec3), m_eps: T, gvo: wp.array(dtype=vec3)):
        # the grid's velocity before the substep's forces (flat views; empty nodes as grid_update's)
        t = wp.tid()
        m = gm[t]
        if m > m_eps:
            gvo[t] = gmo[t] / m
        else:
            gvo[t] = vec3()

    @wp.kernel(module=module_rate, enable_backward=False)
    def grid_old_adj(gm: wp.array(dtype=T), gmo: wp.array(dtype=vec3), m_eps: T, adj_gvo: wp.array(dtype=vec3),
                     adj_gm: wp.array(dtype=T), adj_gmo: wp.array(dtype=vec3)):
        t = wp.tid()
        m = gm[t]
        if m > m_eps:
            a = adj_gvo[t]
            adj_gmo[t] = adj_gmo[t] + a / m
            adj_gm[t] = adj_gm[t] - wp.dot(a, gmo[t]) / (m * m)

    @wp.kernel(module=module, enable_backward=False)
    def zero_vec3(a: wp.array(dtype=vec3)):
        # a launch, not a memset: captured into the CPU's graphs too
        a[wp.tid()] = vec3()

    @wp.func
    def rate_free(p: int, pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int), frame: int):
        # whether no pin drives particle p in frame ``frame`` (pin_velocity's rule)
        cid = pin_id[p]
        if cid >= 0:
            if pin_active[cid, frame] != 0:
                return 0
        return 1

    @wp.kernel(module=module_rate, enable_backward=False)
    def rate_update(v: wp.array(dtype=vec3), vgo: wp.array(dtype=vec3), pin_id: wp.array(dtype=int),
                    pin_active: wp.array2d(dtype=int), frame: int, f: T, v1: wp.array(dtype=vec3)):
        # in place on the substep's output velocity (after g2p_update / g2p_fused); x1 is not changed
        # (the particle moves with the grid's velocity, as APIC's)
        p = wp.tid()
        if rate_free(p, pin_id, pin_active, frame) != 0:
            v1[p] = v1[p] + f * (v[p] - vgo[p])

    @wp.kernel(module=module_rate, enable_backward=False)
    def rate_update_adj(pin_id: wp.array(dtype=int), pin_active: wp.array2d(dtype=int), frame: int, f: T,
                        adj_v1: wp.array(dtype=vec3), adj_v: wp.array(dtype=vec3), adj_vgo: wp.array(dtype=vec3)):
        # adjoint of rate_update (adj_v1 passes through unchanged to g2p_update's adjoint)
        p = wp.tid()
        if rate_free(p, pin_id, pin_active, frame) != 0:
            a = f * adj_v1[p]
            adj_v[p] = adj_v[p] + a
            adj_vgo[p] = adj_vgo[p] - a

    return SimpleNamespace(
        name=name, T=T, vec3=vec3, mat33=mat33, module=module,
        modules=SimpleNamespace(core=module, adj=module_adj, rate=module_rate, cuda=module_cuda, test=module_test),
        p2g_stress=p2g_stress, p2g_stress_adj=p2g_stress_adj, p2g_stress_visco=p2g_stress_visco,
        p2g_scatter=p2g_scatter, p2g_scatter_adj=p2g_scatter_adj, p2g_fused=p2g_fused, g2p_fused=g2p_fused,
        grid_update=grid_update, g2p_gather=g2p_gather, g2p_gather_adj=g2p_gather_adj, g2p_update=g2p_update,
        check=check, zero_grid=zero_grid, zero_grid_adj=zero_grid_adj, zero_particle_adj=zero_particle_adj,
        grid_update_box=grid_update_box, ground_impulse=ground_impulse,
        p2g_scatter_old=p2g_scatter_old, p2g_scatter_old_adj=p2g_scatter_old_adj, grid_old=grid_old,
        grid_old_adj=grid_old_adj, rate_update=rate_update, rate_update_adj=rate_update_adj,
        zero_vec3=zero_vec3,
        add_vec3=add_vec3, add_mat33=add_mat33, set_rest=set_rest, eval_matfuncs=eval_matfuncs,
    )
