"""How long a stopped fit takes to write its best iterate (docs/benchmarks/cpu.md, issue #26).

    python benchmarks/stop_latency.py STAGE [--signal TERM|INT] [--after N] [--delay S] [--grid G] [--out DIR]

Copies the stage's folder (root layer, its layers, extraction, versions) to --out, or, with
--grid, builds a fresh stage of the bundled sample at that grid there (a bigger case: more
particles and substeps per frame); starts `fit` on it with a checkpoint every iteration, waits
until N iterations are checkpointed, sends the signal and measures the seconds until the new
version's snapshot is written and until the process exits. Prints one line per measure.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "foam_bar"


def prepare(args) -> Path:
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    if args.grid:
        stage = out / "scene.usda"
        subprocess.run([sys.executable, "-m", "physinteract_usd", "init", str(stage), "--capture", str(SAMPLE),
                        "--grid", str(args.grid), "--padding", "0.3", "--youngs-range", "1e3,6e4",
                        "--max-poisson", "0.4", "--density", "150", "--yes"], check=True, cwd=ROOT,
                       stdout=subprocess.DEVNULL)
        return stage
    src = Path(args.stage)
    stem = src.stem
    for p in src.parent.iterdir():
        if p.name.startswith(stem + ".") and p.name != src.name + ".lock":
            (shutil.copytree if p.is_dir() else shutil.copy2)(p, out / p.name)
    versions = out / f"{stem}.versions"
    if versions.exists():
        (versions / "checkpoint.npz").unlink(missing_ok=True)
    return out / src.name


def iterations_done(ck: Path) -> int:
    import numpy as np

    try:
        with np.load(ck, allow_pickle=True) as d:
            return int(json.loads(str(d["meta"]))["iteration"])
    except Exception:  # noqa: BLE001 - being written
        return 0


def cpu_seconds(pid: int) -> float:
    """user + system CPU seconds of a running process (Linux /proc), 0.0 once it is gone."""
    import os

    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("stage", nargs="?", default=str(ROOT / "out" / "demo" / "scene.usda"))
    ap.add_argument("--signal", default="TERM", choices=["TERM", "INT"])
    ap.add_argument("--after", type=int, default=1, help="iterations checkpointed before the signal")
    ap.add_argument("--delay", type=float, default=0.0, help="seconds more after that checkpoint (to land in a "
                    "backward pass: the stop acts between frames)")
    ap.add_argument("--grid", type=int, default=0, help="build a fresh stage of the sample at this grid instead")
    ap.add_argument("--out", default=str(ROOT / "out" / "stop_latency"))
    args = ap.parse_args()
    stage = prepare(args)
    versions = stage.parent / f"{stage.stem}.versions"
    before = set(versions.glob("v*.usdc")) if versions.exists() else set()
    log = open(stage.parent / "fit.log", "w")
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "physinteract_usd", "fit", str(stage), "--checkpoint-every", "1",
                             "--json"], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    ck = versions / "checkpoint.npz"
    while iterations_done(ck) < args.after:
        if proc.poll() is not None:
            raise SystemExit(f"the fit ended before {args.after} iterations ({proc.returncode}); see {log.name}")
        time.sleep(0.05)
    time.sleep(args.delay)
    cpu0 = cpu_seconds(proc.pid)
    t_sig = time.perf_counter()
    proc.send_signal(getattr(signal, "SIG" + args.signal))
    written, cpu1 = None, cpu0
    while proc.poll() is None:
        cpu1 = max(cpu1, cpu_seconds(proc.pid) or cpu1)
        if written is None and versions.exists() and set(versions.glob("v*.usdc")) - before:
            written = time.perf_counter() - t_sig
        time.sleep(0.02)
    t_exit = time.perf_counter() - t_sig
    if written is None and set(versions.glob("v*.usdc")) - before:
        written = t_exit
    log.close()
    text = (stage.parent / "fit.log").read_text()
    summary = {}
    if "{" in text:
        try:
            summary = json.loads(text[text.rindex("\n{") + 1:] if "\n{" in text else text[text.index("{"):])
        except ValueError:
            summary = {}
    print(f"stage {stage} ({'grid ' + str(args.grid) if args.grid else 'copy'}): SIG{args.signal} after "
          f"{args.after} iteration(s) + {args.delay:g} s, {t_sig - t0:.1f} s into the fit")
    print(f"  snapshot written {written if written is None else round(written, 2)} s after the signal; "
          f"process exited {t_exit:.2f} s after it (code {proc.returncode}); the fit's CPU time from the "
          f"signal to its last reading: {cpu1 - cpu0:.2f} s (wall inflated by other load)")
    if summary:
        print(f"  status {summary.get('status')}, stopped_by {summary.get('stopped_by')}, iterations "
              f"{summary.get('iterations')}, confidence_estimated {summary.get('confidence_estimated')}")


if __name__ == "__main__":
    main()
