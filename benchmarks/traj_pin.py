"""E traded against the trajectory (#24): the fit with the hand path pinned vs free, from true contacts.

With `--contact-from gt` the fit's T0 is the truth's own path, but the fit still moves it within
the measured path's uncertainty (`FitProblem.trajectory_prior`: sigma_px = 2 px across the camera
ray, 3.2x that along it, weight TRAJ_PRIOR_WEIGHT per sigma^2), exactly as it would an extracted
path. Per scene and mode, the same bumps fit (same settings, iterations, seed) with the path:

  pinned    not fitted (`FitSettings.joint=False`, the CLI's `fit --no-joint`): the true path
  prior     fitted under the prior at its current width (the default)
  noprior   fitted with the prior's weight at 0 (free within the optimiser's steps)
  wide      fitted under a prior 4x wider (sigma_px = 8)

Each row: MA (per Gaussian, the design's metric) beside the best single E's, masked PSNR, the
fit's loss, its path's largest image-plane deviation from the true path (px, and in sigma), and,
all at one substep (the rung of the stage's E range's top), the reconstruction loss of: the fit with its path,
the fit's E with the true path, the truth's E and nu with the true path.

    # one stage (e.g. benchmarks/suite.py made it), in this process:
    python benchmarks/traj_pin.py --stage S.usda --gt CAP/gt [--modes pinned,prior] [--iterations 20] [--device cuda]
    # scenes from scratch (synth -> init through the CLI, then the fits), one process per scene at once:
    python benchmarks/traj_pin.py --scenes balloon,telephone_cable,foam_bar,hemp_rope --work /tmp/tp --size small \
        --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --device cuda --jobs 4 --out rows.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

MODES = ("pinned", "prior", "noprior", "wide")


def make_stage(scene: str, a, work: Path) -> tuple[Path, Path]:
    """synth + init through the CLI (the capture's suggested settings, --grid as given); reused when there."""
    cap, st = work / scene, work / f"{scene}.usda"
    log = open(work / f"{scene}.log", "a")
    run = lambda cmd: subprocess.run([sys.executable, "-m", "physinteract_usd", *cmd], stdout=log,  # noqa: E731
                                     stderr=subprocess.STDOUT).returncode
    if not (cap / "gt" / "gt.json").exists():
        cmd = ["synth", scene, str(cap), "--size", a.size, "--device", a.device, "--force"]
        cmd += ["--frames", str(a.frames)] if a.frames else []
        cmd += ["--fit-grid", str(a.synth_fit_grid)] if a.synth_fit_grid else []
        cmd += ["--transfer-tau", str(a.transfer_tau)] if a.transfer_tau else []
        if run(cmd):
            raise RuntimeError(f"{scene}: synth failed (see {work / scene}.log)")
    if not st.exists():
        sug = json.loads((cap / "gt" / "gt.json").read_text())["suggested_init"]
        if run(["init", str(st), "--capture", str(cap), "--grid", str(a.grid or sug["grid"]), "--padding",
                str(sug["padding"]), "--youngs-range", ",".join(str(v) for v in sug["youngs_range"]),
                "--max-poisson", str(sug["max_poisson"]), "--density", str(sug["density"]), "--yes"]
               + (["--transfer-tau", str(a.transfer_tau)] if a.transfer_tau else [])):
            raise RuntimeError(f"{scene}: init failed (see {work / scene}.log)")
    return st, cap / "gt"


def path_deviation(prob, fitted: list, measured: list) -> dict:
    """The largest image-plane distance (px) of a fitted path from the measured one over all
    frames and slots, and its depth offset (mm) at that frame."""
    best = {"max_px": 0.0, "max_sigma": 0.0, "depth_mm": 0.0, "frame": 0}
    for tr, t0 in zip(fitted, measured):
        tr, t0 = np.asarray(tr, float), np.asarray(t0, float)
        for k in range(len(tr)):
            (u0, u1), z = prob.cameras[k].project(np.stack([t0[k], tr[k]]))
            d = float(np.linalg.norm(u1 - u0))
            if d > best["max_px"]:
                best = {"max_px": d, "max_sigma": d / prob.traj_sigma_px, "depth_mm": float(1e3 * (z[1] - z[0])),
                        "frame": k}
    return best


def one_stage(stage, gt_dir, a, tag="") -> list[dict]:
    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit import FitProblem
    from physinteract_usd.fit import fit as optimise
    from physinteract_usd.fit.select import frame_losses
    from physinteract_usd.synth.gt import read_gt_array

    if a.cfl is not None:      # the adaptive substep's CFL number (simulation.CFL, default 0.6): smaller, finer steps
        import physinteract_usd.simulation as simulation

        simulation.CFL = float(a.cfl)
    over = {"schedule": "bumps", **json.loads(a.settings or "{}")}
    job = prepare_fit(stage, iterations=a.iterations, contact_from=gt_dir, device=a.device, warm=False,
                      progress=False, log=lambda m: None, settings_overrides=over)
    e_gt = read_gt_array(gt_dir, "youngs_modulus.npy")
    nu_gt = read_gt_array(gt_dir, "poisson_ratio.npy")
    g0 = read_gt_array(gt_dir, "gaussian_positions.npy")[0]
    ma_best, e_best = M.best_uniform_ma(e_gt)
    # every loss below at one substep: the rung of the stage's E range's top (the stiffest any fit may take)
    e_top = float(job.scene.settings.youngs_max)
    frames = None
    rows, truth, truth_loss = [], None, None
    for mode in a.modes.split(","):
        if mode not in MODES:
            raise SystemExit(f"--modes: unknown mode {mode!r} (one of {', '.join(MODES)})")
        prob = make_problem(job) if mode != "wide" else \
            FitProblem(job.scene, job.observations, job.contacts, effects=job.effects, device=a.device, traj_sigma_px=8.0)
        if mode == "noprior":
            prob.weights.trajectory = 0.0
        s = dataclasses.replace(job.settings, joint=mode != "pinned")
        c0, t0 = time.process_time(), time.perf_counter()
        r = optimise(prob, s, progress=False, log=None)
        cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - t0
        names = prob.sim.slot_names()
        t_true = [tr.detach().cpu().numpy() for tr in prob.initial_trajectories()]
        t_fit = [np.asarray(r.trajectories[n]) for n in names]
        frames = list(range(1, prob.T))
        if truth is None:   # the truth's E and nu per particle (its nearest Gaussian's at rest), the true path
            _, nn = cKDTree(g0).query(np.asarray(prob.x0))
            truth = dataclasses.replace(r, youngs=e_gt[nn], poisson=nu_gt[nn], effect_parameters={},
                                        trajectories=dict(zip(names, t_true)))
            truth_loss = float(np.mean(frame_losses(prob, truth, s, frames, e_top)))
        on_true = dataclasses.replace(r, trajectories=truth.trajectories)
        fm = r.frame_metrics
        row = {"tag": tag, "stage": str(stage), "mode": mode, "iterations": s.iterations,
               "particles": int(len(prob.x0)), "ma": M.material_accuracy(r.youngs_gaussian, e_gt),
               "ma_best_uniform": ma_best, "e_best_uniform": e_best,
               "median_e_fit": float(np.median(r.youngs_gaussian)), "median_e_truth": float(np.median(e_gt)),
               "psnr_masked": float(np.nanmean([min(f["psnr_masked"], 100) for f in fm])),
               "final_loss": float(r.final_loss), "path": path_deviation(prob, t_fit, t_true),
               "loss_fit": float(np.mean(frame_losses(prob, r, s, frames, e_top))),
               "loss_fit_e_true_path": float(np.mean(frame_losses(prob, on_true, s, frames, e_top))),
               "loss_truth": truth_loss, "cfl": a.cfl, "transfer_tau": float(prob.sim.model.transfer_tau), "substeps": int(prob.sim.substeps), "cpu_s": round(cpu_s, 1), "wall_s": round(wall_s, 1), "device": a.device}
        rows.append(row)
        if a.out:
            with open(a.out, "a") as fh:
                fh.write(json.dumps(row, default=float) + "\n")
        print(json.dumps(row, default=float), flush=True)
    return rows


def table(rows: list[dict]) -> str:
    head = ("| scene | mode | MA | best single E | masked PSNR | loss (one substep) | fit's E, true path | truth, true path "
            "| path dev. px (sigma) | CPU s |\n" + "|---" * 10 + "|\n")
    out = []
    for r in rows:
        p = r["path"]
        out.append(f"| {Path(r['stage']).stem} | {r['mode']} | {r['ma']:.3f} | {r['ma_best_uniform']:.3f} | "
                   f"{r['psnr_masked']:.2f} | {r['loss_fit']:.5f} | {r['loss_fit_e_true_path']:.5f} | "
                   f"{r['loss_truth']:.5f} | {p['max_px']:.2f} ({p['max_sigma']:.1f}) | {r['cpu_s']:.0f} |")
    return head + "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stage", default=None)
    ap.add_argument("--gt", default=None)
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--scene", default=None, help="one scene: synth + init (if not in --work yet) and its fits here")
    ap.add_argument("--work", default="out/traj_pin")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--synth-fit-grid", type=int, default=None)
    ap.add_argument("--grid", default=None, help="init --grid (N or auto; default the capture's suggestion)")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--modes", default="pinned,prior")
    ap.add_argument("--settings", default=None, help="FitSettings overrides as JSON (e.g. a test's small schedule)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cfl", type=float, default=None, help="the fit's adaptive substep CFL number (default "
                    "simulation.CFL, 0.6); rows record it")
    ap.add_argument("--jobs", type=int, default=1, help="scenes at once (one process each)")
    ap.add_argument("--out", default=None, help="JSON lines to append the rows to")
    ap.add_argument("--tag", default="")
    ap.add_argument("--transfer-tau", type=float, default=0.0,
                    help="synth and init --transfer-tau (the truth and the fit with the rate transfer; #24): use a "
                         "separate --work, the captures differ")
    a = ap.parse_args(argv)
    if a.stage:
        if not a.gt:
            raise SystemExit("--stage needs --gt")
        print(table(one_stage(a.stage, a.gt, a, a.tag)))
        return
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    if a.scene:
        st, gt = make_stage(a.scene, a, work)
        print(table(one_stage(st, gt, a, a.tag)))
        return
    if not a.scenes:
        raise SystemExit("give --stage STAGE --gt DIR, --scene NAME or --scenes a,b,...")
    out = Path(a.out) if a.out else work / "rows.jsonl"
    procs = []
    passthru = ["--iterations", str(a.iterations), "--modes", a.modes, "--device", a.device, "--out", str(out),
                "--tag", a.tag, "--work", str(work), "--size", a.size] + (["--settings", a.settings] if a.settings else []) \
        + (["--frames", str(a.frames)] if a.frames else []) \
        + (["--synth-fit-grid", str(a.synth_fit_grid)] if a.synth_fit_grid else []) + (["--grid", a.grid] if a.grid else []) \
        + (["--cfl", str(a.cfl)] if a.cfl is not None else []) \
        + (["--transfer-tau", str(a.transfer_tau)] if a.transfer_tau else [])
    t0 = time.perf_counter()
    pending = a.scenes.split(",")
    while pending or procs:
        while pending and len(procs) < max(a.jobs, 1):
            sc = pending.pop(0)
            lf = open(work / f"{sc}.traj_pin.log", "w")
            procs.append((sc, subprocess.Popen([sys.executable, __file__, "--scene", sc, *passthru],
                                               stdout=lf, stderr=subprocess.STDOUT)))
        time.sleep(2)
        for sc, p in list(procs):
            if p.poll() is not None:
                procs.remove((sc, p))
                print(f"{sc}: done (rc {p.returncode}) at {time.perf_counter() - t0:.0f} s", flush=True)
    rows = [json.loads(line) for line in out.read_text().splitlines()] if out.exists() else []
    print(table([r for r in rows if r.get("tag", "") == a.tag]))


if __name__ == "__main__":
    main()
