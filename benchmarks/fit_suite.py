"""Fit accuracy on synthetic scenes, through the application layer: synth (cached) -> init (the
capture's suggested settings) -> fit from the true contacts -> evaluate, one JSON row per fit.

    python benchmarks/fit_suite.py --scenes foam_bar,bow_tie --work data/fits --out out/fits.jsonl \\
        [--frames 14] [--grid 20] [--iterations 60] [--set schedule=ladder,max_regions=4] [--tag A]
        [--device cuda] [--seeds 0]

Rows are appended to --out as each fit ends (a run cut short keeps what it measured); a fit whose
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
    from physinteract_usd import api

    cap = work / (scene if frames is None else f"{scene}-f{frames}")
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
    done = {(r["scene"], r["tag"], r["seed"]) for r in rows}
    for scene in [s for s in a.scenes.split(",") if s]:
        for seed in (int(x) for x in a.seeds.split(",")):
            if (scene, a.tag, seed) in done:
                continue
            t0 = time.perf_counter()
            try:
                row = run_one(scene, work, a.frames, a.grid, a.iterations, parse_set(a.set), a.device, seed, a.tag)
            except Exception as exc:  # noqa: BLE001  (one scene's failure is a row; the rest go on)
                traceback.print_exc()
                row = {"scene": scene, "tag": a.tag, "seed": seed, "error": f"{type(exc).__name__}: {exc}"}
            row["wall_s"] = time.perf_counter() - t0
            with out.open("a") as f:
                f.write(json.dumps(row, default=float) + "\n")
            print(f"{a.tag} {scene} s{seed}: " + (f"MA {row['ma']:.3f} (uniform {row['ma_best_uniform']:.3f}), masked PSNR "
                                                 f"{row['psnr_masked']:.2f}, {row['model'].get('regions', '-')} regions, "
                                                 f"{row['fit_s']:.0f} s" if "ma" in row else row["error"]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
