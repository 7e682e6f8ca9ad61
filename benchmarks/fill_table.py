"""What init's fill makes of every synthetic scene and the bundled sample: particle count and
filled volume beside the truth's (no fit, no simulation; the scene's Gaussians are the ones `synth`
writes as object.ply, made here directly; the fill is init's own at its grid's particle spacing).

    python benchmarks/fill_table.py [--size small] [--grid 24] [--scenes a,b] [--json out.jsonl]

Per scene: particles and filled volume (cm^3) at `--grid` (default: the size's suggested grid, 24
for small) and at a fixed 2.5 mm spacing, the truth's volume (the ground-truth particle lattice that
`synth` simulates, gt/particles.npz), the fill's particles within 3 cm of the object's vertical axis
below its top (material where an open shell such as knit_cap has a cavity), and CPU seconds.
The bundled sample (samples/foam_bar/object.ply) is filled at grid 24 and at init's default 32.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _fill_row(name, g, pts, fps, grids, padding=None, truth=None):
    from physinteract_usd.app import init as app_init
    from physinteract_usd.fill import fill_from_gaussians

    row = {"scene": name}
    for n in grids:
        s = (app_init.choose_sim_settings(pts, fps, n) if padding is None
             else app_init.choose_sim_settings(pts, fps, n, padding))
        t0 = time.process_time()
        p = fill_from_gaussians(g, s.particle_spacing, anchor=s.domain_min)
        row[f"cpu_s_{n}"] = round(time.process_time() - t0, 2)
        row[f"particles_{n}"] = len(p)
        row[f"volume_cm3_{n}"] = round(float(p.volumes.sum()) * 1e6, 1)
        row[f"spacing_mm_{n}"] = round(1000 * p.spacing, 2)
    t0 = time.process_time()
    p = fill_from_gaussians(g, 0.0025)
    row["cpu_s_2.5mm"] = round(time.process_time() - t0, 2)
    row["particles_2.5mm"] = len(p)
    row["volume_cm3_2.5mm"] = round(float(p.volumes.sum()) * 1e6, 1)
    c = pts.mean(0)
    r = np.linalg.norm((p.positions - c)[:, [0, 2]], axis=1)
    row["axis_particles_2.5mm"] = int(((r < 0.03) & (p.positions[:, 1] < pts[:, 1].max() - 0.08)).sum())
    if truth is not None:
        row["truth_volume_cm3"] = round(truth * 1e6, 1)
    return row


def scene_row(name: str, size: str, grid: int | None):
    from physinteract_usd.synth.generate import SIZES, surface_gaussians
    from physinteract_usd.synth.scenes import SCENES

    spec, sz = SCENES[name], SIZES[size]
    shape = spec.shape()
    g, _ = surface_gaussians(spec, shape, sz.gaussians, 0)
    lo, hi = shape.bounds()
    ext = float(np.max(hi - lo))
    h = 0.5 * sz.gt_ratio * (1 + 2 * sz.fit_padding) * ext / sz.fit_grid  # synth's GroundTruth spacing
    truth = len(shape.lattice(h)) * h ** 3
    return _fill_row(name, g, g.means, sz.fps, [grid or sz.fit_grid], sz.fit_padding, truth=truth)


def sample_row():
    from physinteract_usd.gaussians import read_ply

    g = read_ply(ROOT / "samples" / "foam_bar" / "object.ply")
    fps = json.loads((ROOT / "samples" / "foam_bar" / "transforms.json").read_text()).get("fps", 20.0)
    return _fill_row("foam_bar (sample)", g, g.means, fps, [24, 32], 0.3)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="small")
    ap.add_argument("--grid", type=int, default=None)
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--json", default=None, help="JSON-lines file to write the rows to")
    a = ap.parse_args(argv)
    from physinteract_usd.synth.scenes import SCENES

    names = a.scenes.split(",") if a.scenes else list(SCENES) + ["sample"]
    out = open(a.json, "w") if a.json else None
    for n in names:
        r = sample_row() if n == "sample" else scene_row(n, a.size, a.grid)
        print(json.dumps(r), flush=True)
        if out:
            out.write(json.dumps(r) + "\n")
            out.flush()


if __name__ == "__main__":
    main()
