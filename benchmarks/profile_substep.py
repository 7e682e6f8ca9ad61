"""Where a simulator substep's time goes: per-kernel times of the forward and the backward.

Runs bench_sim's scene (a block with a clamp, a grasp and damping, float32) and prints one markdown
table per size: every kernel / memset of a forward substep and of a backward substep (the backward
recomputes its substep's grid first), its calls per substep and microseconds per substep, beside
the whole substep timed eagerly (every launch from Python) and as the captured graph the fit uses.

    python benchmarks/profile_substep.py --device cuda --sizes 2000:32 15000:100
    python benchmarks/profile_substep.py --device cpu --sizes 500:16

The per-kernel backward is profiled twice: as the fit runs it (the forward stored every substep's
state: the adjoints alone, each recomputing its substep's grid) and replaying (the frame's substeps
replayed from its checkpoint first: what a rollout whose states exceed `rollout.STORE_STATES_BYTES`
does; until session 11 the only backward this script profiled, hence its ~2 p2g per substep).

`--box both` profiles the grid kernels over the whole grid (`sim.solver.GRID_BOX = False`) and over
the object's box (True) in the same process, with a before / after table; `--box on|off` one.

`--zeroing both` (the default) profiles the memset path (`sim.solver.FUSED_ZERO = False`: each
grid / adjoint buffer cleared by its own memset) and the fused path (one clearing kernel over the
grid nodes, one over the particles) in the same process, and ends each size with a before / after
table; `--zeroing fused` or `memset` profiles one.

On CUDA the per-kernel times are Warp's activity timing (`wp.timing_begin`, CUDA events around each
launch, eager launches); on the CPU each launch is timed on the host (Warp's CPU launches are
synchronous). Kernel times are sums of the GPU's own execution times: the gap between them and
the graph's wall time per substep is launch / scheduling overhead.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time

import numpy as np
import torch
import warp as wp

wp.config.quiet = True
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))
from bench_sim import device_name, make_scene, median_wall, sync  # noqa: E402
from physinteract_usd.sim import Rollout  # noqa: E402
from physinteract_usd.sim import solver as solver_mod  # noqa: E402


class _HostLaunchTimer:
    """CPU: time each wp.launch made by the solver module and each array.zero_ (as 'memset') on the host."""

    def __init__(self):
        self.t = collections.defaultdict(float)
        self.n = collections.Counter()

    def __enter__(self):
        self._launch = solver_mod.wp.launch
        timer = self

        def launch(kernel, *a, **kw):
            t0 = time.perf_counter()
            r = timer._launch(kernel, *a, **kw)
            name = ("backward kernel " if kw.get("adjoint") else "forward kernel ") + kernel.key
            timer.t[name] += time.perf_counter() - t0
            timer.n[name] += 1
            return r

        self._zero = wp.array.zero_

        def zero_(arr, *a, **kw):
            t0 = time.perf_counter()
            r = timer._zero(arr, *a, **kw)
            timer.t["memset"] += time.perf_counter() - t0
            timer.n["memset"] += 1
            return r

        solver_mod.wp.launch = launch
        wp.array.zero_ = zero_
        return self

    def __exit__(self, *exc):
        solver_mod.wp.launch = self._launch
        wp.array.zero_ = self._zero
        return False


def profile(P, n, S, device, reps, fused: bool = True, box: bool | None = None):
    old = solver_mod.FUSED_ZERO, solver_mod.GRID_BOX
    solver_mod.FUSED_ZERO = fused          # read by every solver built below
    solver_mod.GRID_BOX = box
    try:
        return _profile(P, n, S, device, reps)
    finally:
        solver_mod.FUSED_ZERO, solver_mod.GRID_BOX = old


def _profile(P, n, S, device, reps):
    m, ctrl = make_scene(P, n, 1, S, device)
    tdev = "cpu" if device == "cpu" else device
    E = torch.full((m.n_particles,), 1e4, device=tdev)
    rows = {}
    grads = []

    # whole rollouts: graph (the fit's path) and eager launches
    for graphs in (True, False):
        ro = Rollout(m, ctrl, graphs=graphs)
        Eg = E.clone().requires_grad_(True)
        x, F = ro(Eg)
        (x[-1].sum() + F[-1].sum()).backward()        # warm up: compile, capture
        if graphs:                                     # the loss and dL/dE twice, for the paths' comparison
            for _ in range(2):
                E1 = E.clone().requires_grad_(True)
                x, F = ro(E1)
                loss = x[-1].sum() + F[-1].sum()
                loss.backward()
                grads.append((loss.detach().double().cpu(), E1.grad.double().cpu()))

        def fwd():
            with torch.no_grad():
                ro(E)

        def fb():
            x, F = ro(Eg)
            (x[-1].sum() + F[-1].sum()).backward()

        rows[graphs] = (median_wall(fwd, device, reps) / S, median_wall(fb, device, reps) / S)

    # per kernel: eager passes of the warp-level forward and backward
    ro = Rollout(m, ctrl, graphs=False)
    x, F = ro(E.clone().requires_grad_(True))
    (x[-1].sum() + F[-1].sum()).backward()
    ro.grad_x.zero_()
    per = {}
    gen = ro.run_forward(store=True)        # the fit's backward: stored states, no replay
    per_box = (ro.solver.box_volume, ro.solver.n_nodes, ro.box_redos)
    for phase, fn in (("forward", ro.run_forward), ("backward", lambda: ro.run_backward(gen)),
                      ("backward, replaying", ro.run_backward)):
        if device == "cpu":
            with _HostLaunchTimer() as tm:
                for _ in range(reps):
                    fn()
            per[phase] = {k: (tm.t[k] / reps / S * 1e3, tm.n[k] / reps / S) for k in tm.t}
        else:
            fn()
            sync(device)
            wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET | wp.TIMING_MEMCPY)
            for _ in range(reps):
                fn()
            res = wp.timing_end()
            acc = collections.defaultdict(float)
            cnt = collections.Counter()
            for r in res:
                acc[r.name] += r.elapsed
                cnt[r.name] += 1
            per[phase] = {k: (acc[k] / reps / S, cnt[k] / reps / S) for k in acc}
    return m.n_particles, rows, per, grads, per_box


def _short(name: str) -> str:
    """'forward kernel _build__locals__p2g_scatter_1a2b' -> 'forward p2g_scatter'."""
    import re
    name = name.replace("_build__locals__", "").replace(" kernel ", " ")
    return re.sub(r"_[0-9a-f]{6,}$", "", name)


def _clears(per) -> tuple[float, float]:
    """(memsets, clearing kernel launches) per substep of one pass's profile."""
    mem = sum(c for k, (_, c) in per.items() if k.startswith("memset"))
    ker = sum(c for k, (_, c) in per.items() if _short(k).split(" ", 1)[-1].startswith("zero_"))
    return mem, ker


def compare_table(Pn, n, old, new, names=("memsets", "fused")) -> str:
    """Before (memsets) / after (fused zeroing) in one table: graph and eager times per substep,
    the backward alone (forward+backward minus forward), and the clears per substep."""
    lines = [f"### before / after: {Pn} particles, {n}^3 grid (us per substep)\n",
             f"| path | {names[0]} | {names[1]} | change |", "|---|---:|---:|---:|"]
    for graphs, label in ((True, "graph"), (False, "eager")):
        (fo, fbo), (fn_, fbn) = old[0][graphs], new[0][graphs]
        for name, a, b in (("forward", fo, fn_), ("forward+backward", fbo, fbn), ("backward", fbo - fo, fbn - fn_)):
            lines.append(f"| {label}, {name} | {a * 1e6:.1f} | {b * 1e6:.1f} | {(b / a - 1) * 100:+.1f}% |")
    for phase in ("forward", "backward"):
        (mo, ko), (mn, kn) = _clears(old[1][phase]), _clears(new[1][phase])
        lines.append(f"| {phase}: memsets + clearing kernels per substep | {mo:.2f} + {ko:.2f} "
                     f"| {mn:.2f} + {kn:.2f} | |")
    return "\n".join(lines) + "\n"


def grad_check(old, new) -> str:
    """Loss and dL/dE of the graph path, memsets vs fused, against the run-to-run spread of one path
    (float atomics on a GPU add in no fixed order; on the CPU both are 0)."""
    def rel(a, b):
        (la, ga), (lb, gb) = a, b
        return (float(abs(la - lb) / max(abs(la), 1e-30)),
                float((ga - gb).abs().max() / max(float(ga.abs().max()), 1e-30)))

    across, within = rel(old[0], new[0]), max(rel(old[0], old[1]), rel(new[0], new[1]))
    return (f"gradient check (graph path): memsets vs fused: loss rel. diff {across[0]:.2e}, dL/dE max rel. diff "
            f"{across[1]:.2e}; run to run within one path: {within[0]:.2e} / {within[1]:.2e}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", nargs="*", default=["500:16"], help="P:n pairs (particles : grid cells per axis)")
    ap.add_argument("--substeps", type=int, default=25)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--box", choices=("default", "on", "off", "both"), default="default",
                    help="the grid kernels over the object's box (on), the whole grid (off), both (before / "
                         "after in one run) or the device's default (sim.solver.GRID_BOX = None)")
    ap.add_argument("--zeroing", choices=("both", "fused", "memset"), default="both",
                    help="which way the substep clears its buffers (both: before / after in one run)")
    args = ap.parse_args(argv)
    device = "cuda:0" if args.device == "cuda" else args.device
    wp.init()
    print(f"device: {device_name(device)}; Warp {wp.__version__}; medians of {args.reps}; float32\n")
    zmodes = {"both": (False, True), "fused": (True,), "memset": (False,)}[args.zeroing]
    bmodes = {"default": (None,), "on": (True,), "off": (False,), "both": (False, True)}[args.box]
    for spec in args.sizes:
        P, n = (int(v) for v in spec.split(":"))
        res = {}
        for fused in zmodes:
            for box in bmodes:
                Pn, rows, per, grads, pbox = profile(P, n, args.substeps, device, args.reps, fused=fused, box=box)
                res[(fused, box)] = (rows, per, grads)
                zeroing = "fused zeroing kernels" if fused else "memsets"
                boxs = {None: "the device's default", True: "on", False: "off (whole grid)"}[box]
                print(f"### {Pn} particles, {n}^3 grid, {args.substeps} substeps; zeroing: {zeroing}; grid box: "
                      f"{boxs} ({pbox[0]:,} of {pbox[1]:,} nodes, {pbox[0] / pbox[1]:.1%}; passes redone: {pbox[2]})\n")
                print("| path | forward us/substep | forward+backward us/substep |")
                print("|---|---:|---:|")
                for graphs, label in ((True, "captured graph (the fit's path)"), (False, "eager launches")):
                    f, fb = rows[graphs]
                    print(f"| {label} | {f * 1e6:.1f} | {fb * 1e6:.1f} |")
                print()
                for phase in ("forward", "backward", "backward, replaying"):
                    tot = sum(v[0] for v in per[phase].values())
                    print(f"| {phase} pass: kernel / memset | calls per substep | us per substep | share |")
                    print("|---|---:|---:|---:|")
                    for k, (ms, c) in sorted(per[phase].items(), key=lambda kv: -kv[1][0]):
                        print(f"| {_short(k)} | {c:.2f} | {ms * 1e3:.2f} | {ms / tot:.0%} |")
                    print(f"| **sum of {phase} kernel times** | | **{tot * 1e3:.1f}** | |\n")
        for box in bmodes:
            if len(zmodes) == 2:
                print(compare_table(Pn, n, res[(False, box)], res[(True, box)]))
                print(grad_check(res[(False, box)][2], res[(True, box)][2]) + "\n", flush=True)
        if len(bmodes) == 2:
            z = zmodes[-1]
            print(compare_table(Pn, n, res[(z, False)], res[(z, True)], ("whole grid", "box")))
            print(grad_check(res[(z, False)][2], res[(z, True)][2]).replace("memsets vs fused", "whole grid vs box")
                  + "\n", flush=True)


if __name__ == "__main__":
    main()
