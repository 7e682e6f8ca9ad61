"""Does the fit's simulation reproduce a synth truth at the truth's own E and path? Its particles vs the
truth's, its adaptive substep vs a fixed one (#24: telephone_cable's drape, docs/benchmarks/fit.md).

For each (particles, substeps): the fit's simulation (the stage's grid, the supports and path from gt/,
the pin rule) at the truth's E and nu, run for --frames frames; per frame the largest displacement
from rest beside the truth's, and the mean error against the truth (particles: the truth's own
particles, gt/particles.npz, point for point; fit: the stage's fill, its Gaussians through the
binding against gt/gaussian_positions.npy, in mm).

    python benchmarks/substep_drape.py STAGE GT_DIR [--frames 10] [--substeps 0,1205] [--particles fit,truth]

substeps 0 = the fit's adaptive substep (simulation.CFL at the field's rung); N = N a frame, fixed (the
partial pin / collider blends then act once per substep, as the truth's do). --blend-substeps N: the
adaptive substep with the blends' rate of N substeps a frame (the rate alone, not the step).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--substeps", default="0")
    ap.add_argument("--particles", default="fit,truth")
    ap.add_argument("--blend-substeps", default="0", help="with the adaptive substep: the stage's substeps a frame "
                    "the partial pin / collider blends take their rate from (model.blend_dt = 1 / (fps N)); 0: the "
                    "stage's. Comma-separated: each is a run")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)

    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd.app.fit import prepare_fit
    from physinteract_usd.simulation import build_simulation
    from physinteract_usd.synth.gt import read_gt_array, read_gt_contacts

    job = prepare_fit(a.stage, iterations=1, contact_from=a.gt, device=a.device, warm=False, progress=False,
                      log=lambda m: None)
    T = min(int(a.frames), job.scene.n_frames)
    p = np.load(Path(a.gt) / "particles.npz")
    gpos = read_gt_array(a.gt, "gaussian_positions.npy")
    e_g, nu_g = read_gt_array(a.gt, "youngs_modulus.npy"), read_gt_array(a.gt, "poisson_ratio.npy")
    for which in a.particles.split(","):
        runs = [(int(v), 0) for v in a.substeps.split(",")] + \
            [(0, int(v)) for v in a.blend_substeps.split(",") if int(v) > 0]
        for sub, blend in runs:
            sd = job.scene
            if which == "truth":
                sd = dataclasses.replace(sd, particles_positions=p["rest"], particles_volumes=p["volume"],
                                         particles_surface=np.zeros(len(p["rest"]), bool), youngs_modulus=p["E"],
                                         poisson_ratio=p["nu"])
                E, nu = p["E"], p["nu"]
            else:
                _, nn = cKDTree(gpos[0]).query(np.asarray(sd.particles_positions))
                E, nu = e_g[nn], nu_g[nn]
            if sub or blend:
                sd = dataclasses.replace(sd, settings=dataclasses.replace(sd.settings, substeps=sub or blend))
            cs = read_gt_contacts(a.gt, sd.particles_positions, job.scene.n_frames)
            cs = [dataclasses.replace(c, trajectory=None if c.trajectory is None else np.asarray(c.trajectory)[:T])
                  for c in cs]
            sim = build_simulation(sd, cs, T, device=a.device, adaptive_substeps=not sub)
            t0 = time.process_time()
            with torch.no_grad():
                x, F = sim.simulate(torch.as_tensor(E, dtype=sim.tdtype, device=sim.tdev),
                                    torch.as_tensor(nu, dtype=sim.tdtype, device=sim.tdev))
                if which == "truth":
                    pts, ref = x.cpu().numpy(), p["positions"][:T]
                else:
                    pts = np.stack([sim.gaussians_at(x[k], F[k])[0].cpu().numpy() for k in range(T)])
                    ref = gpos[:T]
            row = {"particles": which, "substeps": int(sim.substeps), "adaptive": not sub,
                   "blend_substeps": int(sd.settings.substeps) if not sub else int(sub),
                   "cpu_s": round(time.process_time() - t0, 1),
                   "model_max_mm": [round(1e3 * float(np.linalg.norm(pts[k] - pts[0], axis=1).max()), 1) for k in range(T)],
                   "truth_max_mm": [round(1e3 * float(np.linalg.norm(ref[k] - ref[0], axis=1).max()), 1) for k in range(T)],
                   "mean_error_mm": [round(1e3 * float(np.linalg.norm(pts[k] - ref[k], axis=1).mean()), 2) for k in range(T)]}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
