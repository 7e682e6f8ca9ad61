"""The simulator's forward and backward on the README demo's problem, in process CPU seconds.

The demo's stage (`scripts/demo.sh`'s init on samples/foam_bar, grid 24, contacts extracted from the
video as `fit` does) is built once into --stage; then R rounds of one forward (the fit's rollout, at
a uniform E) and one backward of a fixed random loss over every frame's x and F, each timed with
`time.process_time` (the machine is shared: CPU seconds are what to compare), and the median and
min per round printed with the substeps per frame and the loss (equal across code versions that
compute the same thing).

    python benchmarks/cpu_sim_demo.py [--code DIR] [--stage DIR] [--rounds 5] [--E 2.5e4] [--json F]

`--code DIR` imports the package from another checkout (e.g. `git worktree add /tmp/old da30241`),
to compare two versions in the same conditions (docs/benchmarks/cpu.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def build_stage(stage_dir: Path, code: Path) -> Path:
    stage = stage_dir / "scene.usda"
    if (stage_dir / "scene.fit.usdc").exists():
        return stage
    stage_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(code))
    subprocess.run([sys.executable, "-m", "physinteract_usd", "init", str(stage), "--capture",
                    str(ROOT / "samples" / "foam_bar"), "--grid", "24", "--padding", "0.3", "--youngs-range",
                    "1e3,6e4", "--max-poisson", "0.4", "--density", "150", "--force"], check=True, env=env)
    subprocess.run([sys.executable, "-m", "physinteract_usd", "extract", str(stage)], check=True, env=env)
    return stage


def _kernel_timer(prob, E: float) -> dict:
    """Eager launches (graphs off), each solver launch and memset timed in process CPU seconds."""
    import warp as wp

    from physinteract_usd.sim import solver as solver_mod

    acc: dict = {}
    launch, zero = wp.launch, wp.array.zero_

    def timed(name, fn, *a, **kw):
        c0 = time.process_time()
        try:
            return fn(*a, **kw)
        finally:
            t, n = acc.get(name, (0.0, 0))
            acc[name] = (t + time.process_time() - c0, n + 1)

    def t_launch(kernel, *a, **kw):
        name = kernel.key + (" (adjoint)" if kw.get("adjoint") else "")
        return timed(name, launch, kernel, *a, **kw)

    solver_mod.wp = type("wp_timed", (), {k: getattr(wp, k) for k in dir(wp) if not k.startswith("__")})
    solver_mod.wp.launch = staticmethod(t_launch)
    wp.array.zero_ = lambda self: timed("memset", zero, self)
    if prob.sim.adaptive:
        prob.sim.ensure_stable(E)
    prob.sim.rollout.graphs = False
    return acc


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--code", default=str(ROOT), help="the checkout whose package to import")
    ap.add_argument("--stage", default=str(ROOT / "out" / "cpu_sim_demo"), help="where the demo's stage is kept")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--E", type=float, default=2.5e4, help="uniform Young's modulus (Pa)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--opt-level", type=int, default=None,
                    help="Warp's optimization_level for the kernels (default: Warp's, -O2 on the CPU)")
    ap.add_argument("--per-kernel", action="store_true",
                    help="launch eagerly (no graphs) and print each kernel's CPU seconds per round")
    args = ap.parse_args()
    code = Path(args.code).resolve()
    stage = build_stage(Path(args.stage), code)
    sys.path.insert(0, str(code))
    import numpy as np
    import torch

    torch.set_num_threads(1)
    if args.opt_level is not None:
        import warp as wp

        wp.config.optimization_level = args.opt_level
    from physinteract_usd.app import fit as app_fit
    assert Path(app_fit.__file__).resolve().is_relative_to(code), app_fit.__file__

    job = app_fit.prepare_fit(stage, log=lambda *a, **k: None, progress=False)
    prob = app_fit.make_problem(job)
    per_kernel = _kernel_timer(prob, args.E) if args.per_kernel else None
    P = len(prob.x0)
    E = torch.full((P,), args.E, dtype=torch.float32)
    nu = torch.full((P,), 0.3, dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    W = None
    rows = []
    for r in range(args.rounds + 1):           # round 0 warms up (module loads, graph capture)
        Er = E.clone().requires_grad_(True)
        nur = nu.clone().requires_grad_(True)
        c0, w0 = time.process_time(), time.perf_counter()
        x, F = prob.simulate(Er, nur)
        c1, w1 = time.process_time(), time.perf_counter()
        if W is None:
            W = torch.randn(x.shape, generator=g, dtype=x.dtype)
            WF = torch.randn(F.shape, generator=g, dtype=F.dtype)
        loss = (x * W).sum() + (F * WF).sum()
        loss.backward()
        c2, w2 = time.process_time(), time.perf_counter()
        if r:
            rows.append((c1 - c0, c2 - c1, w1 - w0, w2 - w1))
        elif per_kernel is not None:
            per_kernel.clear()
        gE = float(Er.grad.abs().sum())
    fw, bw, fw_wall, bw_wall = np.array(rows).T
    out = dict(code=str(code), opt_level=args.opt_level, particles=P, frames=int(x.shape[0]), substeps=int(prob.model.substeps),
               grid=list(prob.model.grid.resolution), loss=float(loss.detach()), grad_E_l1=gE,
               forward_median=float(np.median(fw)), forward_min=float(fw.min()),
               backward_median=float(np.median(bw)), backward_min=float(bw.min()), rounds=args.rounds,
               forward_wall_median=float(np.median(fw_wall)), backward_wall_median=float(np.median(bw_wall)),
               lanes=os.environ.get("PHYSINTERACT_SIM_LANES", ""), load_avg=os.getloadavg()[0])
    print(f"code {code} (opt level {args.opt_level}): P {P}, T {out['frames']}, substeps/frame {out['substeps']}, grid {out['grid']}, "
          f"loss {out['loss']:.9g}, |dL/dE|_1 {gE:.9g}")
    print(f"forward  CPU s: median {out['forward_median']:.3f}, min {out['forward_min']:.3f}; "
          f"wall median {out['forward_wall_median']:.3f}")
    print(f"backward CPU s: median {out['backward_median']:.3f}, min {out['backward_min']:.3f}; "
          f"wall median {out['backward_wall_median']:.3f}")
    print(f"lanes {out['lanes'] or 'default'}, load average (1 min) at the end {out['load_avg']:.2f}")
    if per_kernel is not None:
        print("| kernel | CPU s per round | launches per round |\n|---|---:|---:|")
        for name, (t, n) in sorted(per_kernel.items(), key=lambda kv: -kv[1][0]):
            print(f"| {name} | {t / args.rounds:.3f} | {n // args.rounds} |")
        out["per_kernel"] = {k: v[0] / args.rounds for k, v in per_kernel.items()}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
