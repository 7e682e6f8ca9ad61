"""The README's demo (scripts/demo.sh) on the CPU, step by step, with wall and process CPU time per
phase (docs/benchmarks/cpu.md).

    python benchmarks/cpu_demo.py [--out out/cpu_demo] [--cold] [-- fit arguments]

Each verb runs in its own process, as demo.sh runs them (imports and Warp's module loads count);
the fit runs under `profiled` below, which wraps the package's functions with timers (nothing in
the package changes) and prints its breakdown: extraction, the start search, the iterations (the
simulator's forward / backward, the renderer's forward / backward, the loss), the last pass, the
confidence estimate, the interaction check, the write. `--cold`: every process gets an empty
WARP_CACHE_PATH, so Warp compiles every kernel, as on a fresh machine or in CI.

    python benchmarks/cpu_demo.py profiled STAGE [fit arguments]    (one profiled fit)
"""

from __future__ import annotations

import functools
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "foam_bar"

_acc = defaultdict(lambda: [0.0, 0.0, 0])    # name -> [wall, cpu, calls]
_stack: list[str] = []


def _timed(name, fn):
    """A phase (name without a leading dot) is timed as itself and, when no phase is open, opens
    one; a piece (".name") is timed as "phase > .name" under the outermost open phase."""
    @functools.wraps(fn)
    def wrapper(*a, **kw):
        piece = name.startswith(".")
        key = f"{_stack[0] if _stack else '-'} > {name}" if piece else name
        opened = not piece and not _stack
        if opened:
            _stack.append(name)
        w0, c0 = time.perf_counter(), time.process_time()
        try:
            return fn(*a, **kw)
        finally:
            acc = _acc[key]
            acc[0] += time.perf_counter() - w0
            acc[1] += time.process_time() - c0
            acc[2] += 1
            if opened:
                _stack.pop()
    return wrapper


def _patch(obj, attr, name):
    setattr(obj, attr, _timed(name, getattr(obj, attr)))


def install():
    """Wrap the phases (names without a dot) and the pieces counted inside the current phase
    (names with a leading dot: `phase > .piece`)."""
    import torch

    from physinteract_usd.app import extract as app_extract
    from physinteract_usd.app import fit as app_fit
    from physinteract_usd.fit import optimize, problem
    from physinteract_usd.render import function as rf
    from physinteract_usd.sim import rollout

    _patch(app_extract, "extract", "extraction")
    _patch(app_fit, "make_problem", "problem build")
    _patch(app_fit, "select_supports", "start search (supports)")
    _patch(optimize, "golden_uniform_search", "start search")
    _patch(optimize, "confidence", "confidence")
    _patch(optimize, "frame_metrics", "frame metrics")
    _patch(optimize, "assemble_result", "assemble result")
    _patch(app_fit, "interaction_notes", "interaction check")
    _patch(app_fit, "write_fit_layer", "write")
    _patch(app_fit, "prepare_fit", "read stage")
    # pieces
    _patch(rollout.Rollout, "run_forward", ".sim forward")
    _patch(rollout.Rollout, "run_backward", ".sim backward")
    _patch(rf.RasterizeGaussians, "forward", ".render forward (raster)")
    _patch(rf.RasterizeGaussians, "backward", ".render backward (raster)")
    _patch(problem, "render", ".render (all)")
    _patch(problem, "reconstruction_loss", ".loss terms")
    _patch(problem.FitProblem, "gaussians_at", ".gaussians_at")
    _patch(torch.Tensor, "backward", ".backward (all)")

    # the iterations: prob.loss with gradients on is an iteration's forward
    orig_loss = problem.FitProblem.loss

    def loss(self, *a, **kw):
        if not _stack and torch.is_grad_enabled():
            return _timed("iterations", orig_loss)(self, *a, **kw)
        if not _stack and kw.get("keep_renders"):
            return _timed("last pass", orig_loss)(self, *a, **kw)
        return orig_loss(self, *a, **kw)
    problem.FitProblem.loss = loss
    orig_bw = torch.Tensor.backward

    def backward(self, *a, **kw):
        if not _stack:
            return _timed("iterations", orig_bw)(self, *a, **kw)
        return orig_bw(self, *a, **kw)
    torch.Tensor.backward = backward


def report(total_wall, total_cpu, file=sys.stdout):
    rows = sorted(_acc.items(), key=lambda kv: -kv[1][0])
    print(f"{'phase > piece':58s} {'wall s':>8s} {'cpu s':>8s} {'calls':>6s}", file=file)
    for k, (w, c, n) in rows:
        print(f"{k:58s} {w:8.2f} {c:8.2f} {n:6d}", file=file)
    print(f"{'whole fit process (after imports)':58s} {total_wall:8.2f} {total_cpu:8.2f}", file=file)
    print("PROFILE_JSON " + json.dumps({k: v for k, v in _acc.items()}), file=file)


def experiment():
    """Levers tried before they are built (docs/benchmarks/cpu.md): CPU_DEMO_CFL scales nothing
    but sets the CFL number the substep is taken at (default 0.4); CPU_DEMO_SETTINGS, a JSON
    object of FitSettings defaults to change."""
    if os.environ.get("CPU_DEMO_CFL"):
        from physinteract_usd.sim import cfl as C
        orig, number = C.substeps_per_frame, float(os.environ["CPU_DEMO_CFL"])

        def spf(fps, dx, E_max, nu_max, density, cfl=0.4, max_speed=0.0):
            return orig(fps, dx, E_max, nu_max, density, cfl=number, max_speed=max_speed)
        C.substeps_per_frame = spf
        print(f"experiment: CFL {number}")
    if os.environ.get("CPU_DEMO_SETTINGS"):
        from physinteract_usd.fit import optimize
        over = json.loads(os.environ["CPU_DEMO_SETTINGS"])
        orig_init = optimize.FitSettings.__init__

        def init(self, *a, **kw):
            orig_init(self, *a, **kw)
            for k, v in over.items():
                setattr(self, k, v)
        optimize.FitSettings.__init__ = init
        print(f"experiment: FitSettings {over}")


def profiled(argv):
    w0, c0 = time.perf_counter(), time.process_time()
    from physinteract_usd.cli import _main
    experiment()
    install()
    code = 1
    try:
        code = _main(["fit", *argv])
    finally:
        report(time.perf_counter() - w0, time.process_time() - c0)
    return code


def run_steps(out: Path, cold: bool, fit_args: list[str], init_args: list[str] = ()):
    out.mkdir(parents=True, exist_ok=True)
    for p in ("scene.usda", "scene.init.usdc", "scene.fit.usdc"):
        (out / p).unlink(missing_ok=True)
    import shutil
    for p in ("scene.versions", "scene.extract"):
        shutil.rmtree(out / p, ignore_errors=True)
    env = dict(os.environ)
    cache = None
    if cold:
        cache = tempfile.mkdtemp(prefix="warp_cold_")
        env["WARP_CACHE_PATH"] = cache
    stage = str(out / "scene.usda")
    exe = [sys.executable, "-m", "physinteract_usd"]
    steps = [
        ("init", exe + ["init", stage, "--capture", str(SAMPLE), "--grid", "24", "--padding", "0.3",
                        "--youngs-range", "1e3,6e4", "--max-poisson", "0.4", "--density", "150", "--no-preload",
                        *init_args]),
        ("fit", [sys.executable, __file__, "profiled", stage, *fit_args]),
        ("evaluate", exe + ["evaluate", stage, "--gt", str(SAMPLE / "gt"), "--json"]),
        ("info", exe + ["info", stage]),
        ("export", exe + ["export", stage, str(out / "foam_bar_twin.usdc"), "--force"]),
    ]
    rows = []
    t_all = time.perf_counter()
    for name, cmd in steps:
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        w0 = time.perf_counter()
        p = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)
        w = time.perf_counter() - w0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        (out / f"{name}.log").write_text(p.stdout + "\n--- stderr\n" + p.stderr)
        if p.returncode != 0:
            print(p.stdout[-3000:], p.stderr[-3000:])
            raise SystemExit(f"{name} failed ({p.returncode})")
        rows.append((name, w, cpu))
        print(f"{name:10s} wall {w:7.1f} s  cpu {cpu:7.1f} s", flush=True)
        if name == "fit":
            print("\n".join(ln for ln in p.stdout.splitlines() if not ln.startswith("PROFILE_JSON")
                            and ("  " in ln or "whole" in ln or "phase" in ln)))
        if name == "evaluate":
            try:
                ev = json.loads(p.stdout[p.stdout.index("{"):])
                print(f"  MA {ev.get('ma')}  masked PSNR {ev.get('psnr_masked')}"
                      if "ma" in ev else "  " + p.stdout.strip()[-600:])
            except ValueError:
                print("  " + p.stdout.strip()[-600:])
    tw = time.perf_counter() - t_all
    print(f"{'demo':10s} wall {tw:7.1f} s  cpu {sum(r[2] for r in rows):7.1f} s"
          f"  ({'cold' if cold else 'warm'} Warp kernel cache{': ' + cache if cache else ''})")


def main():
    argv = sys.argv[1:]
    if argv and argv[0] == "profiled":
        return profiled(argv[1:])
    out, cold, fit_args, init_args = ROOT / "out" / "cpu_demo", False, [], []
    if "--" in argv:
        i = argv.index("--")
        argv, fit_args = argv[:i], argv[i + 1:]
    while argv:
        a = argv.pop(0)
        if a == "--out":
            out = Path(argv.pop(0))
        elif a == "--cold":
            cold = True
        elif a == "--init-args":   # extra `init` arguments, one string: --init-args "--spacing 0.00965"
            init_args = argv.pop(0).split()
        else:
            raise SystemExit(f"unknown argument {a}")
    run_steps(out, cold, fit_args, init_args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
