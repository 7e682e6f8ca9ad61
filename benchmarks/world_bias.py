"""Is our model biased stiff against the world generator, and does resolution remove it? (#24)

For each development capture and each particle cap, `init --grid auto --max-particles CAP` (the
cap decides the grid when a thin part wants more cells than it allows), then the select schedule's
uniform-E sweep with the TRUE interaction (`world_fit.truth_sweep`: contacts, supports, hand
path and floor from the ground truth). One row per
(capture, cap): the grid, cells across the thinnest part, particles, the sweep's best E over the
true median E, its near-best interval and whether it holds the truth.

    python benchmarks/world_bias.py --work data/world_dev --seeds 0-14 --caps 15000,60000 --device cuda --json out/bias.json
    python benchmarks/world_bias.py --work data/world_dev --seeds 3 --caps 4000 --init-only   # grids only (CPU, seconds)
    python benchmarks/world_bias.py --work data/world_stiff --seeds 143 --caps 1500 --rules default,band --grid-scales 1,2

`--rules`, `--grid-scales`, `--steps`, `--blends`: the variants of world_simcheck.py (the pin rule; our grid as a
multiple of grid auto's cells within the cap; the fit's adaptive substep or the truth's; the partial blends at a
rate or once per substep), one row each: does the sweep's minimum move to the truth with them? (#24)

A tuning tool: it refuses the validation split. docs/benchmarks/world_fits.md has the results.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

import physinteract_usd  # noqa: F401
from physinteract_usd import api
from physinteract_usd.errors import InputError
from physinteract_usd.synth.splits import refuse_validation
from physinteract_usd.usd.stage import read_grid_choice

sys.path.insert(0, str(Path(__file__).resolve().parent))

from world_fit import truth_sweep  # noqa: E402
from world_suite import parse_seeds  # noqa: E402


def prepare_stage(cap: Path, gt: Path, out: Path, max_particles: int, grid="auto") -> dict:
    """A fresh stage of the capture at grid auto within `max_particles`; returns init's grid choice."""
    g = json.loads((gt / "gt.json").read_text())["suggested_init"]
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    stage = out / "scene.usda"
    api.init(stage, cap, grid=grid, padding=g["padding"], youngs_range=tuple(g["youngs_range"]),
             max_poisson=g["max_poisson"], density=g["density"], max_particles=int(max_particles),
             log=lambda *a: None)
    return read_grid_choice(stage) or {}


def gt_dir(work: Path, n: str) -> Path:
    """The capture's ground truth: <n>.gt beside it (world_suite.py extract moves it there) or <n>/gt."""
    for p in (work / f"{n}.gt", work / n / "gt"):
        if (p / "gt.json").exists():
            return p
    raise InputError(work / n, "no ground truth (gt.json) next to this capture")


def one(work: Path, n: str, cap_n: int, device: str, init_only: bool, scratch: Path, true_nu: bool = False,
        grid="auto") -> dict:
    cap, gt = work / n, gt_dir(work, n)
    out = scratch / f"{n}_{cap_n}_{grid}_{'nu' if true_nu else 'default'}"
    t0 = time.perf_counter()
    gc = prepare_stage(cap, gt, out, cap_n if grid == "auto" else 10 ** 7, grid=grid)
    row = {"scene": n, "cap": cap_n, "grid": gc.get("grid"), "cells_across": gc.get("cellsAcross"),
           "particles": gc.get("particles"), "limit": gc.get("limit") or "", "init_s": time.perf_counter() - t0,
           "nu_mode": "true" if true_nu else "default"}
    if init_only:
        return row
    stage = out / "scene.usda"
    floor = json.loads((gt / "gt.json").read_text()).get("floor")   # truth_sweep adds the truth's
    e_true = float(np.median(np.load(gt / "youngs_modulus.npy")))
    t1 = time.perf_counter()
    try:
        nu = float(np.median(np.load(gt / "poisson_ratio.npy"))) if true_nu else None
        sw = truth_sweep(stage, gt, device, e_true, nu=nu)
        row.update({k: v for k, v in sw.items() if k != "truth_sweep"})
        row["ratio"] = sw["truth_sweep_e"] / e_true
    except Exception as exc:  # noqa: BLE001 - one capture's failure is a row, not the end of the run
        row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
    row.update({"e_true": e_true, "floor": bool(floor), "sweep_s": time.perf_counter() - t1})
    return row


def table(rows: list[dict]) -> str:
    out = ["| capture | nu | cap | grid | cells across | particles | limit | variant (rule, grid x, step, blend) | E true | best uniform E / true | near-best interval / true | holds truth | sweep s |",
           "|---|---|---:|---:|---:|---:|---|---|---:|---:|---|---|---:|"]
    for r in rows:
        iv = r.get("truth_sweep_interval")
        ivs = f"{iv[0] / r['e_true']:.2f} .. {iv[1] / r['e_true']:.2f}" if iv and r.get("e_true") else "-"
        ratio = f"{r['ratio']:.2f}" if "ratio" in r else r.get("error", "-")
        nu = f"{r['truth_sweep_nu']:.2f} ({r['nu_mode']})" if r.get("truth_sweep_nu") is not None else r.get("nu_mode", "-")
        out.append(f"| {r['scene']} | {nu} | {r['cap']} | {r.get('grid')} | {r.get('cells_across') or 0:.1f} | {r.get('particles')} "
                   f"| {r.get('limit') or '-'} | {r.get('rule', 'default')}, {r.get('grid_scale', 1):g}, {r.get('step', 'fit')}, {r.get('blend', 'rate')} "
                   f"| {r.get('e_true', float('nan')):.3g} | {ratio} | {ivs} "
                   f"| {r.get('truth_sweep_covers', '-')} | {r.get('sweep_s', 0):.0f} |")
    return "\n".join(out)


def per_capture(tool: str, work: Path, seeds: str, rows_of, json_path=None, table_of=None, show=None) -> int:
    """The dev-capture loop the world experiments share: for each seed's dev_NNNN under `work` (a
    missing folder is one line, exit 2; a validation capture is refused: these are tuning tools),
    `rows_of(name)` gives its rows, appended to `json_path` as they come and printed by `show`
    (default: the row as JSON); `table_of(rows)` is printed at the end. Returns the exit code."""
    if not work.is_dir():
        print(f"{tool}: error: {work}: captures folder not found", file=sys.stderr)
        return 2
    try:
        refuse_validation(work, tool)     # the folder itself, whatever captures it holds
    except InputError as exc:
        print(f"{tool}: error: {exc.oneline()}", file=sys.stderr)
        return 2
    names = [f"dev_{s:04d}" for s in parse_seeds(seeds)]
    missing = [n for n in names if not (work / n).is_dir()]
    if len(missing) == len(names):
        print(f"{tool}: error: {work}: none of the seeds' captures is there ({', '.join(missing[:4])}"
              f"{', ...' if len(missing) > 4 else ''})", file=sys.stderr)
        return 2
    for n in missing:
        print(f"{tool}: note: {work / n}: not there, skipped", file=sys.stderr)
    rows = []
    for n in names:
        if n in missing:
            continue
        try:
            refuse_validation(work / n, tool)
            rs = rows_of(n)
        except InputError as exc:
            print(f"{tool}: error: {exc.oneline()}", file=sys.stderr)
            return 2
        for r in rs:
            rows.append(r)
            print(show(r) if show else json.dumps(r, default=str), flush=True)
            if json_path:
                with open(json_path, "a") as f:
                    f.write(json.dumps(r, default=str) + "\n")
    if table_of:
        print(table_of(rows))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="folder of development captures (<name>/ and <name>.gt/)")
    ap.add_argument("--seeds", required=True, help="capture seeds, e.g. 0-14")
    ap.add_argument("--caps", default="15000,60000", help="particle caps for grid auto, comma separated")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None, help="rows appended here as they finish")
    ap.add_argument("--init-only", action="store_true", help="only the grids each cap gives (no sweep)")
    ap.add_argument("--nu", default="default", help="the sweep's Poisson ratio: default (the stage's), true (the truth's "
                    "median) or both (two rows per cap)")
    ap.add_argument("--scratch", default="/tmp/world_bias")
    ap.add_argument("--rules", default="default", help="pin rules (world_simcheck.RULES: default, band, gain1)")
    ap.add_argument("--grid-scales", default="1", help="our grid: 1 = grid auto within the cap; 2 = twice its cells")
    ap.add_argument("--steps", default="fit", help="fit (adaptive substep) and/or truth (the truth's substeps a frame)")
    ap.add_argument("--blends", default="rate", help="rate (the fit's) and/or substep (the generator's partial blends)")
    a = ap.parse_args(argv)
    caps = [int(c) for c in a.caps.split(",") if c]
    modes = {"default": [False], "true": [True], "both": [False, True]}[a.nu]
    import world_simcheck as wsc
    from physinteract_usd import simulation

    rules = [r for r in a.rules.split(",") if r]
    if any(r not in wsc.RULES for r in rules):
        print(f"world_bias.py: error: --rules: unknown {[r for r in rules if r not in wsc.RULES][0]!r} "
              f"({', '.join(wsc.RULES)})", file=sys.stderr)
        return 2
    scales = [float(t) for t in a.grid_scales.split(",") if t]
    steps = [t for t in a.steps.split(",") if t]
    blends = [t for t in a.blends.split(",") if t]

    def rows_of(n):
        rows = []
        n_auto = {}
        for c in caps:
            for gs in scales:
                grid = "auto"
                if gs != 1.0:
                    if c not in n_auto:
                        n_auto[c] = int(prepare_stage(Path(a.work) / n, gt_dir(Path(a.work), n),
                                                      Path(a.scratch) / f"{n}_{c}_probe", c).get("grid"))
                    grid = int(round(gs * n_auto[c]))
                for rule in rules:
                    for stp in steps:
                        for bl in blends:
                            g = json.loads((gt_dir(Path(a.work), n) / "gt.json").read_text())
                            simulation.PIN_RULE = wsc.RULES[rule]
                            try:
                                with wsc.forced(int(g["gt_sim"]["substeps_per_frame"]) if stp == "truth" else None, bl):
                                    for tn in modes:
                                        r = one(Path(a.work), n, c, a.device, a.init_only, Path(a.scratch), true_nu=tn,
                                                grid=grid)
                                        r.update({"rule": rule, "grid_scale": gs, "step": stp, "blend": bl})
                                        rows.append(r)
                            finally:
                                simulation.PIN_RULE = wsc.RULES["default"]
        return rows

    return per_capture("world_bias.py", Path(a.work), a.seeds, rows_of, a.json, table,
                       show=lambda r: json.dumps({k: v for k, v in r.items() if k != "truth_sweep"}))

if __name__ == "__main__":
    sys.exit(main())
