"""Does a fitted global damping remove the E bias of the truth's and the fit's different numerical
dissipation? (#24; docs/benchmarks/fit.md, "A fitted damping as a nuisance")

The synthetic truths are MPM runs on a finer cell with more substeps than the fit's; APIC's grid <->
particle round trip loses a share of the motion every substep, so truth and fit are damped differently
and a fit with no damping freedom pushes the difference into E. Per scene, from true contacts with the
path pinned (`joint=False`: E alone against E and c), the same bumps fit:

  base   the stage's effects (none): E (and nu) only
  damp   + the `damping` effect fitted jointly (`FitSettings.nuisance_damping`: its start searched first,
         c = exp(raw), lr_effects), what `fit --nuisance-damping` does

and, forward only at the fit's resolution and step, the truth's E and nu with the true path under a scan
of c: the c whose loss is lowest ("c at the truth's E": the dissipation difference in the fit's damping
units; 0 when the fit's own dissipation already exceeds the truth's: c >= 0). Rows: MA (per Gaussian)
beside the best single E's, median E fit / truth, masked PSNR, the fitted c, the fit's loss, CPU s.

    python benchmarks/damp24.py --scenes telephone_cable,balloon --work /tmp/d24 --size small --frames 10 \
        --iterations 12 --out rows.jsonl            # one process per scene (--jobs)
    python benchmarks/damp24.py --stage S.usda --gt CAP/gt --modes base,damp --cscan 0,1,2,4,8
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
sys.path.insert(0, str(ROOT / "benchmarks"))

from traj_pin import make_stage  # noqa: E402  (synth + init through the CLI, reused when there)


def parabola_min(cs, vals) -> float:
    i = int(np.argmin(vals))
    if 0 < i < len(cs) - 1:
        a, b, _ = np.polyfit(np.asarray(cs[i - 1:i + 2], float), np.asarray(vals[i - 1:i + 2], float), 2)
        if a > 0:
            return float(-b / (2 * a))
    return float(cs[i])


def one_stage(stage, gt_dir, a, tag="") -> list[dict]:
    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit import fit as optimise
    from physinteract_usd.fit.select import frame_losses
    from physinteract_usd.synth.gt import read_gt_array

    if a.cfl is not None:
        import physinteract_usd.simulation as simulation

        simulation.CFL = float(a.cfl)
    e_gt = read_gt_array(gt_dir, "youngs_modulus.npy")
    nu_gt = read_gt_array(gt_dir, "poisson_ratio.npy")
    g0 = read_gt_array(gt_dir, "gaussian_positions.npy")[0]
    ma_best, e_best = M.best_uniform_ma(e_gt)
    rows = []
    for mode in a.modes.split(","):
        if mode not in ("base", "damp"):
            raise SystemExit(f"--modes: unknown mode {mode!r} (base, damp)")
        over = {"schedule": "bumps", **json.loads(a.settings or "{}"), "nuisance_damping": mode == "damp"}
        job = prepare_fit(stage, iterations=a.iterations, contact_from=gt_dir, device=a.device, warm=False,
                          progress=False, log=lambda m: None, settings_overrides=over, joint=not a.free_path)
        prob = make_problem(job)
        s = job.settings
        e_top = float(job.scene.settings.youngs_max)
        c0, t0 = time.process_time(), time.perf_counter()
        r = optimise(prob, s, progress=False, log=None)
        cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - t0
        frames = list(range(1, prob.T))
        row = {"tag": tag, "stage": str(stage), "scene": Path(stage).stem, "mode": mode, "iterations": s.iterations,
               "particles": int(len(prob.x0)), "ma": M.material_accuracy(r.youngs_gaussian, e_gt),
               "ma_best_uniform": ma_best, "e_best_uniform": e_best,
               "median_e_fit": float(np.median(r.youngs_gaussian)), "median_e_truth": float(np.median(e_gt)),
               "psnr_masked": float(np.nanmean([min(f["psnr_masked"], 100) for f in r.frame_metrics])),
               "final_loss": float(r.final_loss), "loss_fit": float(np.mean(frame_losses(prob, r, s, frames, e_top))),
               "damping_c": float((r.effect_parameters.get("damping") or {}).get("coefficient", 0.0)),
               "substeps": int(prob.sim.substeps), "cfl": a.cfl, "free_path": bool(a.free_path),
               "cpu_s": round(cpu_s, 1), "wall_s": round(wall_s, 1), "device": a.device}
        if mode == "damp" and a.cscan:
            # the truth's E and nu (its nearest Gaussian's at rest) with the true path, under a scan of c
            names = prob.sim.slot_names()
            _, nn = cKDTree(g0).query(np.asarray(prob.x0))
            t_true = [tr.detach().cpu().numpy() for tr in prob.initial_trajectories()]
            cs = [float(c) for c in a.cscan.split(",")]
            vals = []
            for c in cs:
                tr = dataclasses.replace(r, youngs=e_gt[nn], poisson=nu_gt[nn], trajectories=dict(zip(names, t_true)),
                                         effect_parameters={"damping": {"coefficient": max(c, 1e-6)}})
                vals.append(float(np.mean(frame_losses(prob, tr, s, frames, e_top))))
            row["cscan"] = {"c": cs, "loss_truth": vals, "c_best": parabola_min(cs, vals)}
        rows.append(row)
        if a.out:
            with open(a.out, "a") as fh:
                fh.write(json.dumps(row, default=float) + "\n")
        print(json.dumps(row, default=float), flush=True)
    return rows


def table(rows: list[dict]) -> str:
    head = ("| scene | mode | MA | best single E | median E fit / truth | masked PSNR | fitted c (1/s) | loss "
            "| c at the truth's E | truth's loss c=0 -> best | CPU s |\n" + "|---" * 11 + "|\n")
    out = []
    for r in rows:
        cs = r.get("cscan")
        cb = f"{cs['c_best']:.2f}" if cs else ""
        tl = f"{cs['loss_truth'][0]:.5f} -> {min(cs['loss_truth']):.5f}" if cs else ""
        out.append(f"| {r['scene']} | {r['mode']} | {r['ma']:.3f} | {r['ma_best_uniform']:.3f} | "
                   f"{r['median_e_fit'] / r['median_e_truth']:.2f} | {r['psnr_masked']:.2f} | {r['damping_c']:.2f} | "
                   f"{r['loss_fit']:.5f} | {cb} | {tl} | {r['cpu_s']:.0f} |")
    return head + "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stage", default=None)
    ap.add_argument("--gt", default=None)
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--scene", default=None)
    ap.add_argument("--work", default="out/damp24")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--synth-fit-grid", type=int, default=None)
    ap.add_argument("--grid", default=None)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--modes", default="base,damp")
    ap.add_argument("--cscan", default="0,0.5,1,2,4,8", help="c values (1/s) of the truth's-E scan ('' : none)")
    ap.add_argument("--settings", default=None, help="FitSettings overrides as JSON")
    ap.add_argument("--free-path", action="store_true", help="fit the path too (default: pinned to the truth's)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cfl", type=float, default=None)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", default=None)
    ap.add_argument("--tag", default="")
    ap.add_argument("--transfer-tau", type=float, default=0.0)
    ap.add_argument("--table-only", action="store_true", help="print the table of --out's rows")
    a = ap.parse_args(argv)
    if a.table_only:
        print(table([json.loads(x) for x in Path(a.out).read_text().splitlines() if x.strip()]))
        return
    if a.stage:
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
    a.out = a.out or str(work / "rows.jsonl")
    scenes = a.scenes.split(",")
    passthru = [x for x in (argv if argv is not None else sys.argv[1:])]
    i = passthru.index("--scenes")
    del passthru[i:i + 2]
    if "--out" not in passthru:
        passthru += ["--out", a.out]
    running = []
    for sc in scenes:
        while len(running) >= a.jobs:
            running = [p for p in running if p.poll() is None]
            time.sleep(2)
        log = open(work / f"{sc}.damp24.log", "w")
        running.append(subprocess.Popen([sys.executable, __file__, "--scene", sc, *passthru], stdout=log,
                                        stderr=subprocess.STDOUT))
    for p in running:
        p.wait()
    rows = [json.loads(x) for x in Path(a.out).read_text().splitlines() if x.strip()] if Path(a.out).exists() else []
    print(table(rows))


if __name__ == "__main__":
    main()
