"""One GPU, one run, one table (issue #26): the baselines in ../shared/device timed beside ours.

    python3 benchmarks/gpu_bench.py --out OUT [--deadline 560] [--paper-scene hemp_rope]

Runs, in this order and each as its own process with a time limit (so one that hangs cannot take
the rest with it), all within `--deadline` seconds of wall time:

1. the baselines: mpm_probe.py (naive MLS-MPM, wp.Tape, CUDA graphs) at 2k / 32^3 and 15k / 100^3,
   gsplat_probe.py (gsplat forward+backward) at 15k Gaussians, 512^2;
2. our simulator (bench_sim.py, medians of 5) at the same sizes, forward and forward+backward per
   substep, and (`--kernels both`, `--box both`, in its log) the fused transfer kernels against the
   separate ones, the grid kernels over the object's box against the whole grid;
3. our renderer (bench_render.py, medians) forward+backward per frame at 15k, 512^2 and 2k, 256^2,
   one image per call and 13 per call (`render_batch`, as a fit renders its frames on CUDA);
4. a small fit: the bundled sample (samples/foam_bar: 14 frames, grid 24, the demo's settings),
   true contacts, default iterations, `fit --device cuda`, then `evaluate` (MA, masked PSNR);
4b. the issue's small capture (~2k particles, 36-40 frames, 60 iterations): `synth foam_bar --frames 36 --noise
   0.015 --blur 3` (the small size: grid 24, 1,769 particles), true contacts, `fit --iterations 60`, `evaluate`
   (`--skip small36` leaves it out);
5. four small fits batched in one process against one fit (benchmarks/batch_fits.py --copies 4: the
   bundled sample at grid 24, 60 iterations each, the start search once beforehand; with
   `--batch-before` also B=4 with its renders and loss per copy and frame, the before of the batched
   renders);
6. a paper-size fit: `synth SCENE --size paper --device cuda`, `init --grid 100`, true contacts,
   `fit --device cuda` with whatever time is left (SIGTERM at the deadline: the fit keeps its best
   iterate and writes it), then `evaluate`.

Prints the table (markdown) at the end and writes it to OUT/gpu_bench.md, with every raw log in
OUT/. The first CUDA compilation of the Warp kernels lands in step 2 (cached for the rest).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
T0 = time.monotonic()
DEVICE = "cuda"


def left(deadline):
    return deadline - (time.monotonic() - T0)


def run(name, argv, out: Path, limit, deadline, reserve=0.0, env=None):
    """Run argv with a time limit (SIGTERM, then SIGKILL 20 s later); log to OUT/name.log."""
    limit = min(limit, left(deadline) - reserve)
    log = out / f"{name}.log"
    if limit < 5:
        log.write_text(f"skipped: {limit:.0f} s left\n")
        print(f"[{time.monotonic() - T0:5.0f}s] {name}: skipped (no time left)", flush=True)
        return None, 0.0
    t = time.monotonic()
    with open(log, "w") as fh:
        fh.write("$ " + " ".join(map(str, argv)) + "\n")
        fh.flush()
        p = subprocess.Popen(list(map(str, argv)), stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT,
                             env={**os.environ, **(env or {})})
        try:
            p.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGTERM)
            fh.write(f"\n[gpu_bench] SIGTERM after {limit:.0f} s\n")
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    dt = time.monotonic() - t
    print(f"[{time.monotonic() - T0:5.0f}s] {name}: rc {p.returncode} in {dt:.1f} s", flush=True)
    return p.returncode, dt


def grab(path: Path, pattern, cast=float, group=1):
    try:
        m = re.search(pattern, path.read_text())
    except OSError:
        return None
    return cast(m.group(group)) if m else None


def last_json(path: Path):
    """The last JSON object printed in a log (pretty or one-line)."""
    try:
        txt = path.read_text()
    except OSError:
        return None
    for start in [m.start() for m in re.finditer(r"^\{", txt, re.M)][::-1]:
        depth = 0
        for i, ch in enumerate(txt[start:]):
            depth += ch == "{"
            depth -= ch == "}"
            if depth == 0:
                try:
                    return json.loads(txt[start:start + i + 1])
                except json.JSONDecodeError:
                    break
    return None


def fit_case(tag, out, deadline, *, capture, stage, init_args, fit_limit, iterations=None, reserve=25.0,
             synth=None):
    """synth (optional) -> init -> fit (true contacts) -> evaluate; returns a row dict."""
    py = sys.executable
    row = {"case": tag}
    work = Path(stage).parent
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    if synth:
        rc, dt = run(f"{tag}_synth", [py, "-m", "physinteract_usd", *synth], out, 200, deadline, reserve=60)
        row["synth_s"] = dt
        if rc != 0:
            row["note"] = "synth failed"
            return row
    rc, dt = run(f"{tag}_init", [py, "-m", "physinteract_usd", "init", stage, "--capture", capture, *init_args],
                 out, 120, deadline, reserve=40)
    if rc != 0:
        row["note"] = "init failed"
        return row
    rc, _ = run(f"{tag}_info", [py, "-m", "physinteract_usd", "info", stage, "--json"], out, 60, deadline)
    info = last_json(out / f"{tag}_info.log") or {}
    row["particles"] = (info.get("particles") or {}).get("count")
    sim = info.get("simulation") or {}
    row["grid"] = "x".join(map(str, sim.get("grid", []))) or None
    row["substeps_max"] = sim.get("substeps_per_frame")
    row["frames"] = (info.get("frames") or {}).get("count")
    argv = [py, "-m", "physinteract_usd", "fit", stage, "--contact-from", f"{capture}/gt", "--device", DEVICE,
            "--json", "--yes"]
    if iterations:
        argv += ["--iterations", str(iterations)]
    rc, dt = run(f"{tag}_fit", argv, out, fit_limit, deadline, reserve=reserve)
    row["fit_s"] = dt
    fj = last_json(out / f"{tag}_fit.log") or {}
    row["iterations"] = fj.get("iterations")
    row["status"] = fj.get("status") or (f"rc {rc}" if rc is not None else "not run")
    row["fit_runtime_s"] = fj.get("runtime_s")
    row["phases_s"] = fj.get("phases_s")      # where the fit's time went (fit --json, #26)
    row["iteration_s"] = fj.get("iteration_s")  # each gradient iteration's seconds
    rc, _ = run(f"{tag}_eval", [py, "-m", "physinteract_usd", "evaluate", stage, "--gt", f"{capture}/gt",
                                "--device", DEVICE, "--json"], out, 60, deadline)
    ev = last_json(out / f"{tag}_eval.log") or {}
    row.update({k: ev.get(k) for k in ("ma", "psnr", "psnr_masked", "position_error_m")})
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/gpu_bench")
    ap.add_argument("--deadline", type=float, default=560.0, help="seconds of wall time for everything")
    ap.add_argument("--probes", default=None, help="folder of mpm_probe.py / gsplat_probe.py")
    ap.add_argument("--paper-scene", default="hemp_rope")
    ap.add_argument("--paper-iterations", type=int, default=20)
    ap.add_argument("--device", default="cuda", help="cuda (cpu: a smoke test of this script)")
    ap.add_argument("--small-iterations", type=int, default=None)
    ap.add_argument("--skip", default="", help="comma list of steps to skip: probes,sim,render,small,small36,batch,paper")
    ap.add_argument("--batch-before", action="store_true",
                    help="the batch step also runs B=4 with per-copy renders (batch_fits.py --per-copy-renders)")
    ap.add_argument("--batch-args", default="", help="more arguments for batch_fits.py (e.g. '--grid 12 "
                                                     "--iterations 2' for a CPU smoke test)")
    ap.add_argument("--gsplat-limit", type=float, default=150.0,
                    help="seconds for gsplat's probe (a fresh machine builds its CUDA extension first: >90 s once)")
    ap.add_argument("--batch-limit", type=float, default=200.0, help="seconds for the batch step at most")
    a = ap.parse_args(argv)
    out = Path(a.out)
    global DEVICE
    DEVICE = a.device
    out.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, a.skip.split(",")))
    py = sys.executable
    dl = a.deadline
    probes = Path(a.probes) if a.probes else next(
        (p for p in (ROOT / ".dev/probes", ROOT.parent / "shared/device", ROOT / "../shared/device")
         if (p / "mpm_probe.py").exists()), None)
    try:
        dev_name = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                                  capture_output=True, text=True).stdout.strip()
    except OSError:
        dev_name = "no nvidia-smi (CPU)"
    import torch
    import warp
    head = (f"device: {dev_name}; torch {torch.__version__}, warp {warp.__version__}, python "
            f"{sys.version.split()[0]}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(head, flush=True)
    R = {}
    if "probes" not in skip and probes is not None:
        for P, n in ((2000, 32), (15000, 100)):
            run(f"probe_mpm_{P}", [py, probes / "mpm_probe.py", "cuda", P, n, 100], out, 60, dl)
            lg = out / f"probe_mpm_{P}.log"
            R[f"probe_{P}"] = (grab(lg, r"graph: forward ([\d.]+) us"), grab(lg, r"forward\+backward ([\d.]+) us/substep"))
        run("probe_gsplat", [py, probes / "gsplat_probe.py", 15000, 512], out, a.gsplat_limit, dl)
        R["gsplat"] = grab(out / "probe_gsplat.log", r"median ([\d.]+) ms")
    if "sim" not in skip:
        run("bench_sim", [py, "benchmarks/bench_sim.py", "--device", "cuda", "--sizes", "2000:32", "15000:100",
                          "--frames", "2", "--substeps", "50", "--reps", "5", "--stat", "median", "--probe", "",
                          "--kernels", "both", "--box", "both"],
            out, 240, dl)
        for P in ("2,0", "15,0"):
            m = re.search(rf"\| ({P}\d\d) \| (\d+)\^3 \| ([\d,]+) \| ([\d,]+) \|", (out / "bench_sim.log").read_text()
                          if (out / "bench_sim.log").exists() else "")
            if m:
                R[f"sim_{P[:2].strip(',')}k"] = (int(m.group(1).replace(",", "")), int(m.group(2)),
                                                   float(m.group(3).replace(",", "")), float(m.group(4).replace(",", "")))
    if "render" not in skip:
        run("bench_render", [py, "benchmarks/bench_render.py", "--device", "cuda", "--sizes", "15000x512,2000x256",
                             "--reps", "10", "--json", "--batch", "13"], out, 150, dl)
        txt = (out / "bench_render.log").read_text() if (out / "bench_render.log").exists() else ""
        for line in txt.splitlines():
            if line.startswith("{"):
                try:
                    r = json.loads(line)
                    R[f"render_{r['n']}_{r['size']}" + (f"_batch{r['batch']}" if "batch" in r else "")] = (
                        r["fwd_ms"], r["fwd_bwd_ms"])
                except (json.JSONDecodeError, KeyError):
                    pass
    rows = []
    if "small" not in skip:
        rows.append(fit_case("small", out, dl, capture="samples/foam_bar", stage="/tmp/gpu_bench/small/scene.usda",
                             init_args=["--grid", "24", "--padding", "0.3", "--youngs-range", "1e3,6e4",
                                        "--max-poisson", "0.4", "--density", "150", "--no-preload"],
                             fit_limit=150, iterations=a.small_iterations, reserve=max(0.0, min(250.0, left(dl) - 160))))
    if "small36" not in skip:
        cap = "/tmp/gpu_bench/small36_foam_bar"
        rows.append(fit_case("small36", out, dl, capture=cap, stage="/tmp/gpu_bench/small36/scene.usda",
                             synth=["synth", "foam_bar", cap, "--frames", "36", "--noise", "0.015", "--blur", "3",
                                    "--device", DEVICE, "--force"],
                             init_args=["--grid", "24", "--padding", "0.3", "--youngs-range", "1e3,6e4",
                                        "--max-poisson", "0.4", "--density", "150", "--no-preload"],
                             fit_limit=150, iterations=60, reserve=max(0.0, min(230.0, left(dl) - 120))))
    batch_rows = []
    if "batch" not in skip:
        bf = out / "bf"
        shutil.rmtree(bf, ignore_errors=True)
        argv = [py, "benchmarks/batch_fits.py", "--device", DEVICE, "--copies", "4", "--work", "/tmp/gpu_bench/bf",
                "--out", bf] + (["--per-copy-renders"] if a.batch_before else []) + a.batch_args.split()
        # keep ~170 s for the paper-size fit after it (unless it is skipped)
        run("batch_fits", argv, out, a.batch_limit, dl, reserve=0.0 if "paper" in skip else 170.0)
        try:
            batch_rows = [json.loads(x) for x in (bf / "batch_fits.jsonl").read_text().splitlines() if x.strip()]
        except OSError:
            batch_rows = []
        batch_rows = [r for r in batch_rows if "case" in r and not r.get("profiled")]
    if "paper" not in skip:
        cap = f"/tmp/gpu_bench/paper_{a.paper_scene}"
        rows.append(fit_case("paper", out, dl, capture=cap, stage="/tmp/gpu_bench/paper/scene.usda",
                             synth=["synth", a.paper_scene, cap, "--size", "paper", "--device", DEVICE, "--force"],
                             init_args=["--grid", "100", "--padding", "0.3", "--youngs-range", "1e3,6e4",
                                        "--max-poisson", "0.4", "--density", "150", "--no-preload"],
                             fit_limit=600, iterations=a.paper_iterations, reserve=30))

    def f(v, fmt="{:.1f}"):
        return "-" if v is None else fmt.format(v)

    lines = [head, "", "| part | size | ours | baseline (same run) |", "|---|---|---|---|"]
    for k in ("2", "15"):
        s = R.get(f"sim_{k}k")
        p = R.get(f"probe_{k}000", (None, None))
        if s:
            lines.append(f"| simulator forward, us/substep (median of 5) | {s[0]:,} particles, {s[1]}^3 | {s[2]:.0f} | "
                         f"mpm_probe graph {f(p[0], '{:.0f}')} |")
            lines.append(f"| simulator fwd+bwd, us/substep | {s[0]:,} particles, {s[1]}^3 | {s[3]:.0f} "
                         f"(bwd/fwd {(s[3] - s[2]) / s[2]:.1f}) | mpm_probe graph {f(p[1], '{:.0f}')} |")
    for key, size in (("render_15000_512", "15k Gaussians, 512^2"), ("render_2000_256", "2k Gaussians, 256^2"),
                      ("render_15000_512_batch13", "15k Gaussians, 512^2, 13 images in one pass, per image"),
                      ("render_2000_256_batch13", "2k Gaussians, 256^2, 13 images in one pass, per image")):
        r = R.get(key)
        if r:
            g = f(R.get("gsplat"), "{:.2f}") if key == "render_15000_512" else "-"
            lines.append(f"| renderer forward / fwd+bwd, ms/frame (median) | {size} | {r[0]:.2f} / {r[1]:.2f} | "
                         f"gsplat fwd+bwd {g} |")
    for r in rows:
        size = (f"{r.get('particles') or '?'} particles, grid {r.get('grid') or '?'}, {r.get('frames') or '?'} frames, "
                f"{r.get('substeps_max') or '?'} substeps/frame at E max")
        ma = r.get("ma")
        lines.append(f"| fit ({r['case']}), wall s incl. start search, writing | {size} | {f(r.get('fit_s'), '{:.0f}')} s, "
                     f"{r.get('iterations') or '?'} iterations ({r.get('status')}), MA {f(ma, '{:.3f}')}, "
                     f"masked PSNR {f(r.get('psnr_masked'), '{:.2f}')} dB"
                     + (f"; synth {r['synth_s']:.0f} s" if r.get("synth_s") else "")
                     + (f"; {r['note']}" if r.get("note") else "") + " | - |")
    one = next((r for r in batch_rows if r["case"] == "1"), None)
    for r in batch_rows:
        if r["case"] == "1" or one is None:
            continue
        per = ", ".join(f"MA {c['ma']:.3f}" if c.get("ma") is not None else "MA ?" for c in r["copy"])
        lines.append(f"| {r['copies']} small fits batched in one process ({r['case']}), {r['lockstep_iterations']} "
                     f"lockstep iterations | the bundled sample, {r['particles']} particles, {r['frames']} frames | "
                     f"{r['wall_s']:.1f} s = {r['wall_s'] / one['wall_s']:.2f}x one fit's {one['wall_s']:.1f} s "
                     f"({one['lockstep_iterations']} iterations, MA {f(one['copy'][0].get('ma'), '{:.3f}')}); "
                     f"{r['wall_per_iteration_s']:.3f} s / iteration (one fit {one['wall_per_iteration_s']:.3f}); {per} | - |")
    lines.append("")
    for r in rows:
        ph = r.get("phases_s") or {}
        if ph:
            lines.append(f"fit ({r['case']}) phases, s (fit --json): fit clock {f(r.get('fit_runtime_s'))} = "
                         + ", ".join(f"{k} {v:.1f}" for k, v in ph.items()
                                     if k in ("start_search", "starts", "iterations", "final_pass", "confidence"))
                         + "; around it " + ", ".join(f"{k} {v:.1f}" for k, v in ph.items()
                                                      if k in ("prepare", "problem", "notes", "write"))
                         + f"; the CLI's wall {f(r.get('fit_s'))} s")
        if r.get("iteration_s"):
            lines.append(f"fit ({r['case']}) gradient iterations, s each: "
                         + " ".join(f"{v:.2f}" for v in r["iteration_s"]))
    lines.append("")
    lines.append(f"total wall time {time.monotonic() - T0:.0f} s; raw logs in {out}/")
    table = "\n".join(lines)
    (out / "gpu_bench.md").write_text(table + "\n")
    (out / "gpu_bench.json").write_text(json.dumps({"head": head, "R": R, "fits": rows, "batch": batch_rows}, indent=1,
                                                   default=str))
    print(table)


if __name__ == "__main__":
    main()
