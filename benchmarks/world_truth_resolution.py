"""Is the world suite's truth finer than the fit that `init --grid auto` makes of it? (#23, #24)

The world generator (`synth --random SEED`) simulates its ground truth finer than the grid its README
*suggests* (0.5-0.85x that cell, at least 3 particles across the thinnest part, within a CPU's budget of
particle-substeps), but the world benchmarks fit at `init --grid auto` (4 cells across the thinnest part,
within --max-particles): on a thin object that fit is finer than the truth, and the fit's MA then also
measures the truth's own discretisation (`metrics.truth_resolution`; the 22nd session's suite: bow_tie 0.22
against a coarse truth, 0.79 against one finer than its fit).

Per development seed, without simulating anything: the generator's truth cell (`World`: 2 x its particle
spacing) against the cell init's auto rule (`thickness.auto_grid`) gives the shape's own thinnest part (init
measures it from the Gaussians: checked on dev seeds 2, 5, 22 with real captures and `init`: 1.31 / 1.46 / 0.62
measured against 1.35 / 1.50 / 0.62 estimated), and what `synth --truth-for-auto N` (the truth finer than that
fit too) costs in particle-substeps against today's truth. Development seeds only.

    python benchmarks/world_truth_resolution.py [--seeds 0-119] [--max-particles 15000] [--max-grid 128]
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-119", help="development seeds (N-M,K)")
    ap.add_argument("--max-particles", type=int, default=15000, help="init's cap (the GPU world runs' 15000)")
    ap.add_argument("--max-grid", type=int, default=128)
    a = ap.parse_args(argv)

    from physinteract_usd.synth.world import FIT_PADDING, World, draw_world
    from physinteract_usd.thickness import auto_grid
    from world_suite import parse_seeds         # benchmarks/: the world suite's seed lists (N-M,K)

    rows = []
    for seed in parse_seeds(a.seeds):
        w = draw_world(seed, "dev")
        W = World(w)
        n, _ = auto_grid(W._thinnest(), W._volume(), W.extent, FIT_PADDING, a.max_grid, a.max_particles)
        cell = (1 + 2 * FIT_PADDING) * W.extent / n
        # the same capture with `synth --truth-for-auto`: its truth's particle-substeps against today's
        F = World(draw_world(seed, "dev", {"truth_for_auto": a.max_particles}))
        e = float(w["e_max"])
        cost = len(F.x0) * F._substeps(2 * F.h, e) / (len(W.x0) * W._substeps(2 * W.h, e))
        rows.append({"seed": seed, "shape": w["shape"], "scenario": w["scenario"], "ratio": 2 * W.h / cell,
                     "truth_across": W._thinnest() / (2 * W.h), "cost": cost, "ratio_fine": 2 * F.h / cell})
    r = np.array([x["ratio"] for x in rows])
    print(f"{len(rows)} development seeds, init --grid auto --max-particles {a.max_particles} --max-grid {a.max_grid}: "
          f"the truth's cell / the fit's: median {np.median(r):.2f}; not finer (>= 0.95) on {np.mean(r >= 0.95):.0%}, "
          f">= 1.5x on {np.mean(r >= 1.5):.0%}; with synth --truth-for-auto {a.max_particles}: at most "
          f"{max(x['ratio_fine'] for x in rows):.2f}, at {np.median([x['cost'] for x in rows]):.1f}x today's "
          f"particle-substeps (median)\n")
    by = defaultdict(list)
    for x in rows:
        by[x["shape"]].append(x)
    print("| shape | captures | truth cell / fit cell: median (min-max) | truth not finer | truth's cells across the thinnest "
          "part (median) | --truth-for-auto: particle-substeps x today's, median (max) |")
    print("|---|---:|---|---:|---:|---:|")
    for shape, xs in sorted(by.items()):
        q = np.array([x["ratio"] for x in xs])
        t = np.array([x["truth_across"] for x in xs])
        print(f"| {shape} | {len(xs)} | {np.median(q):.2f} ({q.min():.2f}-{q.max():.2f}) | {np.mean(q >= 0.95):.0%} | "
              f"{np.median(t):.1f} | {np.median([x['cost'] for x in xs]):.1f} ({max(x['cost'] for x in xs):.1f}) |")


if __name__ == "__main__":
    main()
