"""Fit accuracy on synthetic scenes, through the application layer: synth (cached) -> init (the
capture's suggested settings) -> fit from the true contacts -> evaluate, one JSON row per fit.

    python benchmarks/fit_suite.py --scenes foam_bar,bow_tie --work data/fits --out out/fits.jsonl \\
        [--frames 14] [--grid 20] [--iterations 60] [--variant A:schedule=ladder,max_regions=4 ...]
        [--device cuda] [--seeds 0] [--jobs 15 --cuda-jobs 1] [--deadline 540]

Each (scene, variant, seed) is one job; `--jobs N` runs N of them at once in worker processes on
the CPU (Warp's CPU backend is single-threaded: one core each) and `--cuda-jobs M` more on the
GPU; `--deadline S` stops starting jobs after S seconds and stops the run at S + the longest
fit seen so far (what finished is kept). Rows are appended to --out as each fit ends; a job whose
(scene, tag, seed) row exists is skipped, so a run can be resumed. `--table` prints the table of
the rows in --out (MA, best single E's MA, masked PSNR, regions, seconds) per tag.

Which data: the 13-scene suite (`synth --list`) is the development set. A validation split made
by the generalisation suite's own command refuses to be read here (it is never tuned on).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import traceback
from pathlib import Path


def _value(v: str):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    if v.startswith("(") or v.startswith("["):
        return tuple(_value(x) for x in v.strip("()[]").split(";") if x)
    return {"true": True, "false": False}.get(v.lower(), v)


def parse_set(text: str) -> dict:
    """`key=value,key=value` (tuples as (a;b)) into FitSettings overrides."""
    out = {}
    for item in [t for t in (text or "").split(",") if t]:
        k, _, v = item.partition("=")
        out[k.strip()] = _value(v.strip())
    return out


def prepare(scene: str, work: Path, frames: int | None, device: str) -> tuple[Path, Path]:
    """The scene's capture (made once: a lock file keeps two workers from making it together)."""
    import fcntl

    from physinteract_usd import api

    cap = work / (scene if frames is None else f"{scene}-f{frames}")
    work.mkdir(parents=True, exist_ok=True)
    with open(work / f".{cap.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (cap / "gt" / "gt.json").exists():
            shutil.rmtree(cap, ignore_errors=True)
            api.synth(scene, cap, frames=frames, device=device, log=lambda *a: None)
    return cap, cap / "gt"


def run_one(scene, work, frames, grid, iterations, overrides, device, seed, tag) -> dict:
    from physinteract_usd import api

    cap, gt = prepare(scene, work, frames, device)
    g = json.loads((gt / "gt.json").read_text())["suggested_init"]
    d = work / f"{cap.name}.fit-{tag}-s{seed}"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    stage = d / "scene.usda"
    api.init(stage, cap, grid=grid or g["grid"], padding=g["padding"], youngs_range=tuple(g["youngs_range"]),
             max_poisson=g["max_poisson"], density=g["density"])
    t0 = time.perf_counter()
    out = api.fit(stage, iterations=iterations, contact_from=gt, progress=False, log=lambda *a: None,
                  device=device, seed=seed, settings_overrides=overrides)
    fit_s = time.perf_counter() - t0
    ev = api.evaluate(stage, gt, device=device)
    r = out.result
    return {"scene": scene, "tag": tag, "seed": seed, "frames": frames, "grid": grid or g["grid"],
            "iterations": iterations, "overrides": overrides, "ma": ev["ma"], "ma_best_uniform": ev["ma_best_uniform"],
            "best_uniform_e": ev["best_uniform_e"], "psnr": ev["psnr"], "psnr_masked": ev["psnr_masked"],
            "iou": ev["iou"], "position_error_m": ev["position_error_m"], "fit_s": fit_s,
            "particles": int(len(r.youngs)), "final_loss": r.final_loss, "model": r.model,
            "e_median": float(__import__("numpy").median(r.youngs)), "device": r.device}


def table(rows: list[dict]) -> str:
    lines = ["| tag | scene | MA | best single E | masked PSNR | regions | fit s |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in sorted(rows, key=lambda r: (r["tag"], r["scene"], r["seed"])):
        if "error" in r:
            lines.append(f"| {r['tag']} | {r['scene']} | error: {r['error'][:60]} | | | | |")
            continue
        lines.append(f"| {r['tag']} | {r['scene']} | {r['ma']:.3f} | {r['ma_best_uniform']:.3f} | "
                     f"{r['psnr_masked']:.2f} | {r['model'].get('regions', '-')} | {r['fit_s']:.0f} |")
    by_tag: dict[str, list] = {}
    for r in rows:
        if "error" not in r:
            by_tag.setdefault(r["tag"], []).append(r)
    for tag, rs in sorted(by_tag.items()):
        n = len(rs)
        lines.append(f"| **{tag} mean ({n})** | | **{sum(r['ma'] for r in rs) / n:.3f}** | "
                     f"{sum(r['ma_best_uniform'] for r in rs) / n:.3f} | {sum(r['psnr_masked'] for r in rs) / n:.2f} | | "
                     f"{sum(r['fit_s'] for r in rs) / n:.0f} |")
    return "\n".join(lines)


def _worker(job):
    scene, work, frames, grid, iterations, overrides, device, seed, tag = job
    import os

    for k in [k for k in overrides if k.startswith("env.")]:     # experiments: env.NAME=value
        os.environ[k[4:]] = str(overrides[k])
    overrides = {k: v for k, v in overrides.items() if not k.startswith("env.")}
    import physinteract_usd  # noqa: F401
    from physinteract_usd.devices import cpu_threads

    cpu_threads(device)
    t0 = time.perf_counter()
    try:
        row = run_one(scene, Path(work), frames, grid, iterations, overrides, device, seed, tag)
    except Exception as exc:  # noqa: BLE001  (one scene's failure is a row; the rest go on)
        row = {"scene": scene, "tag": tag, "seed": seed, "error": f"{type(exc).__name__}: {exc}",
               "trace": traceback.format_exc()[-2000:]}
    row["wall_s"] = time.perf_counter() - t0
    row["worker_device"] = device
    return row


def _report(row, out: Path) -> None:
    with out.open("a") as f:
        f.write(json.dumps(row, default=float) + "\n")
    print(f"{row['tag']} {row['scene']} s{row['seed']} [{row.get('worker_device')}]: "
          + (f"MA {row['ma']:.3f} (uniform {row['ma_best_uniform']:.3f}), masked PSNR {row['psnr_masked']:.2f}, "
             f"{row['model'].get('regions', '-')} regions, {row['fit_s']:.0f} s" if "ma" in row else row["error"]),
          flush=True)


def run_pool(jobs: list, out: Path, n_cpu: int, n_cuda: int, deadline: float | None,
             cuda_scenes: set = frozenset()) -> None:
    """Run jobs on n_cpu CPU worker processes and n_cuda CUDA ones, appending rows to `out`; the
    scenes in `cuda_scenes` (the large ones) go to the CUDA workers only, the rest to the CPU ones
    (to either when the other kind has no workers)."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")
    pools = {"cpu": ProcessPoolExecutor(n_cpu, mp_context=ctx) if n_cpu else None,
             "cuda": ProcessPoolExecutor(n_cuda, mp_context=ctx) if n_cuda else None}
    free = {"cpu": n_cpu, "cuda": n_cuda}
    t0 = time.perf_counter()
    pending = list(jobs)
    running = {}
    longest = 0.0
    try:
        while pending or running:
            late = deadline is not None and time.perf_counter() - t0 > deadline
            for dev in ("cuda", "cpu"):
                def mine(j):
                    if not (n_cpu and n_cuda):
                        return True
                    return (j[0] in cuda_scenes) == (dev == "cuda")
                while not late and free[dev] > 0:
                    i = next((i for i, j in enumerate(pending) if mine(j)), None)
                    if i is None:
                        break
                    job = pending.pop(i)
                    job = job[:6] + (dev,) + job[7:]
                    running[pools[dev].submit(_worker, job)] = (dev, job)
                    free[dev] -= 1
            if not running:
                break
            if late and deadline is not None and time.perf_counter() - t0 > deadline + max(longest, 60.0):
                print(f"deadline: {len(running)} fits still running are dropped, {len(pending)} not started", flush=True)
                break
            done, _ = wait(list(running), timeout=5.0, return_when=FIRST_COMPLETED)
            for fut in done:
                dev, job = running.pop(fut)
                free[dev] += 1
                row = fut.result()
                longest = max(longest, row.get("wall_s", 0.0))
                _report(row, out)
    finally:
        for p in pools.values():
            if p is not None:
                procs = list(getattr(p, "_processes", {}).values())
                p.shutdown(wait=False, cancel_futures=True)
                for proc in procs:          # fits still running at the deadline end now
                    if proc.is_alive():
                        proc.terminate()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="")
    ap.add_argument("--work", default="data/fits")
    ap.add_argument("--out", default="out/fits.jsonl")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--grid", type=int, default=None)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--set", default="", help="FitSettings overrides key=value,... (tuples as (a;b))")
    ap.add_argument("--tag", default="default")
    ap.add_argument("--variant", action="append", default=[],
                    help="TAG:key=value,... (repeatable; replaces --tag / --set)")
    ap.add_argument("--jobs", type=int, default=0, help="CPU worker processes (0: run in this process)")
    ap.add_argument("--cuda-jobs", type=int, default=0, help="CUDA worker processes")
    ap.add_argument("--deadline", type=float, default=None, help="seconds after which no job starts")
    ap.add_argument("--cuda-scenes", default="", help="scenes only the CUDA workers fit (the large ones)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--table", action="store_true", help="print the table of --out and exit")
    a = ap.parse_args(argv)
    out = Path(a.out)
    rows = [json.loads(x) for x in out.read_text().splitlines()] if out.exists() else []
    if a.table:
        print(table(rows))
        return 0
    import physinteract_usd  # noqa: F401
    from physinteract_usd.devices import cpu_threads

    cpu_threads(a.device)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = {(r["scene"], r["tag"], r["seed"]) for r in rows if "error" not in r}
    variants = [(v.partition(":")[0], parse_set(v.partition(":")[2])) for v in a.variant] or [(a.tag, parse_set(a.set))]
    scenes = [s for s in a.scenes.split(",") if s]
    jobs = [(scene, str(work), a.frames, a.grid, a.iterations, over, a.device, seed, tag)
            for scene in scenes for tag, over in variants for seed in (int(x) for x in a.seeds.split(","))
            if (scene, tag, seed) not in done]
    if a.jobs or a.cuda_jobs:
        run_pool(jobs, out, a.jobs, a.cuda_jobs, a.deadline, set(a.cuda_scenes.split(",")))
        return 0
    for job in jobs:
        _report(_worker(job), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
