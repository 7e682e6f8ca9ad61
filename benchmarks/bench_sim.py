"""Speed of the differentiable MPM simulator: forward and forward+backward time per substep.

Prints a markdown table for a few particle counts and grids, with the naive MLS-MPM probe
(mpm_probe.py: the same substep without effects or contacts, backward on a wp.Tape that keeps
every substep's grid) timed in the same run as the baseline.

    python benchmarks/bench_sim.py --device cpu
    python benchmarks/bench_sim.py --device cuda --sizes 2000:32 15000:100 --probe .dev/probes/mpm_probe.py

The scene: a block of P particles (2 per cell per axis) in the middle of an n^3 grid, fixed
corotated, float32, gravity, damping, a grasp pulling one end and a clamp on the other (so the
pin and effect code paths run), T frames of S substeps.

`--box both` adds the same before / after table for the grid bounded to the object
(`sim.solver.GRID_BOX` False: the grid kernels over the whole grid; True: over the box of nodes the
block's stencils reach + `rollout.BOX_MARGIN` cells; the box's size is printed).
`--kernels both` adds the same before / after table for the fused transfer kernels
(`sim.solver.FUSED_KERNELS` False: p2g_stress, p2g_scatter, g2p_gather, g2p_update; True: p2g_fused,
g2p_fused). `--zeroing both` adds, after the main table (the default path: fused zeroing kernels on CUDA,
memsets on the CPU), a before /
after table in the same run: the memset path (`sim.solver.FUSED_ZERO = False`) against the fused
one, wall and host CPU time (`time.process_time`, the measure to trust on a shared CPU) per
substep, each timed in alternating rounds so that load changes hit both alike:

    python benchmarks/bench_sim.py --device cuda --sizes 2000:32 15000:100 --zeroing both --probe ''
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import time

import numpy as np
import torch
import warp as wp

wp.config.quiet = True

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel  # noqa: E402
from physinteract_usd.sim import solver as solver_mod  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_PROBES = [os.path.join(HERE, "..", ".dev", "probes", "mpm_probe.py"),
                  os.path.join(HERE, "..", "..", "shared", "device", "mpm_probe.py")]


def make_scene(P: int, n: int, T: int, S: int, device: str, dtype: str = "float32"):
    dx = 1.0 / n
    sp = dx / 2
    side = max(2, int(round(P ** (1 / 3))))
    dims = [side, side, max(1, int(round(P / side / side)))]
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in dims], indexing="ij"), -1).reshape(-1, 3)
    pts = (idx - np.array(dims) / 2) * sp + 0.5
    left = np.nonzero(idx[:, 0] == 0)[0]
    right = np.nonzero(idx[:, 0] == dims[0] - 1)[0]
    traj = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0, 0.2 * dx, T + 1)     # a gentle pull (0.4 m/s at dt = 1e-4, S = 25)
    ctrl = Control([Contact("fixed", indices=left), Contact("pointAdherent", indices=right, trajectory=traj)],
                   n_frames=T)
    fps = 1.0 / (S * 1e-4)        # dt = 1e-4 s, as in the probe
    m = SimModel.create(pts, sp ** 3, 1000.0, 1e4, 0.3, grid=GridSpec((0, 0, 0), dx, (n, n, n)), fps=fps,
                        substeps=S, E_max=1e4, dtype=dtype, device=device,
                        effects={"damping": {"coefficient": 1.0}})
    return m, ctrl


def sync(device):
    wp.synchronize_device(device)


def median_wall(fn, device, reps: int) -> float:
    """The median wall time [s] of `reps` calls of fn(), the device synchronised around each."""
    out = []
    for _ in range(reps):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        out.append(time.perf_counter() - t0)
    return float(np.median(out))


STAT = "min"


def _rollout(m, ctrl, fused: bool | None = None, switch: str = "FUSED_ZERO"):
    """A rollout with `sim.solver.<switch>` (FUSED_ZERO, FUSED_KERNELS, GRID_BOX) = fused (None: the
    device's default), read when the solver is built."""
    old = getattr(solver_mod, switch)
    setattr(solver_mod, switch, fused)
    try:
        return Rollout(m, ctrl)
    finally:
        setattr(solver_mod, switch, old)


def time_rollout(P, n, T, S, device, reps):
    m, ctrl = make_scene(P, n, T, S, device)
    ro = _rollout(m, ctrl)
    tdev = "cpu" if device == "cpu" else device
    E = torch.full((m.n_particles,), 1e4, device=tdev, requires_grad=True)
    # warm up (compiles)
    x, F = ro(E)
    (x[-1].sum() + F[-1].sum()).backward()
    sync(device)
    tf_list, tb_list = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        with torch.no_grad():
            x, F = ro(E)
        sync(device)
        tf_list.append(time.perf_counter() - t0)
    for _ in range(reps):
        t0 = time.perf_counter()
        x, F = ro(E)
        (x[-1].sum() + F[-1].sum()).backward()
        sync(device)
        tb_list.append(time.perf_counter() - t0)
    stat = np.median if STAT == "median" else np.min        # min: robust to other load on the machine
    tf, tb = float(stat(tf_list)), float(stat(tb_list))
    return m.n_particles, tf / (T * S), tb / (T * S)


def compare_zeroing(P, n, T, S, device, reps, switch="FUSED_ZERO"):
    """Memsets vs fused zeroing (switch "FUSED_KERNELS": separate vs fused transfer kernels) on one
    scene: per path, (wall fwd, wall fwd+bwd, cpu fwd, cpu fwd+bwd) per substep, the `STAT` over
    `reps` rounds; the two paths alternate within each round."""
    m, ctrl = make_scene(P, n, T, S, device)
    tdev = "cpu" if device == "cpu" else device
    E = torch.full((m.n_particles,), 1e4, device=tdev, requires_grad=True)
    ros = {f: _rollout(m, ctrl, f, switch) for f in (False, True)}
    for ro in ros.values():                  # warm up: compile, capture
        x, F = ro(E)
        (x[-1].sum() + F[-1].sum()).backward()
    sync(device)
    if switch == "GRID_BOX":
        s = ros[True].solver
        print(f"  grid box ({m.n_particles} particles, {n}^3): nodes {s.box_lo} .. {s.box_hi} = {s.box_volume:,} "
              f"of {s.n_nodes:,} ({s.box_volume / s.n_nodes:.1%}); passes redone on the whole grid: "
              f"{ros[True].box_redos}", flush=True)

    def fwd(ro):
        with torch.no_grad():
            ro(E)

    def fb(ro):
        x, F = ro(E)
        (x[-1].sum() + F[-1].sum()).backward()

    t = {(f, k): [] for f in ros for k in range(4)}
    for _ in range(reps):
        for j, fn in enumerate((fwd, fb)):
            for f, ro in ros.items():
                sync(device)
                w0, c0 = time.perf_counter(), time.process_time()
                fn(ro)
                sync(device)
                t[(f, j)].append(time.perf_counter() - w0)
                t[(f, j + 2)].append(time.process_time() - c0)
    stat = np.median if STAT == "median" else np.min
    return m.n_particles, {f: [float(stat(t[(f, k)])) / (T * S) for k in range(4)] for f in ros}


def zeroing_table(rows, names=("memsets", "fused")) -> str:
    lines = [f"| particles | grid | measure (us/substep) | {names[0]} | {names[1]} | change |",
             "|---:|---:|---|---:|---:|---:|"]
    for Pm, n, r in rows:
        old, new = r[False], r[True]
        for name, i in (("wall forward", 0), ("wall fwd+bwd", 1), ("wall backward", None), ("CPU forward", 2),
                        ("CPU fwd+bwd", 3), ("CPU backward", -1)):
            if i is None:
                a, b = old[1] - old[0], new[1] - new[0]
            elif i == -1:
                a, b = old[3] - old[2], new[3] - new[2]
            else:
                a, b = old[i], new[i]
            lines.append(f"| {Pm:,} | {n}^3 | {name} | {a * 1e6:,.1f} | {b * 1e6:,.1f} | {(b / a - 1) * 100:+.1f}% |")
    return "\n".join(lines)


def run_probe(probe, device, P, n, S):
    if not probe or not os.path.exists(probe):
        return None, None
    try:
        out = subprocess.run([sys.executable, probe, device, str(P), str(n), str(S)], capture_output=True,
                             text=True, timeout=900).stdout
    except Exception as e:  # noqa: BLE001
        print(f"probe failed: {e}", file=sys.stderr)
        return None, None
    f = re.search(r"forward \d+ substeps: [\d.]+ ms\s+\(([\d.]+) us/substep", out)
    b = re.search(r"forward\+backward \d+ substeps: ([\d.]+) ms", out)
    fwd = float(f.group(1)) * 1e-6 if f else None
    fb = float(b.group(1)) * 1e-3 / S if b else None
    g = re.search(r"graph: forward ([\d.]+) us/substep; forward\+backward ([\d.]+) us/substep", out)
    if g:
        print(f"  probe graph ({P}, {n}^3): forward {g.group(1)} us, fwd+bwd {g.group(2)} us per substep")
    return fwd, fb


def device_name(device):
    if device == "cpu":
        cpu = platform.processor() or "CPU"
        try:
            with open("/proc/cpuinfo") as fh:
                for line in fh:
                    if line.startswith("model name"):
                        cpu = line.split(":", 1)[1].strip()
                        break
        except OSError:
            pass
        return f"{cpu}, {os.cpu_count()} cores (Warp CPU backend: single-threaded)"
    return wp.get_device(device).name


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", nargs="*", default=None, help="P:n pairs (particles : grid nodes per axis)")
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--substeps", type=int, default=25)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--probe", default=None, help="path of mpm_probe.py ('' to skip)")
    ap.add_argument("--stat", choices=("min", "median"), default="min", help="statistic over the runs")
    ap.add_argument("--zeroing", choices=("fused", "both"), default="fused",
                    help="both: also a before / after table, memsets vs fused zeroing kernels")
    ap.add_argument("--box", choices=("default", "both"), default="default",
                    help="both: also a before / after table, the grid kernels over the whole grid vs over "
                         "the object's box (sim.solver.GRID_BOX)")
    ap.add_argument("--kernels", choices=("fused", "both"), default="fused",
                    help="both: also a before / after table, separate vs fused transfer kernels "
                         "(sim.solver.FUSED_KERNELS: p2g_fused, g2p_fused)")
    ap.add_argument("--json", default=None, help="also write the tables' numbers here (e.g. $OUT/bench_sim.json)")
    args = ap.parse_args(argv)
    report = {"device": None, "rows": [], "comparisons": []}
    global STAT
    STAT = args.stat
    device = "cuda:0" if args.device == "cuda" else args.device
    wp.init()
    sizes = args.sizes or (["500:16", "1000:24", "2000:32", "4000:40"] if device == "cpu"
                           else ["2000:32", "15000:64", "15000:100", "50000:100"])
    probe = args.probe
    if probe is None:
        probe = next((p for p in DEFAULT_PROBES if os.path.exists(p)), "")
    print(f"device: {device_name(device)}; warp {wp.__version__}, torch {torch.__version__}; float32; "
          f"{args.frames} frames x {args.substeps} substeps; {'best' if STAT == 'min' else 'median'} of {args.reps} runs "
          "(probe: mean of 5)")
    rows = []
    for s in sizes:
        P, n = (int(v) for v in s.split(":"))
        Pm, tf, tb = time_rollout(P, n, args.frames, args.substeps, device, args.reps)
        pf, pb = run_probe(probe, device.split(":")[0] if device == "cpu" else device, P, n,
                           args.frames * args.substeps)
        rows.append((Pm, n, tf, tb, pf, pb))
        report["rows"].append({"particles": Pm, "grid": n, "forward_us": tf * 1e6, "fwd_bwd_us": tb * 1e6})
        print(f"  P={Pm} n={n}: fwd {tf * 1e6:.0f} us, fwd+bwd {tb * 1e6:.0f} us per substep", flush=True)

    def us(v):
        return "-" if v is None else f"{v * 1e6:,.0f}"

    print()
    print("| particles | grid | forward us/substep | fwd+bwd us/substep | bwd/fwd | probe fwd | probe fwd+bwd |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for Pm, n, tf, tb, pf, pb in rows:
        print(f"| {Pm:,} | {n}^3 | {us(tf)} | {us(tb)} | {tb / tf:.1f} | {us(pf)} | {us(pb)} |")
    stat = "best" if STAT == "min" else "median"
    comparisons = (   # (asked, switch, what the two paths are, the columns' names)
        (args.zeroing == "both", "FUSED_ZERO", "zeroing: memsets (FUSED_ZERO=False) vs fused kernels", None),
        (args.box == "both", "GRID_BOX", "grid box: the grid kernels over the whole grid (GRID_BOX=False) vs over "
                                         "the object's box (True)", ("whole grid", "box")),
        (args.kernels == "both", "FUSED_KERNELS", "transfer kernels: separate (FUSED_KERNELS=False: stress, scatter, "
                                                  "gather, update) vs fused (p2g_fused, g2p_fused)", ("separate", "fused")),
    )
    for asked, switch, what, names in comparisons:
        if not asked:
            continue
        crows = []
        for s in sizes:
            P, n = (int(v) for v in s.split(":"))
            Pm, r = compare_zeroing(P, n, args.frames, args.substeps, device, args.reps, switch)
            crows.append((Pm, n, r))
            keys = ("wall_forward_us", "wall_fwd_bwd_us", "cpu_forward_us", "cpu_fwd_bwd_us")
            report["comparisons"].append({"switch": switch, "what": what, "particles": Pm, "grid": n,
                                          **{f"{names[0] if names else 'before'}": dict(zip(keys, [v * 1e6 for v in r[False]])),
                                             f"{names[1] if names else 'after'}": dict(zip(keys, [v * 1e6 for v in r[True]]))}})
        print(f"\n{what}, alternating rounds, {stat} of {args.reps}; backward = fwd+bwd - forward\n")
        print(zeroing_table(crows, names) if names else zeroing_table(crows))
    if args.json:
        import json
        report["device"] = device_name(device)
        report["warp"] = wp.__version__
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
