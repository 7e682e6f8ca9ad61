"""Several rollouts of one scene in one launch (sim/batch.py): what B copies cost against one.

Prints a markdown table: for B copies of bench_sim's scene (a block with a clamp, a grasp and
damping, float32) tiled side by side on one grid, the wall time of a forward and of a
forward+backward rollout, per copy, and the speed-up per probe against B = 1. With `--stage`, also
a uniform-E sweep of the fit (N probes, forward only, as the start search does) on a real stage:
sequential `FitProblem.loss` calls against one `FitProblem.losses_batch`, with the losses compared.

    python benchmarks/bench_tiled.py --device cuda --sizes 2000:32 15000:100 --copies 1 4 8 16
    python benchmarks/bench_tiled.py --device cuda --stage out/demo/scene.usda --gt samples/foam_bar/gt
    python benchmarks/bench_tiled.py --device cpu --sizes 300:12 --copies 1 4
"""

from __future__ import annotations

import argparse
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
from physinteract_usd.sim.batch import tile  # noqa: E402


def time_copies(P, n, B, T, S, device, reps):
    m, ctrl = make_scene(P, n, T, S, device)
    tl = tile(m, ctrl, B)
    ro = Rollout(tl.model, tl.control)
    tdev = "cpu" if device == "cpu" else device
    E = torch.full((B, m.n_particles), 1e4, device=tdev)
    E *= torch.linspace(0.5, 1.0, B, device=tdev)[:, None]
    nu = torch.full((m.n_particles,), 0.3, device=tdev)
    Eg = E.clone().requires_grad_(True)

    def fwd():
        with torch.no_grad():
            ro(tl.stack(E), tl.stack(nu))

    def fb():
        x, F = ro(tl.stack(Eg), tl.stack(nu))
        (x[-1].sum() + F[-1].sum()).backward()

    fb()
    return m.n_particles, median_wall(fwd, device, reps), median_wall(fb, device, reps)


def sweep(stage, gt, device, n_probes, reps):
    from physinteract_usd.app.fit import make_problem, prepare_fit

    job = prepare_fit(stage, contact_from=gt, device=device, log=lambda *a: None)
    prob = make_problem(job)
    st = job.scene.settings
    Es = np.exp(np.linspace(np.log(st.youngs_min), np.log(st.youngs_max), n_probes + 2)[1:-1])
    P = len(prob.x0)
    nu = torch.full((P,), 0.3, dtype=prob.tdtype, device=prob.tdev)
    prob.sim.ensure_stable(float(Es.max()))
    prob.sim.adaptive = False                 # both paths at the stiffest probe's substep

    def seq():
        out = []
        with torch.no_grad():
            for e in Es:
                out.append(float(prob.loss(torch.full((P,), float(e), dtype=prob.tdtype, device=prob.tdev), nu)["rec"]))
        return out

    def bat():
        E = torch.as_tensor(Es, dtype=prob.tdtype, device=prob.tdev)[:, None].expand(len(Es), P)
        return prob.losses_batch(E, nu)

    a, b = seq(), bat()                        # warm up (compile, capture)
    ts = median_wall(seq, device, reps)
    tb = median_wall(bat, device, reps)
    return P, prob.sim.substeps, prob.T, Es, np.asarray(a), np.asarray(b), ts, tb


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", nargs="*", default=["300:12"], help="P:n pairs (particles : grid cells per axis)")
    ap.add_argument("--copies", nargs="*", type=int, default=[1, 4, 8])
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--substeps", type=int, default=25)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--stage", default=None, help="a stage for the fit-level sweep (with --gt)")
    ap.add_argument("--gt", default=None)
    ap.add_argument("--probes", type=int, default=8)
    args = ap.parse_args(argv)
    device = "cuda:0" if args.device == "cuda" else args.device
    wp.init()
    print(f"device: {device_name(device)}; Warp {wp.__version__}; medians of {args.reps}; float32\n")
    if args.sizes:
        print("| particles per copy | grid per copy | copies | forward ms | per copy | fwd+bwd ms | per copy | "
              "speed-up per probe (fwd / fwd+bwd) |")
        print("|---:|---|---:|---:|---:|---:|---:|---|")
        for spec in args.sizes:
            P, n = (int(v) for v in spec.split(":"))
            base = None
            for B in args.copies:
                Pn, tf, tb = time_copies(P, n, B, args.frames, args.substeps, device, args.reps)
                if base is None:
                    base = (tf, tb)
                print(f"| {Pn} | {n}^3 | {B} | {tf * 1e3:.2f} | {tf / B * 1e3:.2f} | {tb * 1e3:.2f} | "
                      f"{tb / B * 1e3:.2f} | {base[0] * B / tf:.2f}x / {base[1] * B / tb:.2f}x |")
        print()
    if args.stage:
        P, S, T, Es, a, b, ts, tb = sweep(args.stage, args.gt, device, args.probes, args.reps)
        print(f"uniform-E sweep on {args.stage}: {len(Es)} probes ({Es.min():.3g}..{Es.max():.3g} Pa), {P} particles, "
              f"{T} frames x {S} substeps, forward + render + loss\n")
        print("| path | wall s | per probe s | largest relative loss difference |")
        print("|---|---:|---:|---:|")
        print(f"| sequential FitProblem.loss | {ts:.2f} | {ts / len(Es):.3f} | - |")
        print(f"| FitProblem.losses_batch | {tb:.2f} | {tb / len(Es):.3f} | "
              f"{float(np.max(np.abs(a - b) / np.abs(a))):.2e} |")
        print(f"\nspeed-up {ts / tb:.2f}x")


if __name__ == "__main__":
    main()
