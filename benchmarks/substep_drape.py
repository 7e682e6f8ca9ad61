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
--transfer apic,rate:TAU: the product's APIC step, or (forward only, host-side, benchmarks/dt_convergence.py's
RateTransfer) the same step whose particles keep exp(-dt / TAU) of what the grid could not carry: the
projection's dissipation as a rate per unit time instead of once per substep (#24's mechanism).
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
    ap.add_argument("--transfer", default="apic", help="comma-separated: apic (the product's) or rate:TAU "
                    "(dt_convergence.RateTransfer, forward only); each is a run")
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
        for (sub, blend), transfer in [(r, t) for r in runs for t in a.transfer.split(",")]:
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
            vmax = 0.0
            with torch.no_grad():
                if transfer == "apic":
                    x, F = sim.simulate(torch.as_tensor(E, dtype=sim.tdtype, device=sim.tdev),
                                        torch.as_tensor(nu, dtype=sim.tdtype, device=sim.tdev))
                else:
                    from dt_convergence import run_solver

                    from physinteract_usd.sim import MPMSolver, SimParams
                    sim.ensure_stable(float(np.max(E)))
                    m = sim.model
                    sol = MPMSolver(m, sim.control, SimParams(m, E, nu))
                    rec, _ = run_solver(sol, T - 1, transfer, 1, lambda s: (s.x.numpy().copy(), s.F.numpy().copy(),
                                                                              float(np.linalg.norm(s.v.numpy(), axis=1).max())))
                    x = torch.as_tensor(np.stack([r[0] for r in rec]), dtype=sim.tdtype)
                    F = torch.as_tensor(np.stack([r[1] for r in rec]), dtype=sim.tdtype)
                    vmax = max(r[2] for r in rec)
                if which == "truth":
                    pts, ref = x.cpu().numpy(), p["positions"][:T]
                else:
                    pts = np.stack([sim.gaussians_at(x[k], F[k])[0].cpu().numpy() for k in range(T)])
                    ref = gpos[:T]
            if not vmax:
                xs = x.cpu().numpy()
                vmax = float(np.linalg.norm(np.diff(xs, axis=0), axis=2).max() * sim.scene.fps)  # a frame's mean
            row = {"particles": which, "transfer": transfer, "substeps": int(sim.substeps), "adaptive": not sub,
                   "particle_speed_max": round(vmax, 3),
                   "cfl_speed": round(vmax / (sim.scene.fps * sim.substeps) / sim.grid.dx, 4),
                   "blend_substeps": int(sd.settings.substeps) if not sub else int(sub),
                   "cpu_s": round(time.process_time() - t0, 1),
                   "model_max_mm": [round(1e3 * float(np.linalg.norm(pts[k] - pts[0], axis=1).max()), 1) for k in range(T)],
                   "truth_max_mm": [round(1e3 * float(np.linalg.norm(ref[k] - ref[0], axis=1).max()), 1) for k in range(T)],
                   "mean_error_mm": [round(1e3 * float(np.linalg.norm(pts[k] - ref[k], axis=1).mean()), 2) for k in range(T)]}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
