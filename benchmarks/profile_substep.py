"""Where a simulator substep's time goes: per-kernel times of the forward and the backward.

Runs bench_sim's scene (a block with a clamp, a grasp and damping, float32) and prints one markdown
table per size: every kernel / memset of a forward substep and of a backward substep (the backward
recomputes its substep's grid first), its calls per substep and microseconds per substep, beside
the whole substep timed eagerly (every launch from Python) and as the captured graph the fit uses.

    python benchmarks/profile_substep.py --device cuda --sizes 2000:32 15000:100
    python benchmarks/profile_substep.py --device cpu --sizes 500:16

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
    """CPU: time each wp.launch / array.zero_ made by the solver module on the host."""

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

        solver_mod.wp.launch = launch
        return self

    def __exit__(self, *exc):
        solver_mod.wp.launch = self._launch
        return False


def profile(P, n, S, device, reps):
    m, ctrl = make_scene(P, n, 1, S, device)
    tdev = "cpu" if device == "cpu" else device
    E = torch.full((m.n_particles,), 1e4, device=tdev)
    rows = {}

    # whole rollouts: graph (the fit's path) and eager launches
    for graphs in (True, False):
        ro = Rollout(m, ctrl, graphs=graphs)
        Eg = E.clone().requires_grad_(True)
        x, F = ro(Eg)
        (x[-1].sum() + F[-1].sum()).backward()        # warm up: compile, capture

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
    for phase, fn in (("forward", ro.run_forward), ("backward", ro.run_backward)):
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
    return m.n_particles, rows, per


def _short(name: str) -> str:
    """'forward kernel _build__locals__p2g_scatter_1a2b' -> 'forward p2g_scatter'."""
    import re
    name = name.replace("_build__locals__", "").replace(" kernel ", " ")
    return re.sub(r"_[0-9a-f]{6,}$", "", name)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", nargs="*", default=["500:16"], help="P:n pairs (particles : grid cells per axis)")
    ap.add_argument("--substeps", type=int, default=25)
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args(argv)
    device = "cuda:0" if args.device == "cuda" else args.device
    wp.init()
    print(f"device: {device_name(device)}; Warp {wp.__version__}; medians of {args.reps}; float32\n")
    for spec in args.sizes:
        P, n = (int(v) for v in spec.split(":"))
        Pn, rows, per = profile(P, n, args.substeps, device, args.reps)
        print(f"### {Pn} particles, {n}^3 grid, {args.substeps} substeps\n")
        print("| path | forward us/substep | forward+backward us/substep |")
        print("|---|---:|---:|")
        for graphs, label in ((True, "captured graph (the fit's path)"), (False, "eager launches")):
            f, fb = rows[graphs]
            print(f"| {label} | {f * 1e6:.1f} | {fb * 1e6:.1f} |")
        print()
        for phase in ("forward", "backward"):
            tot = sum(v[0] for v in per[phase].values())
            print(f"| {phase} pass: kernel / memset | calls per substep | us per substep | share |")
            print("|---|---:|---:|---:|")
            for k, (ms, c) in sorted(per[phase].items(), key=lambda kv: -kv[1][0]):
                print(f"| {_short(k)} | {c:.2f} | {ms * 1e3:.2f} | {ms / tot:.0%} |")
            print(f"| **sum of {phase} kernel times** | | **{tot * 1e3:.1f}** | |\n")


if __name__ == "__main__":
    main()
