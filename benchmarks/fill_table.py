"""What init's fill makes of every synthetic scene and the bundled sample: particle count and
filled volume beside the truth's (no fit, no simulation; the scene's Gaussians are the ones `synth`
writes as object.ply, made here directly; the fill is init's own at its grid's particle spacing).

    python benchmarks/fill_table.py [--size small] [--grid 24] [--scenes a,b] [--json out.jsonl]
        [--against REV]

`--against REV` also fills with fill.py as of git revision REV (e.g. 08756ff, before the open-shell
cavity test) at the grid's spacing and reports the particles it had, how many the current fill
removed and added, and how many of the removed lie outside the true shape (synthetic scenes).

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


OLD = None  # fill.py of --against's revision, as a module


def _old_fill(rev: str):
    import subprocess
    import sys
    import types

    src = subprocess.run(["git", "show", f"{rev}:physinteract_usd/fill.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    mod = types.ModuleType("fill_at_" + rev)
    sys.modules[mod.__name__] = mod
    exec(compile(src.replace("from .gaussians", "from physinteract_usd.gaussians"), mod.__name__, "exec"), mod.__dict__)
    return mod


def _compare(row, tag, g, h, anchor, new, shape):
    t0 = time.process_time()
    old = OLD.fill_from_gaussians(g, h, anchor=anchor)
    row[f"cpu_s_{tag}_before"] = round(time.process_time() - t0, 2)
    a = {tuple(p) for p in np.round(old.positions, 7)}
    b = {tuple(p) for p in np.round(new.positions, 7)}
    gone = np.array(sorted(a - b)).reshape(-1, 3)
    row[f"particles_{tag}_before"] = len(old)
    row[f"volume_cm3_{tag}_before"] = round(float(old.volumes.sum()) * 1e6, 1)
    row[f"removed_{tag}"], row[f"added_{tag}"] = len(gone), len(b - a)
    if shape is not None and len(gone):
        row[f"removed_outside_truth_{tag}"] = int((shape.sdf(gone) > 0).sum())


def _fill_row(name, g, pts, fps, grids, padding=None, truth=None, shape=None):
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
        if OLD is not None:
            _compare(row, str(n), g, s.particle_spacing, s.domain_min, p, shape)
    t0 = time.process_time()
    p = fill_from_gaussians(g, 0.0025)
    row["cpu_s_2.5mm"] = round(time.process_time() - t0, 2)
    row["particles_2.5mm"] = len(p)
    row["volume_cm3_2.5mm"] = round(float(p.volumes.sum()) * 1e6, 1)
    c = pts.mean(0)
    r = np.linalg.norm((p.positions - c)[:, [0, 2]], axis=1)
    row["axis_particles_2.5mm"] = int(((r < 0.03) & (p.positions[:, 1] < pts[:, 1].max() - 0.08)).sum())
    if OLD is not None:
        _compare(row, "2.5mm", g, 0.0025, None, p, shape)
    if shape is not None:
        row["outside_truth_2.5mm"] = int((shape.sdf(p.positions) > 0).sum())
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
    return _fill_row(name, g, g.means, sz.fps, [grid or sz.fit_grid], sz.fit_padding, truth=truth, shape=shape)


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
    ap.add_argument("--against", default=None, help="git revision whose fill.py to compare with")
    a = ap.parse_args(argv)
    global OLD
    OLD = _old_fill(a.against) if a.against else None
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
