"""The simulation's grid for a stage before and after the reach rule (#24; docs/sim.md "The domain").

    python benchmarks/grid_reach.py STAGE [GT_DIR] [--before REV]

The grid `simulation.grid_covering` builds from the stage's contacts (extracted, or the truth's with GT_DIR, plus
the truth's floor as the ground), under git REV's rule (default 523199b: the hand's path only) and the working
tree's; with GT_DIR also how far the truth's particles go past each grid's valid box, in cells (> 0: outside).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import types
from pathlib import Path

import numpy as np

import physinteract_usd  # noqa: F401
from physinteract_usd import simulation
from physinteract_usd.app.fit import prepare_fit

ROOT = Path(__file__).resolve().parents[1]


def old_rule(rev: str):
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:physinteract_usd/simulation.py"],
                         capture_output=True, text=True, check=True).stdout
    mod = types.ModuleType("physinteract_usd._grid_before")
    mod.__package__ = "physinteract_usd"
    exec(compile(src, f"{rev}:simulation.py", "exec"), mod.__dict__)
    return mod.grid_covering


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stage")
    ap.add_argument("gt", nargs="?", default=None)
    ap.add_argument("--before", default="523199b")
    a = ap.parse_args(argv)
    job = prepare_fit(a.stage, iterations=1, log=lambda *x: None, warm=False, contact_from=a.gt)
    sd, cs = job.scene, job.contacts
    eff = dict(job.effects or {})
    truth = None
    if a.gt:
        g = json.loads((Path(a.gt) / "gt.json").read_text())
        if g.get("floor"):
            eff["ground"] = {"height": g["floor"]["height"]}
        truth = np.load(Path(a.gt) / "particles.npz")["positions"].reshape(-1, 3)
    trajs = [c.trajectory for c in cs]
    grids = {"before": old_rule(a.before)(sd.settings, sd.particles_positions, trajs),
             "after": simulation.grid_covering(sd.settings, sd.particles_positions, trajs, contacts=cs, effects=eff,
                                               fps=sd.fps, n_frames=sd.n_frames)}
    print(f"{a.stage}: contacts {[(c.name, c.type, len(c.indices), c.grasp_frame, c.release_frame) for c in cs]}, "
          f"ground {eff.get('ground')}")
    n0 = int(np.prod(grids["before"].resolution))
    for name, gg in grids.items():
        line = (f"  {name:6s} res {gg.resolution} nodes {int(np.prod(gg.resolution))} ({np.prod(gg.resolution) / n0:.2f}x) "
                f"valid {np.round(gg.valid_lower, 3)} - {np.round(gg.valid_upper, 3)}")
        if truth is not None:
            lo = (gg.valid_lower - truth.min(0)) / gg.dx
            hi = (truth.max(0) - gg.valid_upper) / gg.dx
            line += f" | truth past (cells) lo {np.round(lo, 1)} hi {np.round(hi, 1)}"
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
