"""Items per hour of `batch` with 1, 2, ... local workers (the process pool) on one machine.

Every item is a copy of one small synthetic capture (foam_bar at --size, --frames frames), run
through the whole chain (init -> extract -> fit -> report -> diagnose -> export) with --iterations
fit iterations; `--tiny` uses the test suite's settings (one golden-section step, no confidence
probes, one basis level; the diagnosis tests damping only, without refits). Each worker count
runs the same items into its own output folder; a warm-up item first fills Warp's kernel cache
(not timed).

    python benchmarks/batch_bench.py --work /tmp/bb --items 4 --workers 1,2 --tiny
    python benchmarks/batch_bench.py --work /tmp/bb --items 8 --workers 1,2,4 --device cuda --json out.json

Prints a markdown table (the machine named) and, with --json, writes the rows.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import time
from pathlib import Path

TINY_FIT = "search_evals=1;confidence_probes=0;levels=[1];level_share=[1.0]"
TINY_DIAGNOSE = "refit=0;candidates=damping;max_pixels=1500"


def machine(device: str) -> str:
    if device.startswith("cuda"):
        import torch

        return f"{torch.cuda.get_device_name(0)}, {os.cpu_count()} CPU cores"
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores"


def manifest(path: Path, caps: list[Path], a) -> Path:
    cols = "source,iterations,grid,device,fit_settings,diagnose_settings"
    fit, diag = (TINY_FIT, TINY_DIAGNOSE) if a.tiny else ("", a.diagnose_settings or "")
    rows = [f"{c},{a.iterations},{a.grid},{a.device},{fit},{diag}" for c in caps]
    path.write_text(cols + "\n" + "\n".join(rows) + "\n")
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", required=True, help="scratch folder (the capture is kept and reused)")
    p.add_argument("--items", type=int, default=4)
    p.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    p.add_argument("--device", default="cpu")
    p.add_argument("--size", default="small")
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--iterations", type=int, default=2)
    p.add_argument("--grid", type=int, default=12)
    p.add_argument("--tiny", action="store_true", help="the test suite's fit and diagnosis settings")
    p.add_argument("--diagnose-settings", default=None, help="without --tiny: the diagnosis's options")
    p.add_argument("--no-warmup", action="store_true")
    p.add_argument("--json", help="write the rows here")
    a = p.parse_args(argv)

    from physinteract_usd import api

    work = Path(a.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    base = work / f"foam_bar_{a.size}_{a.frames}"
    if not (base / "transforms.json").exists():
        t0 = time.perf_counter()
        api.synth("foam_bar", base, size=a.size, frames=a.frames, log=lambda *x: None, force=True, device=a.device)
        print(f"synth foam_bar ({a.size}, {a.frames} frames): {time.perf_counter() - t0:.1f} s", flush=True)
    caps = []
    for i in range(a.items):
        c = work / "caps" / f"item{i:03d}"
        if not c.exists():
            shutil.copytree(base, c, ignore=shutil.ignore_patterns("gt"))
        caps.append(c)
    if not a.no_warmup:
        d = work / "warmup.batch"
        shutil.rmtree(d, ignore_errors=True)
        t0 = time.perf_counter()
        api.batch(manifest(work / "warmup.csv", caps[:1], a), out=d, workers=1, progress=False, log=lambda *x: None)
        print(f"warm-up item: {time.perf_counter() - t0:.1f} s", flush=True)
    rows = []
    for w in [int(x) for x in a.workers.split(",")]:
        d = work / f"w{w}.batch"
        shutil.rmtree(d, ignore_errors=True)
        m = manifest(work / f"w{w}.csv", caps, a)
        t0 = time.perf_counter()
        res = api.batch(m, out=d, workers=w, progress=False, log=lambda *x: None)
        wall = time.perf_counter() - t0
        recs = [r for r in res.records.values() if r.get("status") == "done"]
        steps = {s: statistics.mean(r["steps"][s].get("seconds", 0.0) for r in recs) if recs else float("nan")
                 for s in ("init", "extract", "fit", "report", "diagnose", "export")}
        row = {"device": a.device, "machine": machine(a.device), "workers": w, "items": a.items, "done": len(recs),
               "failed": len(res.failed), "wall_s": wall, "items_per_hour": len(recs) / wall * 3600.0,
               "item_s_mean": statistics.mean(r["seconds"] for r in recs) if recs else float("nan"),
               "steps_s_mean": steps, "frames": a.frames, "size": a.size, "iterations": a.iterations,
               "grid": a.grid, "tiny": a.tiny,
               "load_avg": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
        rows.append(row)
        print(f"workers {w}: {len(recs)}/{a.items} done in {wall:.1f} s -> {row['items_per_hour']:.0f} items/h "
              f"(an item {row['item_s_mean']:.1f} s; load avg {row['load_avg']})", flush=True)
        if res.failed:
            print("  failed: " + "; ".join(f"{n}: {res.records[n].get('error')}" for n in res.failed), flush=True)
    print(f"\n{rows[0]['machine']}; foam_bar {a.size}, {a.frames} frames, grid {a.grid}, {a.iterations} iterations"
          f"{', tiny fit and diagnosis settings' if a.tiny else ''}\n")
    print("| device | workers | items | wall s | items / hour | s per item (in its worker) | fit s | report s | diagnose s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        s = r["steps_s_mean"]
        print(f"| {r['device']} | {r['workers']} | {r['done']}/{r['items']} | {r['wall_s']:.1f} | {r['items_per_hour']:.0f} "
              f"| {r['item_s_mean']:.1f} | {s['fit']:.1f} | {s['report']:.1f} | {s['diagnose']:.1f} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
