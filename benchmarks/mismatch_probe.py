"""Which part of the fit's simulator keeps the truth from explaining the video? (#24)

`truth_loss.py` showed (22nd session, GPU suite, development data) that on balloon, basketball, bow_tie, flower
and glove the fit's wrong field explains the video better than the truth's own field, on either path: the
fit's simulator at the true E is not the truth's. This script asks which of its discretisation choices is
responsible, by forward runs only: for one fitted synthetic stage it re-simulates, under each of several
simulator configurations, the truth's E and nu (true path), the truth x 1.2 (true path) and the fit's own E
with its own path, and prints the fit's loss of each. A configuration under which the truth's loss falls below
the fit's names the mismatch (and is the one to fit with next); one under which nothing moves rules it out.

Configurations (`--configs`, ';'-separated, each a ','-separated list of key=value; "base" = the stage's own):
  cfl=C     the substep's CFL number (`simulation.CFL`, 0.6 by default): smaller = more substeps a frame
  tau=S     the rate transfer's time constant in seconds (`SimModel.transfer_tau`; 0 = APIC): larger = less
            of APIC's numerical dissipation per second (docs/sim.md)
  grid=F    the stage re-initialised (`init`, the capture's suggested settings) at F x its grid's cells
            along the longest side (F x the particles' spacing): the fit's field is carried to the new
            particles by nearest neighbour

    python benchmarks/mismatch_probe.py STAGE CAPTURE_DIR [--configs "base;tau=0.05;grid=1.5"]
        [--device cuda] [--out rows.jsonl] [--tag T]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DEFAULT_CONFIGS = "base;tau=0.01;tau=0.05;cfl=0.3;grid=1.5;grid=1.5,tau=0.05"


def parse_configs(text: str) -> list[dict]:
    """"base;tau=0.05,grid=1.5" -> [{}, {"tau": 0.05, "grid": 1.5}] (a bad key or value: ValueError)."""
    out = []
    for part in text.split(";"):
        part = part.strip()
        if not part:
            continue
        cfg = {}
        if part != "base":
            for kv in part.split(","):
                k, _, v = kv.partition("=")
                k = k.strip()
                if k not in ("cfl", "tau", "grid"):
                    raise ValueError(f"unknown key {k!r} in {part!r} (cfl, tau, grid)")
                cfg[k] = float(v)
                if not cfg[k] > 0 and not (k == "tau" and cfg[k] == 0):
                    raise ValueError(f"{k} must be > 0 in {part!r}")
        out.append(cfg)
    return out


def config_name(cfg: dict) -> str:
    return ",".join(f"{k}={v:g}" for k, v in cfg.items()) or "base"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("capture", help="the synth capture the stage was made from (its gt/ holds the truth)")
    ap.add_argument("--configs", default=DEFAULT_CONFIGS)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--tag", default="")
    a = ap.parse_args(argv)
    configs = parse_configs(a.configs)

    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd import simulation
    from physinteract_usd.app.fit import make_problem, prepare_fit, resume_start
    from physinteract_usd.app.init import init
    from physinteract_usd.fit.select import frame_losses
    from physinteract_usd.synth.gt import read_gt_array
    from truth_loss import fixed_result      # benchmarks/: the same record truth_loss.py scores

    cap = Path(a.capture)
    gt = cap / "gt"
    e_gt = np.asarray(read_gt_array(gt, "youngs_modulus.npy"), np.float64)
    nu_gt = np.asarray(read_gt_array(gt, "poisson_ratio.npy"), np.float64)
    g_pos = np.asarray(read_gt_array(gt, "gaussian_positions.npy"), np.float64)[0]
    g_tree = cKDTree(g_pos)
    sug = json.loads((gt / "gt.json").read_text())["suggested_init"]

    def job_of(stage):
        return prepare_fit(stage, iterations=1, contact_from=gt, device=a.device, warm=False, progress=False,
                           log=lambda m: None, settings_overrides={"schedule": "bumps"})

    base_job = job_of(a.stage)
    start, ver, _ = resume_start(a.stage, base_job.scene, base_job.contacts)
    x0_fit = np.asarray(base_job.scene.particles_positions, np.float64)
    fit_E = np.asarray(start["youngs"], np.float64)
    fit_nu = np.asarray(start["poisson"], np.float64)
    fit_tree = cKDTree(x0_fit)
    base_grid = int(max(base_job.scene.settings.grid_resolution))
    ma_best, e_best = M.best_uniform_ma(e_gt)

    tmp = Path(tempfile.mkdtemp(prefix="mismatch_"))
    default_cfl = simulation.CFL
    rows = []
    for cfg in configs:
        t0 = time.time()
        stage = a.stage
        if cfg.get("grid", 1.0) != 1.0:
            n = int(round(base_grid * cfg["grid"]))
            stage = tmp / f"g{n}.usda"
            if not stage.exists():
                init(stage, cap, grid=n, padding=sug["padding"], youngs_range=tuple(sug["youngs_range"]),
                     max_poisson=sug["max_poisson"], density=sug["density"], max_grid=max(n, 256),
                     max_particles=10 ** 8, log=lambda m: None)
        job = base_job if stage == a.stage else job_of(stage)
        job.scene.settings.transfer_tau = float(cfg.get("tau", 0.0))
        simulation.CFL = float(cfg.get("cfl", default_cfl))
        try:
            prob = make_problem(job)
            names = prob.sim.slot_names()
            x0 = np.asarray(job.scene.particles_positions, np.float64)
            P = len(x0)
            _, nn_g = g_tree.query(x0)
            _, nn_f = fit_tree.query(x0)
            init_traj = {k: t.detach().cpu().numpy() for k, t in zip(names, prob.initial_trajectories())}
            fit_traj = {k: np.asarray(start["trajectories"][k]) if k in start.get("trajectories", {}) else init_traj[k]
                        for k in names}
            models = {
                "truth, true path": fixed_result(e_gt[nn_g], nu_gt[nn_g], init_traj),
                "truth x 1.2, true path": fixed_result(1.2 * e_gt[nn_g], nu_gt[nn_g], init_traj),
                "truth, fit's path": fixed_result(e_gt[nn_g], nu_gt[nn_g], fit_traj),
                "fit, fit's path": fixed_result(fit_E[nn_f], fit_nu[nn_f], fit_traj),
            }
            e_top = max(float(np.max(m.youngs)) for m in models.values())
            frames = list(range(1, prob.T))
            res = {k: float(np.mean(frame_losses(prob, m, job.settings, frames, e_top))) for k, m in models.items()}
            sub = None
            try:
                sub = int(prob.sim._model_at(prob.sim.bound_for(e_top)).substeps)
            except Exception:   # the count is for the table only
                pass
        finally:
            simulation.CFL = default_cfl
        row = {"tag": a.tag, "stage": str(a.stage), "config": config_name(cfg), "particles": P,
               "grid": int(max(job.scene.settings.grid_resolution)), "substeps": sub, "losses": res,
               "truth_over_fit": res["truth, true path"] / res["fit, fit's path"], "wall_s": round(time.time() - t0, 1),
               "fit_version": ver, "ma_best_uniform": ma_best}
        rows.append(row)
        print(json.dumps(row), flush=True)
        if a.out:       # each row as it is made: a run cut short keeps the configurations it finished
            with open(a.out, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    print(f"\n{a.stage}: the fit's loss (frames 1..T-1) of each model under each simulator configuration")
    keys = list(rows[0]["losses"]) if rows else []
    print("| config | grid | particles | substeps | " + " | ".join(keys) + " | truth / fit | s |")
    print("|---" * (len(keys) + 6) + "|")
    for r in rows:
        print(f"| {r['config']} | {r['grid']} | {r['particles']} | {r['substeps']} | "
              + " | ".join(f"{r['losses'][k]:.5f}" for k in keys) + f" | {r['truth_over_fit']:.3f} | {r['wall_s']} |")


if __name__ == "__main__":
    main()
