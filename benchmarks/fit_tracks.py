"""Fits with and without the point-track term (`fit --track-weight W`, fit/tracks_loss.py) on
development data: the bundled sample and synthetic suite scenes (never the validation split).

Per capture: init at the given grid (the capture's suggested settings otherwise), then for each
weight a fresh stage, `fit --contact-from gt --iterations N --track-weight W --json` and `evaluate
--json`, through the CLI in subprocesses. Rows: MA, masked PSNR, the fitted median E against the
truth's median, the fit's CPU time (user + sys of the child processes: the machine is shared, so
wall time is inflated by others' load) and wall time. Rows are appended to OUT/rows.jsonl (a rerun
skips rows already there) and the markdown table printed.

    python benchmarks/fit_tracks.py --case sample:samples/foam_bar:16 --case toy_rope::small \
        --weights 0,1,5 --iterations 20 --out out/fit_tracks
(`NAME:CAPTURE_DIR:GRID`; an empty CAPTURE_DIR synthesises the suite scene NAME at size small;
an empty GRID takes the capture's suggestion.)
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def cli(args, log, capture=False):
    t0 = time.time()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-m", "physinteract_usd", *map(str, args)], text=True,
                       stdout=subprocess.PIPE if capture else log, stderr=log)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return p.returncode, (p.stdout if capture else None), cpu, time.time() - t0


def suggested(cap: Path) -> dict:
    gt = cap / "gt" / "gt.json"
    if gt.exists():
        s = json.loads(gt.read_text()).get("suggested_init")
        if s:
            return s
    # the bundled sample: its README's suggested init line
    line = next(ln for ln in (cap / "README.txt").read_text().splitlines() if "init scene.usda" in ln)
    toks = line.split()
    get = lambda f: toks[toks.index(f) + 1]  # noqa: E731
    return {"grid": int(get("--grid")), "padding": float(get("--padding")),
            "youngs_range": [float(v) for v in get("--youngs-range").split(",")],
            "max_poisson": float(get("--max-poisson")), "density": float(get("--density"))}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", action="append", required=True, help="NAME:CAPTURE_DIR:GRID")
    ap.add_argument("--weights", default="0,1")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--schedule", default=None)
    ap.add_argument("--device", default="cpu", help="cpu or cuda (synth, fit and evaluate)")
    ap.add_argument("--out", default="out/fit_tracks")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    done = set()
    if rows_path.exists():
        for ln in rows_path.read_text().splitlines():
            r = json.loads(ln)
            done.add((r["case"], r["grid"], r["track_weight"], r["iterations"], r.get("schedule")))
    weights = [float(w) for w in a.weights.split(",")]
    for case in a.case:
        name, cap, grid = (case.split(":") + ["", ""])[:3]
        log = open(out / f"{name}.log", "a")
        if not cap:
            cap = out / "captures" / name
            if not (cap / "gt" / "gt.json").exists():
                rc, *_ = cli(["synth", name, cap, "--size", "small", "--force", "--device", a.device], log)
                if rc:
                    sys.exit(f"synth {name} failed (see {log.name})")
        cap = Path(cap)
        if (cap / "SPLIT").exists() or "validation" in str(cap):
            sys.exit(f"{cap}: not development data; tuning on the validation split is refused")
        sug = suggested(cap)
        g = int(grid) if grid else int(sug["grid"])
        e_gt = np.load(cap / "gt" / "youngs_modulus.npy")
        for w in weights:
            key = (name, g, w, a.iterations, a.schedule)
            if key in done:
                continue
            d = out / f"{name}_g{g}_w{w:g}_i{a.iterations}{'_' + a.schedule if a.schedule else ''}"
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir(parents=True)
            st = d / "scene.usda"
            rc, *_ = cli(["init", st, "--capture", cap, "--grid", g, "--padding", sug["padding"],
                          "--youngs-range", ",".join(str(v) for v in sug["youngs_range"]),
                          "--max-poisson", sug["max_poisson"], "--density", sug["density"]], log)
            if rc:
                sys.exit(f"init {name} failed")
            fit = ["fit", st, "--contact-from", cap / "gt", "--iterations", a.iterations, "--json",
                   "--track-weight", w, "--device", a.device]
            if a.schedule:
                fit += ["--schedule", a.schedule]
            rc, so, cpu, wall = cli(fit, log, capture=True)
            if rc:
                print(f"{name} w={w}: fit failed (see {log.name})")
                continue
            s = json.loads(so)
            rc, ev, _, _ = cli(["evaluate", st, "--gt", cap / "gt", "--json", "--device", a.device], log,
                                capture=True)
            ev = json.loads(ev)
            row = {"device": a.device, "case": name, "grid": g, "track_weight": w, "iterations": a.iterations,
                   "schedule": a.schedule,
                   "ma": ev["ma"], "psnr_masked": ev["psnr_masked"], "psnr": ev["psnr"],
                   "e_fit_median": s["youngs_modulus_pa"]["median"], "e_true_median": float(np.median(e_gt)),
                   "cpu_s": round(cpu, 1), "wall_s": round(wall, 1), "final_loss": s["final_loss"],
                   "fit_iterations": s["iterations"], "identifiability": s.get("identifiability")}
            with open(rows_path, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    rows = [json.loads(ln) for ln in rows_path.read_text().splitlines()]
    print("| capture | grid | schedule | iterations | track weight | MA | PSNR masked | E fit / E true (medians) | "
          "what fit says about E | CPU s | wall s |")
    print("|---|---:|---|---:|---:|---:|---:|---|---|---:|---:|")
    for r in rows:
        idf = r.get("identifiability") or {}
        iv = idf.get("interval")
        said = f"{idf.get('level')} {iv[0]:.3g}..{iv[1]:.3g}" if iv else (idf.get("level") or "-")
        print(f"| {r['case']} | {r['grid']} | {r.get('schedule') or 'bumps'} | {r['iterations']} | "
              f"{r['track_weight']:g} | {r['ma']:.3f} | {r['psnr_masked']:.2f} | {r['e_fit_median']:.3g} / "
              f"{r['e_true_median']:.3g} ({r['e_fit_median'] / r['e_true_median']:.2f}x) | {said} | "
              f"{r['cpu_s']:.0f} | {r['wall_s']:.0f} |")


if __name__ == "__main__":
    main()
