"""Is the world suite's truth finer than the fit that `init --grid auto` makes of it? (#23, #24)

The world generator (`synth --random SEED`) simulates its ground truth finer than the grid its README
*suggests* (0.5-0.85x that cell, at least 3 particles across the thinnest part, within a CPU's budget of
particle-substeps), but the world benchmarks fit at `init --grid auto` (4 cells across the thinnest part,
within --max-particles): on a thin object that fit is finer than the truth, and the fit's MA then also
measures the truth's own discretisation (`metrics.truth_resolution`; the 22nd session's suite: bow_tie 0.22
against a coarse truth, 0.79 against one finer than its fit).

Per development seed, without simulating anything: the generator's truth cell (`World`: 2 x its particle
spacing) against the cell init's auto rule would choose (CELLS_ACROSS cells across the shape's thinnest part,
the floor of 24 cells, --max-grid, the particle cap at 8 particles a cell): an estimate of init's measured
thickness by the shape's own (checked on dev seeds 2, 5, 22 with real captures and `init`: 1.31 / 1.46 / 0.62
measured against 1.35 / 1.50 / 0.62 estimated). Development seeds only.

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


def auto_cell(thinnest: float, extent: float, volume: float, padding: float, max_grid: int,
              max_particles: int, cells_across: float, floor_grid: int = 24) -> float:
    """The cell init's auto rule would choose for a shape (module doc: an estimate)."""
    span = (1 + 2 * padding) * extent
    cell = min(thinnest / cells_across, span / floor_grid)
    cell = max(cell, span / max_grid)
    if volume / (cell / 2) ** 3 > max_particles:
        cell = 2 * (volume / max_particles) ** (1 / 3)
    return cell


def seeds_of(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-119", help="development seeds (N-M,K)")
    ap.add_argument("--max-particles", type=int, default=15000, help="init's cap (the GPU world runs' 15000)")
    ap.add_argument("--max-grid", type=int, default=128)
    a = ap.parse_args(argv)

    from physinteract_usd.app.init import CELLS_ACROSS
    from physinteract_usd.synth.world import FIT_PADDING, World, draw_world

    rows = []
    for seed in seeds_of(a.seeds):
        w = draw_world(seed, "dev")
        W = World(w)
        cell = auto_cell(W._thinnest(), W.extent, W._volume(), FIT_PADDING, a.max_grid, a.max_particles, CELLS_ACROSS)
        rows.append({"seed": seed, "shape": w["shape"], "scenario": w["scenario"], "ratio": 2 * W.h / cell,
                     "truth_across": W._thinnest() / (2 * W.h)})
    r = np.array([x["ratio"] for x in rows])
    print(f"{len(rows)} development seeds, init --grid auto --max-particles {a.max_particles} --max-grid {a.max_grid}: "
          f"the truth's cell / the fit's: median {np.median(r):.2f}; not finer (>= 0.95) on {np.mean(r >= 0.95):.0%}, "
          f">= 1.5x on {np.mean(r >= 1.5):.0%}; a truth at 0.85x the fit's cell would cost (particles x substeps) "
          f"{np.median(np.maximum(r / 0.85, 1.0) ** 4):.1f}x today's at the median\n")
    by = defaultdict(list)
    for x in rows:
        by[x["shape"]].append(x)
    print("| shape | captures | truth cell / fit cell: median (min-max) | truth not finer | truth's cells across the thinnest "
          "part (median) | cost of a truth at 0.85x the fit's cell, x today's (median) |")
    print("|---|---:|---|---:|---:|---:|")
    for shape, xs in sorted(by.items()):
        q = np.array([x["ratio"] for x in xs])
        t = np.array([x["truth_across"] for x in xs])
        print(f"| {shape} | {len(xs)} | {np.median(q):.2f} ({q.min():.2f}-{q.max():.2f}) | {np.mean(q >= 0.95):.0%} | "
              f"{np.median(t):.1f} | {np.median(np.maximum(q / 0.85, 1.0) ** 4):.1f} |")


if __name__ == "__main__":
    main()
