"""Kernel launches and memsets per simulator substep, forward and backward (issue #26: a captured
substep is launch-bound on a GPU, so the count is what fusion can lower). Runs on the CPU (eager
launches, counted by wrapping `wp.launch`, `wp.array.zero_` and `wp.copy`); each launch is one
node of the captured graph on a GPU.

    python benchmarks/count_launches.py                 # the tiny scene, every effect on
    python benchmarks/count_launches.py --effects none  # the base model (no effect kernels)

The scene: a 3x3x3 block on a 10^3 grid, a clamp, a grasp, a sphere collider, optionally every
effect (plasticity, viscoelasticity, damping, ground); 2 frames x 6 substeps, float64. Printed per
substep: the forward (`MPMSolver.step`) and the backward (`MPMSolver.step_adjoint`, the replay path
and the stored-states path) with each kernel's name, for the CUDA default (fused zeroing and fused transfer
kernels, `sim.solver.FUSED_ZERO` / `FUSED_KERNELS`), the CUDA default before it and the CPU default; per
frame and per call, the rollout's own launches outside the substeps (status checks, adjoint carries,
input copies; eager, so the first call's buffer allocations are in these counts: a captured graph
replays only the per-frame ones).

    python benchmarks/count_launches.py --fit                     # the CLI's small fit, launches per phase
    python benchmarks/count_launches.py --fit --device cuda --grid 24 --iterations 60 --repeats 2 --json OUT/fit.json

`--fit` (issue #26): `init samples/foam_bar --grid G` (the demo's other flags) once, then `fit --contact-from
samples/foam_bar/gt --iterations N` on a fresh copy of the stage per run, with one captured graph per frame
(`sim.rollout.FRAME_GRAPHS = False`, the old path) and per frame shape (True) alternating, `--repeats` times
each, in one process. Per run: the Python-issued Warp launches (`wp.launch`) by phase (the start search, each
graph set's warm-up + capture, the rest: eager forwards and per-call work), the captures and graph launches,
wall and process CPU time of the fit and of its start search, the final loss (equal between the paths: bitwise
on the CPU). On the CPU the CUDA code paths are forced (fused kernels, fused zeroing, the grid box) and the
graphs are Warp's CPU graphs, so the launch counts are what a CUDA run captures; the CPU's times say nothing
about a GPU's (2 shared cores: wall clock unreliable)."""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--effects", choices=["all", "none"], default="all")
    ap.add_argument("--fit", action="store_true", help="count a small CLI fit's launches per phase (see above)")
    ap.add_argument("--grid", type=int, default=12, help="--fit: init's grid")
    ap.add_argument("--iterations", type=int, default=3, help="--fit: fit iterations")
    ap.add_argument("--device", default="cpu", help="--fit: fit --device")
    ap.add_argument("--repeats", type=int, default=1, help="--fit: runs per path (alternating old / new)")
    ap.add_argument("--paths", default="old,new", help="--fit: which paths, in order per repeat (old: per-frame "
                                                        "graphs, new: per frame shape)")
    ap.add_argument("--json", default=None, help="--fit: write the runs as JSON here")
    ap.add_argument("--cpu-paths", action="store_true", help="--fit on the CPU: keep the CPU's own kernel paths "
                                                             "(memsets, separate kernels, no grid box)")
    a = ap.parse_args(argv)
    if a.fit:
        return fit_counts(a)

    import torch
    import warp as wp

    from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
    from physinteract_usd.sim import rollout as rollout_mod
    from physinteract_usd.sim import solver as solver_mod
    from sim_helpers import block

    wp.init()
    DX, SP, T, S = 0.05, 0.025, 2, 6
    pts = block((3, 3, 3), SP, (0.25, 0.12, 0.25))
    eff = {"plasticity": {"yieldStress": 60.0}, "viscoelasticity": {"modulus": 500.0, "relaxationTime": 0.05},
           "damping": {"coefficient": 1.0}, "ground": {"height": 0.1, "friction": 0.3}} if a.effects == "all" else {}
    m = SimModel.create(pts, SP ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), DX, (10, 10, 10)), fps=20,
                        substeps=S, E_max=1e4, dtype="float64", effects=eff)
    bottom = np.nonzero(pts[:, 1] < pts[:, 1].min() + 1e-9)[0]
    sph = np.repeat(np.array([pts[:, 0].mean(), pts[:, 1].max() + 0.04, pts[:, 2].mean()])[None], T + 1, 0)
    ctrl = Control([Contact("fixed", indices=bottom[:2]),
                    Contact("pointNonAdherent", trajectory=sph, radius=0.03, friction=0.2)], n_frames=T)

    counts = collections.defaultdict(collections.Counter)
    where = ["rollout (outside substeps)"]

    def wrap(obj, attr, label):
        fn = getattr(obj, attr)

        def w(*args, **kw):
            if label == "launch":
                k = args[0] if args else kw.get("kernel")
                name = getattr(k, "key", str(k)).replace("_build__locals__", "") + (
                    " (adjoint)" if kw.get("adjoint") else "")
            else:
                name = label
            counts[where[-1]][name] += 1
            return fn(*args, **kw)
        setattr(obj, attr, w)
        return fn

    calls = collections.Counter()

    def phase(obj, attr, label):
        fn = getattr(obj, attr)

        def w(*args, **kw):
            calls[label] += 1
            where.append(label)
            try:
                return fn(*args, **kw)
            finally:
                where.pop()
        setattr(obj, attr, w)

    wrap(wp, "launch", "launch")
    wrap(wp.array, "zero_", "memset (array.zero_)")
    wrap(wp, "copy", "copy (wp.copy)")
    phase(solver_mod.MPMSolver, "step", "forward substep")
    phase(solver_mod.MPMSolver, "step_adjoint", "backward substep")

    def run(T, fused, store, kernels):
        ctrl_t = Control([Contact("fixed", indices=bottom[:2]),
                          Contact("pointNonAdherent", trajectory=np.repeat(sph[:1], T + 1, 0), radius=0.03,
                                  friction=0.2)], n_frames=T)
        solver_mod.FUSED_ZERO = fused
        solver_mod.FUSED_KERNELS = kernels
        rollout_mod.STORE_STATES_BYTES = (1 << 40) if store else 0
        counts.clear()
        calls.clear()
        ro = Rollout(m, ctrl_t, graphs=False)
        P = len(pts)
        E = torch.full((P,), 2e3, dtype=torch.float64, requires_grad=True)
        nu = torch.full((P,), 0.3, dtype=torch.float64)
        x, F = ro(E, nu)
        (x.sum() + F.sum()).backward()
        return ({k: collections.Counter(v) for k, v in counts.items()}, dict(calls))

    del ctrl
    print(f"effects: {a.effects}; {S} substeps per frame; eager launches on the CPU (a GPU graph has one node each)")
    configs = [(True, True, True, "the CUDA default since session 10 (fused zeroing, fused transfer kernels)"),
               (True, False, True, "the CUDA default before (fused zeroing, separate kernels)"),
               (False, False, True, "the CPU default (memsets, separate kernels)"),
               (True, True, False, "the CUDA default, backward by replay (states too large to store)")]
    for fused, kernels, store, what in configs:
        if True:
            c2, k2 = run(2, fused, store, kernels)
            c4, k4 = run(4, fused, store, kernels)
            fwd, bwd = c4.get("forward substep", {}), c4.get("backward substep", {})
            nf, nb = k4.get("forward substep", 1), k4.get("backward substep", 1)
            out2 = sum(c2.get("rollout (outside substeps)", {}).values())
            out4 = sum(c4.get("rollout (outside substeps)", {}).values())
            per_frame = (out4 - out2) / 2
            per_call = out2 - 2 * per_frame
            print(f"\n## {what}: zeroing {'fused' if fused else 'memsets'}, transfer kernels "
                  f"{'fused' if kernels else 'separate'}, backward from "
                  f"{'stored substep states' if store else 'the replay (each substep recomputed forward)'}")
            print(f"- forward substep ({nf} calls): {sum(fwd.values()) / nf:g} launches+memsets: "
                  + ", ".join(f"{k} {v / nf:g}" for k, v in sorted(fwd.items())))
            print(f"- backward substep ({nb} calls; the replay's forward substeps are in the line above): "
                  f"{sum(bwd.values()) / nb:g}: " + ", ".join(f"{k} {v / nb:g}" for k, v in sorted(bwd.items())))
            print(f"- outside the substeps (forward+backward call): {per_frame:g} per frame + {per_call:g} per call: "
                  + ", ".join(f"{k} {v}" for k, v in sorted(c4.get("rollout (outside substeps)", {}).items()))
                  + " (4 frames)")
    return 0


def fit_counts(a) -> int:
    import json
    import shutil
    import tempfile
    import time

    import warp as wp

    from physinteract_usd import api
    from physinteract_usd.fit import optimize
    from physinteract_usd.sim import rollout as rollout_mod
    from physinteract_usd.sim import solver as solver_mod

    sample = ROOT / "samples" / "foam_bar"
    if not str(a.device).startswith("cuda") and not a.cpu_paths:   # the CUDA code paths on the CPU: a GPU run's launches
        solver_mod.FUSED_ZERO = solver_mod.FUSED_KERNELS = solver_mod.GRID_BOX = True
    tmp = Path(tempfile.mkdtemp(prefix="count_launches_"))
    base = tmp / "init"
    base.mkdir()
    api.init(base / "scene.usda", sample, grid=a.grid, padding=0.3, youngs_range=(1e3, 6e4), max_poisson=0.4,
             density=150.0, log=lambda *x, **k: None)      # as scripts/demo.sh

    stack = ["fit: eager (forwards, per-call work)"]
    counts: dict = collections.defaultdict(collections.Counter)

    orig_launch, orig_cl = wp.launch, wp.capture_launch

    def launch(*args, **kw):
        counts[" / ".join(stack)]["launches"] += 1
        return orig_launch(*args, **kw)

    def capture_launch(*args, **kw):
        counts[" / ".join(stack)]["graph launches"] += 1
        return orig_cl(*args, **kw)

    wp.launch, wp.capture_launch = launch, capture_launch
    R = rollout_mod.Rollout
    orig_ensure = R._ensure_graphs

    def ensure(self, graphs, fn):
        name = {id(self._fwd_graphs): "forward", id(self._fwd_store_graphs): "stored forward",
                id(self._replay_graphs): "replay", id(self._adj_graphs): "adjoint",
                id(self._bwd_graphs): "backward (replay + adjoint)"}.get(id(graphs), "?")
        n0 = len(graphs)
        stack.append(f"capture {name}")
        try:
            return orig_ensure(self, graphs, fn)
        finally:
            stack.pop()
            counts[" / ".join(stack + [f"capture {name}"])]["graphs captured"] += len(graphs) - n0
    R._ensure_graphs = ensure
    orig_search = optimize.golden_uniform_search
    search_time = {}

    def search(*args, **kw):
        stack.append("start search")
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return orig_search(*args, **kw)
        finally:
            wp.synchronize()
            search_time["wall"] = time.perf_counter() - t0
            search_time["cpu"] = time.process_time() - c0
            stack.pop()
    optimize.golden_uniform_search = search

    runs = []
    for rep in range(a.repeats):
        for path in [p.strip() for p in a.paths.split(",") if p.strip()]:
            rollout_mod.FRAME_GRAPHS = {"old": False, "new": True}[path]
            d = tmp / f"run{rep}_{path}"
            shutil.copytree(base, d)
            counts.clear()
            search_time.clear()
            wp.synchronize()
            t0, c0 = time.perf_counter(), time.process_time()
            out = api.fit(d / "scene.usda", iterations=a.iterations, contact_from=sample / "gt", device=a.device,
                          progress=False, log=lambda *x, **k: None)
            wp.synchronize()
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            loss = float(out.result.final_loss)
            hist = [float(v) for v in out.result.loss_history]
            runs.append({"path": path, "repeat": rep, "frame_graphs": rollout_mod.FRAME_GRAPHS, "wall_s": wall,
                         "cpu_s": cpu, "search_wall_s": search_time.get("wall"), "search_cpu_s": search_time.get("cpu"),
                         "loss": loss, "loss_history": hist,
                         "phases": {k: dict(v) for k, v in sorted(counts.items())},
                         "launches": sum(v["launches"] for v in counts.values())})
            r = runs[-1]
            print(f"\n## {path} path ({'one graph per frame shape' if r['frame_graphs'] else 'one graph per frame'}), "
                  f"repeat {rep}: fit {wall:.1f} s wall, {cpu:.1f} s CPU; start search "
                  f"{r['search_wall_s'] or 0:.1f} s wall; loss {r['loss']!r}; {r['launches']:,} Python-issued launches")
            print(f"| phase | launches | graphs captured | graph launches |\n|---|---:|---:|---:|")
            for k, v in r["phases"].items():
                print(f"| {k} | {v.get('launches', 0):,} | {v.get('graphs captured', 0)} | {v.get('graph launches', 0):,} |")
    wp.launch, wp.capture_launch = orig_launch, orig_cl
    R._ensure_graphs = orig_ensure
    optimize.golden_uniform_search = orig_search
    by = collections.defaultdict(list)
    for r in runs:
        by[r["path"]].append(r)
    print("\n## summary (median over repeats)")
    print("| path | fit wall s | fit CPU s | start search wall s | launches | loss |\n|---|---:|---:|---:|---:|---|")
    for p, rs in by.items():
        med = lambda k: float(np.median([r[k] or 0.0 for r in rs]))  # noqa: E731
        print(f"| {p} | {med('wall_s'):.2f} | {med('cpu_s'):.2f} | {med('search_wall_s'):.2f} | "
              f"{int(med('launches')):,} | {rs[0]['loss']!r} |")
    losses = {tuple(r["loss_history"]) for r in runs}
    print(f"loss histories equal across runs (bitwise): {len(losses) == 1}; final losses "
          f"{sorted({r['loss'] for r in runs})}")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"device": str(wp.get_device(a.device)), "grid": a.grid,
                                            "iterations": a.iterations, "runs": runs}, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
