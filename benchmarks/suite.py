"""Fit results on the synthetic suite: synth -> init -> fit -> evaluate, through the CLI, per scene.

Every step runs as the user would run it (`python -m physinteract_usd ...` in a subprocess), with
the capture's suggested init settings (its README.txt / gt.json) unless --grid overrides the grid
(a number of cells, or `auto`: init's choice from the object's thinnest part; each row records the
grid init chose, its particles, the thinnest part and the cells across it).
The fit never sees gt/ except through `--contact-from` (contacts, supports and T0), which this
script uses so that fit quality is measured apart from extraction (docs/benchmarks/extract.md
measures that); with `--extracted` gt/ is moved away first and the fit extracts its own contacts.

Rows are appended to a JSON-lines file as scenes finish (a long run can be stopped and resumed:
scenes already in the file are skipped), and the markdown table is rewritten after each scene.

    python benchmarks/suite.py --size small --device cpu --out out/suite_cpu \
        --write docs/benchmarks/suite_cpu.md [--scenes a,b] [--iterations 60] [--frames N] [--grid N|auto]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

PAPER = {  # PhysInteract, Table 1 (averages over its 11 scenes)
    "psnr": 22.03, "ssim": 0.84, "ma": 0.843, "runtime": "~30 min (A40)"}


def run(cmd: list[str], log, cpu: dict | None = None) -> tuple[int, float]:
    """Run a verb; (exit code, wall s). `cpu`: gets "cpu_s", the subprocess's user + sys CPU time
    (wall time is inflated by other jobs on a shared machine)."""
    import resource

    t = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    log.write("$ " + " ".join(cmd) + "\n")
    log.flush()
    p = subprocess.run([sys.executable, "-m", "physinteract_usd", *cmd], stdout=log, stderr=subprocess.STDOUT)
    if cpu is not None:
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu["cpu_s"] = round((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), 1)
    return p.returncode, time.perf_counter() - t


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        try:
            import torch

            return torch.cuda.get_device_name(0)
        except Exception:  # noqa: BLE001
            return device
    from eval_extract import machine  # benchmarks/: the CPU's model name and core count

    return machine()


def init_args(sug: dict) -> list[str]:
    """init's flags for a capture's suggested settings (gt.json's suggested_init), the grid aside."""
    return ["--padding", str(sug["padding"]), "--youngs-range", ",".join(str(v) for v in sug["youngs_range"]),
            "--max-poisson", str(sug["max_poisson"]), "--density", str(sug["density"])] + \
        {True: ["--preload"], False: ["--no-preload"]}.get(sug.get("preload"), [])


def init_caps(a) -> list[str]:
    """init's caps on --grid auto from this run's flags."""
    return ([] if a.max_grid is None else ["--max-grid", str(a.max_grid)]) + \
        ([] if a.max_particles is None else ["--max-particles", str(a.max_particles)])


def auto_fit_grid(scene: str, a, work: Path, log) -> int | None:
    """The grid `init --grid auto` (with this run's caps) chooses for the scene's object: a 3-frame probe capture
    at the size's suggested grid (the object does not depend on the frames), init, its recorded grid choice;
    the probe's files removed. With `synth --fit-grid` that grid the truth is simulated on a cell 0.7x the
    fit's at `--grid auto`, as docs/synth.md means it (finer than the fit's): at the size's suggested grid
    (24 small) a scene whose thinnest part makes auto choose 44-59 cells got a truth coarser than its fit
    (22nd session, docs/benchmarks/fit.md)."""
    probe = work / f".{scene}.gridprobe"
    st = work / f".{scene}.gridprobe.usda"
    try:
        rc, _ = run(["synth", scene, str(probe), "--size", a.size, "--device", a.device, "--force", "--frames", "3"],
                    log)
        if rc:
            return None
        caps = init_caps(a)
        sug = json.loads((probe / "gt" / "gt.json").read_text())["suggested_init"]
        rc, _ = run(["init", str(st), "--capture", str(probe), "--grid", "auto", "--force", *init_args(sug), *caps], log)
        if rc:
            return None
        info = json.loads(subprocess.run([sys.executable, "-m", "physinteract_usd", "info", str(st), "--json"],
                                         capture_output=True, text=True).stdout)
        n = int((info["simulation"].get("grid_choice") or {})["grid"])
        log.write(f"synth --fit-grid auto: init --grid auto chooses {n} cells for {scene}\n")
        return n
    finally:
        shutil.rmtree(probe, ignore_errors=True)
        for suffix in (".usda", ".init.usdc", ".fit.usdc"):
            (work / f".{scene}.gridprobe{suffix}").unlink(missing_ok=True)
        shutil.rmtree(work / f".{scene}.gridprobe.versions", ignore_errors=True)


def one(scene: str, a, work: Path) -> dict:
    cap = work / scene
    st = work / f"{scene}.usda"
    row = {"scene": scene, "size": a.size, "device": device_name(a.device), "schedule": a.schedule,
           "grid_arg": grid_key(a), "tag": a.tag}
    with open(work / f"{scene}.log", "a") as log:
        # the truth's grid: as asked; with --grid auto and none asked, auto's (a truth finer than the fit)
        want = a.synth_fit_grid if a.synth_fit_grid is not None else ("auto" if a.grid == "auto" else None)
        gj = cap / "gt" / "gt.json"
        marker = cap / ".synth_fit_grid_auto"        # a capture made for auto's grid (its number inside)
        have = json.loads(gj.read_text())["suggested_init"]["grid"] if gj.exists() else None
        n = None
        if want == "auto":
            if have is not None and marker.exists() and marker.read_text().strip() == str(have):
                n = have
            else:
                n = auto_fit_grid(scene, a, work, log)
                if n is None:
                    return {**row, "error": "synth --fit-grid auto: the probe capture failed (see log)"}
        elif want is not None:
            n = int(want)
        if have is None or (n is not None and n != have):
            if have is not None:
                log.write(f"the capture was made for grid {have}, this run's truth is for {n}: made again\n")
            cmd = ["synth", scene, str(cap), "--size", a.size, "--device", a.device, "--force"]
            if a.frames:
                cmd += ["--frames", str(a.frames)]
            if n is not None:
                cmd += ["--fit-grid", str(n)]
            rc, t = run(cmd, log)
            if rc:
                return {**row, "error": "synth failed"}
        if want == "auto":
            marker.write_text(str(n))
        gt = json.loads((cap / "gt" / "gt.json").read_text())
        sug = gt["suggested_init"]
        row["synth_fit_grid"] = sug["grid"]      # the grid the truth was made for (its cell 0.7x that grid's)
        grid = a.grid or sug["grid"]
        caps = init_caps(a)
        for suffix in (".usda", ".init.usdc", ".fit.usdc"):
            (work / f"{scene}{suffix}").unlink(missing_ok=True)
        shutil.rmtree(work / f"{scene}.versions", ignore_errors=True)   # a fresh stage: its old versions go too
        gt_dir = cap / "gt"
        if a.extracted:
            hidden = work / f"{scene}.gt"
            if hidden.exists():
                shutil.rmtree(hidden)
            shutil.move(str(gt_dir), str(hidden))
            gt_dir = hidden
        rc, _ = run(["init", str(st), "--capture", str(cap), "--grid", str(grid), *init_args(sug), *caps], log)
        if rc:
            return {**row, "error": "init failed"}
        info = json.loads(subprocess.run([sys.executable, "-m", "physinteract_usd", "info", str(st), "--json"],
                                         capture_output=True, text=True).stdout)
        gc = info["simulation"].get("grid_choice") or {}
        row.update(particles=info["particles"]["count"], substeps=info["simulation"]["substeps_per_frame"],
                   frames=info["frames"]["count"], grid=max(info["simulation"]["grid"]), grid_arg=grid_key(a),
                   thinnest_mm=1000 * gc["thinnestPart"] if gc else None, cells_across=gc.get("cellsAcross"),
                   grid_limit=gc.get("limit") or None)
        fit_cmd = ["fit", str(st), "--iterations", str(a.iterations), "--device", a.device, "--schedule", a.schedule]
        if not a.extracted:
            fit_cmd += ["--contact-from", str(gt_dir)]
        if a.gauss_newton:
            fit_cmd += ["--gauss-newton", str(a.gauss_newton)]
        cpu = {}
        rc, t_fit = run(fit_cmd, log, cpu)
        row["fit_s"] = round(t_fit, 1)
        row["fit_cpu_s"] = cpu.get("cpu_s")
        row["schedule"] = a.schedule
        if not rc:
            row["model"] = chosen_model(st)
        row["iterations"] = a.iterations
        if rc:
            if a.extracted:
                shutil.move(str(gt_dir), str(cap / "gt"))
            return {**row, "error": "fit failed (see log)"}
        p = subprocess.run([sys.executable, "-m", "physinteract_usd", "evaluate", str(st), "--gt", str(gt_dir),
                            "--device", a.device, "--json"], capture_output=True, text=True)
        if a.extracted:
            shutil.move(str(gt_dir), str(cap / "gt"))
        if p.returncode:
            log.write(p.stderr)
            return {**row, "error": "evaluate failed"}
        ev = json.loads(p.stdout)
        row.update({k: ev[k] for k in ("ma", "ma_best_uniform", "psnr", "psnr_masked", "ssim", "iou",
                                        "position_error_m", "by_truth_level", "calibration")})
        row["truth_resolution"] = ev.get("truth_resolution")
        row["hidden_effect"] = gt.get("hidden_effect")
        row.update(uniform_mas(row.get("model") or {}, cap / "gt"))
    return row


def uniform_mas(model: dict, gt_dir: Path) -> dict:
    """The MA the select schedule's uniform candidates would have scored (what choosing "uniform"
    would have given, and whether the uniform stage itself is biased): at the uniform stage's E and
    at the polished uniform model's E."""
    import numpy as np

    from physinteract_usd import metrics as M
    from physinteract_usd.synth.gt import read_gt_array

    out = {}
    try:
        e_gt = read_gt_array(gt_dir, "youngs_modulus.npy")
        if "uniform_e" in model:
            out["ma_uniform_stage"] = M.material_accuracy(np.full(len(e_gt), model["uniform_e"]), e_gt)
        e_u = (model.get("losses") or {}).get("uniform", {}).get("median_e")
        if e_u is not None:
            out["ma_uniform_model"] = M.material_accuracy(np.full(len(e_gt), e_u), e_gt)
    except Exception:  # noqa: BLE001 - diagnostics only
        pass
    return out


def chosen_model(stage: Path) -> dict:
    """The material model the fit recorded in its report (fit/select.py's model_summary)."""
    from physinteract_usd.app.adapters import read_scene
    from physinteract_usd.fit.select import model_summary

    try:
        return model_summary(read_scene(stage).reports[-1].get("material_model"))
    except Exception as exc:  # noqa: BLE001 - a benchmark row is written whatever the report holds
        return {"error": f"{type(exc).__name__}: {exc}"}


def _synth_grid(v: str):
    if v == "auto":
        return v
    try:
        return int(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number of cells or auto, got {v!r}") from None


def grid_key(a) -> str:
    """Which grid a row was made with: "suggested" (the capture's), a number, or "auto"."""
    return "suggested" if a.grid is None else str(a.grid)


def _grid_cell(r: dict) -> str:
    across = r.get("cells_across")
    return f"{r.get('grid', '-')}" + (f" ({across:.1f})" if across is not None else "")


def table(rows: list[dict], a) -> str:
    head = ("| scene | grid (cells across thinnest) | particles | frames | substeps/frame | fit s | its | MA | "
            "best uniform MA | PSNR | PSNR masked | SSIM | IoU | pos. err. mm |\n" + "|---" * 14 + "|\n")
    out = []
    for r in rows:
        if "error" in r:
            out.append(f"| {r['scene']} | {_grid_cell(r)} | {r.get('particles', '-')} | {r.get('frames', '-')} | "
                       f"{r.get('substeps', '-')} | | | {r['error']} | | | | | | |")
            continue
        out.append(f"| {r['scene']} | {_grid_cell(r)} | {r['particles']} | {r['frames']} | {r['substeps']} | {r['fit_s']:.0f} | "
                   f"{r['iterations']} | {r['ma']:.3f} | {r['ma_best_uniform']:.3f} | {r['psnr']:.2f} | "
                   f"{r['psnr_masked']:.2f} | {r['ssim']:.3f} | {r['iou']:.3f} | {1000 * r['position_error_m']:.2f} |")
    ok = [r for r in rows if "error" not in r]
    if ok:
        mean = lambda k: sum(r[k] for r in ok) / len(ok)  # noqa: E731
        out.append(f"| **mean ({len(ok)})** | | | | | {mean('fit_s'):.0f} | | **{mean('ma'):.3f}** | "
                   f"{mean('ma_best_uniform'):.3f} | {mean('psnr'):.2f} | {mean('psnr_masked'):.2f} | "
                   f"{mean('ssim'):.3f} | {mean('iou'):.3f} | {1000 * mean('position_error_m'):.2f} |")
    out.append(f"| *paper (11 scenes, A40)* | | | | | *{PAPER['runtime']}* | | *{PAPER['ma']}* | | "
               f"*{PAPER['psnr']}* | | *{PAPER['ssim']}* | | |")
    dev = rows[0]["device"] if rows else a.device
    src = "extracted by `fit` (gt/ moved away)" if a.extracted else "`--contact-from gt` (contacts, supports, T0)"
    return (f"Size `{a.size}`, device: {dev}; contacts: {src}; schedule `{a.schedule}`; grid `{grid_key(a)}`.\n\n" + head
            + "\n".join(out) + "\n")


def main(argv=None):
    from physinteract_usd.cli.init import grid_arg      # N cells or "auto", as init takes it

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="small")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scenes", default=None, help="comma-separated (default: every scene)")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--synth-fit-grid", type=_synth_grid, default=None,
                    help="synth --fit-grid for captures it makes: the truth simulated on a cell 0.7x that grid's; "
                         "auto: the grid init --grid auto chooses for the scene's object (a 3-frame probe capture), "
                         "so the truth is finer than that fit (the default with --grid auto; else the size's grid). "
                         "A capture in --out made for another grid is made again")
    ap.add_argument("--grid", type=grid_arg, default=None,
                    help="override the suggested init grid: N cells, or auto (rows are kept per grid too)")
    ap.add_argument("--max-grid", type=int, default=None, help="init's cap with --grid auto (default init's, 128)")
    ap.add_argument("--max-particles", type=int, default=None,
                    help="init's particle cap with --grid auto (default init's, 60000)")
    ap.add_argument("--extracted", action="store_true", help="fit from extracted contacts, not gt")
    ap.add_argument("--schedule", default="bumps", choices=("bumps", "select", "ladder"),
                    help="the fit's schedule (rows are kept per scene and schedule: two schedules can share --out "
                         "and its captures; the table shows this schedule's)")
    ap.add_argument("--tag", default="", help="a label kept in each row: rows are kept per scene, schedule, grid and "
                    "tag (e.g. the same schedule before / after a change, run with PYTHONPATH at the old code)")
    ap.add_argument("--gauss-newton", type=int, default=0, metavar="N",
                    help="fit --gauss-newton N (bumps: Gauss-Newton steps on the finest level; use a --tag)")
    ap.add_argument("--out", default="out/suite")
    ap.add_argument("--write", default=None, help="markdown file to (re)write with the table")
    a = ap.parse_args(argv)

    from physinteract_usd import api

    names = a.scenes.split(",") if a.scenes else [s[0] for s in api.synth_scenes()]
    work = Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    jl = work / "results.jsonl"
    rows = [json.loads(line) for line in jl.read_text().splitlines()] if jl.exists() else []
    mine = lambda r: (r.get("schedule", "bumps"), r.get("grid_arg", "suggested"), r.get("tag", "")) == (  # noqa: E731
        a.schedule, grid_key(a), a.tag)
    done = {r["scene"] for r in rows if mine(r)}
    for n in names:
        if n in done:
            continue
        t = time.perf_counter()
        r = one(n, a, work)
        r["total_s"] = round(time.perf_counter() - t, 1)
        rows.append(r)
        with open(jl, "a") as f:
            f.write(json.dumps(r) + "\n")
        print(json.dumps(r), flush=True)
        md = table([r for r in rows if mine(r)], a)
        if a.write:
            Path(a.write).write_text(md)
    print(table([r for r in rows if mine(r)], a))


if __name__ == "__main__":
    main()
