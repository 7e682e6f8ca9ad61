"""Old vs new on the suite's small scenes: does a lever for bumps stopping short (#24, foam_bar) help
foam_bar without hurting the others? (docs/benchmarks/fit.md, "foam_bar stops short")

Per scene, one process each (--jobs at once): `suite.py` makes the capture and the stage as the suite
does (synth, init with the capture's suggested settings or --grid, the default bumps fit through the
CLI with true contacts, evaluate: the "old" row), then each variant is fitted in process on the same
stage from scratch (same iterations, true contacts, schedule bumps, the variant's FitSettings
overrides) and scored: MA (per Gaussian, as `evaluate`), the fit's final loss, its CPU/GPU wall
time. Rows are appended to --out (JSON lines) as they finish, so a run stopped by a time limit keeps
what it did; the table is printed at the end (and by --table-only).

Variants (name=overrides): damp = {"nuisance_damping": True} (a global damping fitted with E, #24), parts20 / parts40 = {"parts_start": 20 / 40}, lr03 = {"lr_material": 0.3},
gn3 = {"gn_steps": 3} (--variants picks, default parts20,parts40,lr03; "" fits none: the old row alone; a variant may be given inline as
name:key=value,key=value).

    python benchmarks/stall_suite.py --scenes foam_bar,hemp_rope,balloon_dog,toy_rope --device cuda \
        --size small --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --work /tmp/ss \
        --out $OUT/stall_suite.jsonl --jobs 4

The suite's standard since the 22nd session (every truth finer than its fit; docs/benchmarks/fit.md, top): the
first half as above (`foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope`, `--synth-fit-grid 128`), the
second half (`balloon,bow_tie,glove,flower,basketball,knit_cap`) with `--synth-fit-grid auto` (the truth made for the
grid init's auto chooses; at the size's 24, bow_tie's, glove's and flower's truths were coarser than their fits).
`benchmarks/gpu_suite12.sh` runs both halves at once under one deadline and prints the 12 rows and their mean.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

VARIANTS = {"damp": {"nuisance_damping": True}, "gn3": {"gn_steps": 3}, "parts0": {"parts_start": 0}, "parts20": {"parts_start": 20}, "parts40": {"parts_start": 40},
            "lr03": {"lr_material": 0.3},
            # a finer third level (#24, 21st session: the suite's fits compress the stiff/soft contrast)
            "lv32": {"levels": (1, 8, 32), "level_share": (0.2, 0.35, 0.45)}}


def parse_variant(v: str) -> tuple[str, dict]:
    if ":" not in v:
        return v, VARIANTS[v]
    name, rest = v.split(":", 1)
    over = {}
    for kv in rest.split(","):
        k, val = kv.split("=", 1)
        over[k] = json.loads(val)
    return name, over


def one_scene(scene: str, a) -> None:
    """The suite's stage and old row (subprocess), then the variants in process (a second
    subprocess: `--variant-worker`), each row appended to a.out."""
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "suite.py"), "--size", a.size, "--device", a.device,
           "--scenes", scene, "--iterations", str(a.iterations), "--out", str(work / scene), "--tag", "old"]
    if a.frames:
        cmd += ["--frames", str(a.frames)]
    if a.synth_fit_grid:
        cmd += ["--synth-fit-grid", str(a.synth_fit_grid)]
    if a.grid:
        cmd += ["--grid", a.grid]
    t = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=gpu_env(scene, a))
    res = work / scene / "results.jsonl"
    rows = [json.loads(x) for x in res.read_text().splitlines()] if res.exists() else []
    rows = [r for r in rows if r.get("scene") == scene and r.get("tag") == "old"]
    old = rows[-1] if rows else {"scene": scene, "error": "suite.py wrote no row"}
    row = {"scene": scene, "variant": "old", "ma": old.get("ma"), "ma_best_uniform": old.get("ma_best_uniform"),
           "psnr_masked": old.get("psnr_masked"), "fit_s": old.get("fit_s"), "grid": old.get("grid"),
           "particles": old.get("particles"), "error": old.get("error"), "wall_s": round(time.perf_counter() - t, 1),
           "by_truth_level": old.get("by_truth_level"), "calibration": old.get("calibration"),
           "pin_rule": __import__("os").environ.get("PHYSINTERACT_PIN_RULE") or "default",
           "support_rule": __import__("os").environ.get("PHYSINTERACT_SUPPORT_RULE") or "the pin rule",
           # the synth's truth's rule (synth.generate.truth_pin_rule): PHYSINTERACT_PIN_RULE never reached it (#24)
           "truth_pin_rule": __import__("os").environ.get("PHYSINTERACT_TRUTH_PIN_RULE") or "default"}
    with open(a.out, "a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
    if old.get("error"):
        return
    for v in [v for v in a.variants.split(",") if v]:
        cmd = [sys.executable, __file__, "--variant-worker", v, "--scene", scene, "--work", str(work), "--device",
               a.device, "--iterations", str(a.iterations), "--out", a.out]
        subprocess.run(cmd, stdout=sys.stdout, stderr=open(work / f"{scene}.{v.split(':')[0]}.log", "w"),
                       env=gpu_env(scene, a))


def gpu_env(scene: str, a) -> dict:
    """The environment of a scene's processes: on a host of several GPUs the i-th scene of --scenes runs on
    the i-th GPU of benchmarks/gpu_spread.py's list (`NGPUS`, `GPU_LIST`, `GPU_OFFSET`)."""
    import os

    from gpu_spread import gpu_for

    env = dict(os.environ)
    g = gpu_for(a.scenes.split(",").index(scene), env)
    if g is not None:
        env["CUDA_VISIBLE_DEVICES"] = g
    return env


def variant_worker(a) -> None:
    import numpy as np

    from physinteract_usd import api
    from physinteract_usd import metrics as M
    from physinteract_usd.synth.gt import read_gt_array

    name, over = parse_variant(a.variant_worker)
    work = Path(a.work) / a.scene
    stage = work / f"{a.scene}.usda"
    gt = work / a.scene / "gt"
    t = time.perf_counter()
    row = {"scene": a.scene, "variant": name, "overrides": over}
    try:
        out = api.fit(str(stage), iterations=a.iterations, contact_from=str(gt), device=a.device, progress=False,
                      log=lambda m: print(m, file=sys.stderr, flush=True),
                      settings_overrides={"schedule": "bumps", **over})
        r = out.result
        e_gt = np.asarray(read_gt_array(gt, "youngs_modulus.npy"), np.float64)
        e_fit = np.asarray(r.youngs_gaussian, np.float64)
        conf = np.asarray(r.confidence_gaussian, np.float64)
        pos = read_gt_array(gt, "gaussian_positions.npy")
        row.update(by_truth_level=M.ma_by_truth_level(e_fit, e_gt, conf, M.peak_green_strain(pos[0], pos)),
                   calibration=M.confidence_calibration(e_fit, e_gt, conf))
        row.update(ma=M.material_accuracy(e_fit, e_gt),
                   final_loss=r.final_loss, median_e=float(np.median(r.youngs)),
                   median_e_truth=float(np.median(e_gt)), effect_parameters=r.effect_parameters,
                   levers={k: r.model.get(k) for k in ("parts_start", "gauss_newton") if r.model.get(k)})
    except Exception as exc:  # noqa: BLE001  (a row says what failed; the other variants go on)
        row["error"] = f"{type(exc).__name__}: {exc}"
    row["wall_s"] = round(time.perf_counter() - t, 1)
    with open(a.out, "a") as fh:
        fh.write(json.dumps(row, default=float) + "\n")
    print(json.dumps(row, default=float), flush=True)


def table(path: str) -> str:
    rows = [json.loads(x) for x in Path(path).read_text().splitlines()] if Path(path).exists() else []
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    head = "| scene | " + " | ".join(variants) + " | best single E |\n|---|" + "---:|" * (len(variants) + 1)
    lines = [head]
    for s in scenes:
        cells = []
        bu = ""
        for v in variants:
            rr = [r for r in rows if r["scene"] == s and r["variant"] == v]
            if not rr:
                cells.append("-")
                continue
            r = rr[-1]
            if r.get("error"):
                cells.append("error")
                continue
            fl = f" ({r['final_loss']:.5f})" if r.get("final_loss") is not None else ""
            cells.append(f"{r['ma']:.3f}{fl}")
            if r.get("ma_best_uniform") is not None:
                bu = f"{r['ma_best_uniform']:.3f}"
        lines.append(f"| {s} | " + " | ".join(cells) + f" | {bu} |")
    return "MA (final loss) per scene and variant; old = the default bumps fit through the CLI\n\n" + "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="foam_bar,hemp_rope,balloon_dog,toy_rope")
    ap.add_argument("--variants", default="parts20,parts40,lr03")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--synth-fit-grid", default=None, help="suite.py's: N cells or auto")
    ap.add_argument("--grid", default=None)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--work", default="out/stall_suite")
    ap.add_argument("--out", default="out/stall_suite/rows.jsonl")
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--variant-worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--scene", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.variant_worker:
        variant_worker(a)
        return
    if not a.table_only:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        for v in [v for v in a.variants.split(",") if v]:
            parse_variant(v)        # a bad name fails here, before any work
        with ThreadPoolExecutor(max_workers=max(1, a.jobs)) as ex:
            list(ex.map(lambda s: one_scene(s, a), a.scenes.split(",")))
    print(table(a.out))


if __name__ == "__main__":
    main()
