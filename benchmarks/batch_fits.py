"""One fit against B fits of the same scene from different starts batched in one process
(fit/batched.py: one tiled rollout forward+backward per iteration for all B copies), on one device.

    python benchmarks/batch_fits.py --device cuda                      # the bundled sample, the demo's settings
    python benchmarks/batch_fits.py --device cpu --grid 12 --iterations 3   # tiny, to check it runs

The scene: the bundled sample (samples/foam_bar, 14 frames) initialised at the demo's settings
(`init --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150`), true
contacts (its gt/), the default bumps schedule (60 iterations, the convergence stop on), no
confidence estimate (the same for every case: it runs once, for the chosen start). The uniform
start search runs once (timed apart) and every case starts from its E; a short warm-up (Warp's
module loads, one fit iteration) runs before the timed cases. Each case builds its own problem, so
its rollouts' CUDA graphs are captured inside its time.

Cases: "1" = `fit_bumps` (the one fit the app runs); "B=2", "B=4" = `fit_bumps_batched` from the
first B of `batched.START_FACTORS` (x 1, 0.5, 2, 0.25 of the searched uniform E; seeds 0..B-1; the
first copy is the one fit's start). Each copy stops on its own; the batch ends with the last.
Printed: wall and process CPU time in all and per lockstep iteration, the time against one fit
(the issue's target: four small fits batched <= 2x one fit's time), and each copy's iterations,
final loss, MA (per Gaussian against gt/youngs_modulus.npy) and masked PSNR (the fit's own frame
metrics). `--out DIR` also writes the rows as JSON lines.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _clock():
    return time.perf_counter(), time.process_time()


def _sync(device):
    if str(device).startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--capture", default=str(ROOT / "samples" / "foam_bar"))
    ap.add_argument("--grid", type=int, default=24, help="init --grid (the demo: 24; 12 for a tiny CPU check)")
    ap.add_argument("--iterations", type=int, default=60, help="per fit (the demo's default: 60)")
    ap.add_argument("--copies", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--patience", type=int, default=None, help="the convergence stop's patience (default: the fit's)")
    ap.add_argument("--work", default=None, help="folder for the stage (default: a temporary one)")
    ap.add_argument("--out", default=None, help="write the rows as JSON lines into OUT/batch_fits.jsonl")
    a = ap.parse_args(argv)

    import torch

    from physinteract_usd import api
    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.devices import cpu_threads, device_name
    from physinteract_usd.fit import fit_bumps
    from physinteract_usd.fit.batched import default_starts, fit_bumps_batched
    from physinteract_usd.fit.optimize import golden_uniform_search
    from physinteract_usd.fit.material import MaterialField

    cpu_threads(a.device)
    cap = Path(a.capture)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="batch_fits_"))
    work.mkdir(parents=True, exist_ok=True)
    stage = work / "scene.usda"
    quiet = lambda *x: None  # noqa: E731
    api.init(stage, cap, grid=a.grid, padding=0.3, youngs_range=(1e3, 6e4), max_poisson=0.4, density=150.0,
             force=True, discard_fits=True, log=quiet)
    over = {"confidence_probes": 0}
    if a.patience is not None:
        over["plateau_patience"] = a.patience
    job = prepare_fit(stage, iterations=a.iterations, contact_from=cap / "gt", device=a.device, log=quiet,
                      settings_overrides=over, progress=False)
    s = job.settings
    e_gt = np.load(cap / "gt" / "youngs_modulus.npy")
    dev = device_name(a.device)
    print(f"device: {dev}; torch {torch.__version__}; scene {cap.name} at grid {a.grid}, "
          f"{len(job.scene.particles_positions)} particles, {job.scene.n_frames} frames; "
          f"{s.iterations} iterations per fit, patience {s.plateau_patience}", flush=True)

    # the start search (once) and a warm-up iteration
    prob = make_problem(job)
    st = prob.scene.settings
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype, device=prob.tdev)
    mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
    w0, c0 = _clock()
    e_u = golden_uniform_search(prob, mat, s.search_evals, None)
    _sync(a.device)
    w1, c1 = _clock()
    print(f"start search: uniform E {e_u:.4g} Pa in {w1 - w0:.1f} s wall, {c1 - c0:.1f} s CPU", flush=True)
    fit_bumps(prob, dataclasses.replace(s, iterations=1), progress=False, uniform_e=e_u)
    fit_bumps_batched(prob, dataclasses.replace(s, iterations=1), default_starts(2, s.seed), uniform_e=e_u,
                      progress=False)
    _sync(a.device)
    print(f"warm-up done ({time.perf_counter() - w1:.1f} s)", flush=True)

    def copy_row(r):
        fm = M.summarize(r.frame_metrics)
        return {"iterations": len(r.loss_history), "final_loss": r.final_loss,
                "ma": M.material_accuracy(r.youngs_gaussian, e_gt) if len(e_gt) == len(r.youngs_gaussian) else None,
                "psnr_masked": fm["psnr_masked"], "median_e": float(np.median(r.youngs)),
                "status": (r.model.get("start") or {}).get("status", "interrupted" if r.interrupted else "done")}

    rows = []
    for B in [1] + [int(b) for b in a.copies]:
        p = make_problem(job)
        _sync(a.device)
        w0, c0 = _clock()
        if B == 1:
            res = [fit_bumps(p, s, progress=False, uniform_e=e_u)]
        else:
            res = fit_bumps_batched(p, s, default_starts(B, s.seed), uniform_e=e_u, progress=False)
        _sync(a.device)
        w1, c1 = _clock()
        copies = [copy_row(r) for r in res]
        lock = max(c["iterations"] for c in copies)
        row = {"case": "1" if B == 1 else f"B={B}", "copies": B, "device": dev, "grid": a.grid,
               "particles": len(p.x0), "frames": p.T, "wall_s": w1 - w0, "cpu_s": c1 - c0, "lockstep_iterations": lock,
               "wall_per_iteration_s": (w1 - w0) / max(lock, 1), "cpu_per_iteration_s": (c1 - c0) / max(lock, 1),
               "substeps": p.sim.substeps, "copy": copies}
        rows.append(row)
        print(f"{row['case']}: {row['wall_s']:.1f} s wall ({row['cpu_s']:.1f} s CPU), {lock} iterations, "
              + "; ".join(f"[{i}] {c['iterations']} it loss {c['final_loss']:.5f} MA {c['ma']:.3f}"
                          for i, c in enumerate(copies)), flush=True)

    one = rows[0]
    print()
    print(f"### {dev}, {cap.name} at grid {a.grid} ({one['particles']} particles, {one['frames']} frames), "
          f"{s.iterations} iterations per fit" + ("" if a.device.startswith("cuda") else
                                                  " -- CPU: tiling does not pay here (a size check only)"))
    print()
    print("| case | wall s (CPU s) | x one fit | lockstep iterations | wall s / iteration | per copy: iterations, "
          "final loss, MA, masked PSNR |")
    print("|---|---:|---:|---:|---:|---|")
    for r in rows:
        per = "; ".join(f"{c['iterations']} it, {c['final_loss']:.5f}, MA {c['ma']:.3f}, {c['psnr_masked']:.2f} dB"
                        for c in r["copy"])
        print(f"| {r['case']} | {r['wall_s']:.1f} ({r['cpu_s']:.1f}) | {r['wall_s'] / one['wall_s']:.2f} | "
              f"{r['lockstep_iterations']} | {r['wall_per_iteration_s']:.3f} | {per} |")
    four = next((r for r in rows if r["copies"] == 4), None)
    if four is not None:
        ratio = four["wall_s"] / one["wall_s"]
        print(f"\nfour fits batched: {ratio:.2f}x one fit's time (target <= 2x: {'met' if ratio <= 2 else 'missed'}); "
              f"per fit {four['wall_s'] / 4 / one['wall_s']:.2f}x")
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        with open(out / "batch_fits.jsonl", "a") as fh:
            for r in rows:
                fh.write(json.dumps(r) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
