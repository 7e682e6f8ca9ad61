"""One fit against B fits of the same scene from different starts batched in one process
(fit/batched.py: one tiled rollout forward+backward per iteration for all B copies), on one device.

    python benchmarks/batch_fits.py --device cuda                      # the bundled sample, the demo's settings
    python benchmarks/batch_fits.py --device cpu --grid 12 --iterations 3   # tiny, to check it runs

The scene: the bundled sample (samples/foam_bar, 14 frames) initialised at the demo's settings
(`init --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150`), true
contacts (its gt/), the default bumps schedule (60 iterations, the convergence stop on), no
confidence estimate (the same for every case: it runs once, for the chosen start). The uniform
start search runs once (timed apart) and every case starts from its E; a short warm-up (Warp's
module loads, one fit iteration) runs before the timed cases. Each case builds its own problem, so
its rollouts' CUDA graphs are captured inside its time.

Cases: "1" = `fit_bumps` (the one fit the app runs); "B=2", "B=4" = `fit_bumps_batched` from the
first B of `batched.START_FACTORS` (x 1, 0.71, 0.5, 0.35 of the searched uniform E: inside the x1
start's substep rung; seeds 0..B-1; the first copy is the one fit's start). `--factors` gives other
factors (e.g. `--factors 1 0.5 2 0.25`, the old starts); `--also-factors 1 0.5 2 0.25` runs one more
batched case from those, last (a before/after on the same card in one run); `--per-copy-renders`
runs the largest batch once more, last, with its renders and loss per copy and frame
(`batched.BATCH_RENDERS` off: the before of the batched renders). Each copy stops on its own; the batch ends
with the last. Printed: wall and process CPU time in all and per lockstep iteration, the time
against one fit (the issue's target: four small fits batched <= 2x one fit's time), the substep
counts the rollouts ran at (count: rollouts), and each copy's iterations, final loss, MA (per
Gaussian against gt/youngs_modulus.npy) and masked PSNR (the fit's own frame metrics). `--out DIR`
also writes the rows as JSON lines.

`--profile`: where the time goes, per phase. The package's functions are wrapped with timers here
(nothing in the package changes; on cuda each timed piece synchronises torch and Warp before and
after, so a piece's time is its GPU work too): the start search twice (cold: the first simulation
of the process, with Warp's module loads / kernel compiles; warm: a fresh problem, modules
loaded, so its rollouts' models and CUDA graphs are built again), then one fit and the largest
batch again (profiled runs: their totals include the wrappers' syncs, the unprofiled rows above
are the timings). Pieces nest (inclusive times; "(rest)" is the parent's time outside its timed
children: Python, torch's untimed ops, the optimiser's host work): the simulator's forward
(`Rollout.__call__`: input checks, one host sync, the replayed graphs) and backward, the graph
capture (first use of a rung's rollout: a warm-up frame and one capture per frame), Warp's module
loads (calls over 1 ms counted as loads), model builds on a rung change, tiling, the renderer
forward / backward, the loss terms, the optimiser step, the last pass (renders kept), the frame
metrics.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _clock():
    return time.perf_counter(), time.process_time()


def _sync(device):
    if str(device).startswith("cuda"):
        import torch
        import warp as wp

        torch.cuda.synchronize()
        wp.synchronize()


class Profile:
    """Timers wrapped around the package's functions (benchmarks/cpu_demo.py's way: nothing in the
    package changes). Time is kept per phase (`with prof.phase(name)`) and per nesting path of the
    timed pieces open at the call; outside a phase the wrappers only call through. On cuda a piece
    synchronises torch and Warp before and after (`sync`), except where that is unsafe (Warp's
    module load may run inside a graph capture) or meaningless (the package's own host syncs,
    counted)."""

    def __init__(self, device):
        from collections import Counter, defaultdict

        self.device = device
        self.cuda = str(device).startswith("cuda")
        self.acc = defaultdict(lambda: [0.0, 0.0, 0, 0])  # (phase, path) -> [wall, cpu, calls, calls > 1 ms]
        self.count = defaultdict(Counter)                  # phase -> Counter (substep-frames, loads, syncs)
        self.substeps = defaultdict(Counter)               # phase -> {substeps per frame: rollouts}
        self.phase_name = None
        self.stack: list[str] = []
        self.saved: list = []
        self.timing = True

    def sync(self):
        if self.cuda:
            _sync(self.device)

    # ------------------------------------------------------------------ wrapping
    def _wrap(self, obj, attr, name, sync=True, on_call=None):
        import functools

        raw = vars(obj).get(attr) if attr in vars(obj) else None
        static = isinstance(raw, staticmethod)
        fn = getattr(obj, attr)
        prof = self

        @functools.wraps(fn)
        def wrapper(*a, **kw):
            if prof.phase_name is None:
                return fn(*a, **kw)
            label = name(a, kw) if callable(name) else name
            if label is None or not prof.timing:
                out = fn(*a, **kw)
                if on_call is not None:
                    on_call(a, kw, 0.0)
                return out
            if sync:
                prof.sync()
            prof.stack.append(label)
            key = (prof.phase_name, tuple(prof.stack))
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **kw)
            finally:
                if sync:
                    prof.sync()
                dw = time.perf_counter() - w0
                acc = prof.acc[key]
                acc[0] += dw
                acc[1] += time.process_time() - c0
                acc[2] += 1
                acc[3] += dw > 1e-3
                prof.stack.pop()
                if on_call is not None:
                    on_call(a, kw, dw)

        self.saved.append((obj, attr, raw))
        setattr(obj, attr, staticmethod(wrapper) if static else wrapper)

    def install(self, timing=True):
        """Wrap the pieces (timing=False: only the substep counts are recorded, no syncs)."""
        import torch
        import warp._src.context as wctx

        from physinteract_usd import simulation
        from physinteract_usd.fit import batched, optimize, problem
        from physinteract_usd.render import function as rf
        from physinteract_usd.sim import batch as sim_batch
        from physinteract_usd.sim import rollout

        self.timing = timing
        prof = self

        def substeps_after(sim_method):
            def rec(a, kw, dw):
                sim = a[0]
                E = a[1] if len(a) > 1 else kw.get("E")
                n = 1 if sim_method == "simulate" else int(getattr(E, "shape", (1,))[0])
                prof.substeps[prof.phase_name][sim.substeps] += 1
                prof.count[prof.phase_name][f"copy-rollouts at {sim.substeps} substeps"] += n
            return rec

        self._wrap(simulation.Simulation, "simulate", None, on_call=substeps_after("simulate"))
        self._wrap(simulation.Simulation, "simulate_batch", lambda a, kw: None if prof.stack else "tiled rollouts",
                   on_call=substeps_after("simulate_batch"))
        if not timing:
            return

        def frames(a, kw, dw):
            ro = a[0]
            prof.count[prof.phase_name]["substep-frames simulated (forward)"] += ro.T * ro.S

        def load(a, kw, dw):
            if dw > 1e-3:
                prof.count[prof.phase_name]["Warp module loads (> 1 ms)"] += 1

        def synced(a, kw, dw):
            prof.count[prof.phase_name]["host syncs (the package's, per rollout call)"] += 1

        self._wrap(wctx.Module, "load", "Warp module load / compile", sync=False, on_call=load)
        self._wrap(simulation.Simulation, "_use_bound", "model build (rung change)")
        self._wrap(sim_batch, "tile", "tile the model (new copies / rung)")
        self._wrap(rollout.Rollout, "__call__", "sim forward", on_call=frames)
        self._wrap(rollout._SimulateFn, "backward", "sim backward")
        self._wrap(rollout.Rollout, "_ensure_graphs", "graph warm-up + capture")
        self._wrap(rollout, "_torch_sync", "package host syncs", sync=False, on_call=synced)
        self._wrap(rollout, "_warp_sync", "package host syncs", sync=False, on_call=synced)
        self._wrap(problem, "render", "render forward")
        self._wrap(problem, "render_batch", "render forward (batched over copies and frames)")
        self._wrap(rf.RasterizeGaussians, "backward", "render backward (raster)")
        self._wrap(problem, "reconstruction_loss", "loss terms")
        self._wrap(problem, "reconstruction_loss_batch", "loss terms (batched)")
        self._wrap(problem.FitProblem, "loss", lambda a, kw: "last pass (renders kept)" if kw.get("keep_renders")
                   else None)
        self._wrap(torch.Tensor, "backward", "backward (all)")
        self._wrap(torch.optim.AdamW, "step", "optimiser step")
        for m in (optimize, batched):
            self._wrap(m, "frame_metrics", "frame metrics")

    def uninstall(self):
        for obj, attr, raw in reversed(self.saved):
            if raw is None:
                delattr(obj, attr)
            else:
                setattr(obj, attr, raw)
        self.saved.clear()

    # ------------------------------------------------------------------ phases
    def phase(self, name):
        import contextlib

        @contextlib.contextmanager
        def cm():
            self.sync()
            self.phase_name, self.stack = name, []
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                yield
            finally:
                self.sync()
                acc = self.acc[(name, ())]
                acc[0] += time.perf_counter() - w0
                acc[1] += time.process_time() - c0
                acc[2] += 1
                self.phase_name = None
        return cm()

    def rows(self, phase, per=1):
        """[(indent, label, wall s, cpu s, calls, calls over 1 ms, wall ms per `per`)] in tree order,
        children by time, each parent with children followed by its "(rest)"."""
        keys = {path: v for (ph, path), v in self.acc.items() if ph == phase}
        out = []

        def visit(path, depth):
            w, c, n, slow = keys[path]
            out.append((depth, path[-1] if path else phase, w, c, n, slow, 1e3 * w / max(per, 1)))
            kids = sorted((p for p in keys if len(p) == len(path) + 1 and p[:len(path)] == path),
                          key=lambda p: -keys[p][0])
            for k in kids:
                visit(k, depth + 1)
            if kids:
                rw = w - sum(keys[k][0] for k in kids)
                rc = c - sum(keys[k][1] for k in kids)
                out.append((depth + 1, "(rest)", rw, rc, 0, 0, 1e3 * rw / max(per, 1)))
        if () in keys:
            visit((), 0)
        return out

    def print_table(self, phase, per=1, per_label="iteration", file=None):
        print(f"\n#### {phase}\n", file=file)
        print(f"| piece (nested: inclusive) | wall s | CPU s | calls (> 1 ms) | wall ms / {per_label} |", file=file)
        print("|---|---:|---:|---:|---:|", file=file)
        for depth, label, w, c, n, slow, pm in self.rows(phase, per):
            calls = f"{n} ({slow})" if n else ""
            print(f"| {'. ' * depth}{label} | {w:.2f} | {c:.2f} | {calls} | {pm:.1f} |", file=file)
        cnt = dict(self.count.get(phase, {}))
        if cnt:
            print("\n" + "; ".join(f"{k}: {v}" for k, v in sorted(cnt.items())), file=file)

    def dump(self):
        return {"acc": [[ph, list(path), *v] for (ph, path), v in self.acc.items()],
                "count": {ph: dict(c) for ph, c in self.count.items()},
                "substeps": {ph: {str(k): v for k, v in c.items()} for ph, c in self.substeps.items()}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--capture", default=str(ROOT / "samples" / "foam_bar"))
    ap.add_argument("--grid", type=int, default=24, help="init --grid (the demo: 24; 12 for a tiny CPU check)")
    ap.add_argument("--iterations", type=int, default=60, help="per fit (the demo's default: 60)")
    ap.add_argument("--copies", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--factors", type=float, nargs="+", default=None,
                    help="the starts' factors on the searched E (default: batched.START_FACTORS)")
    ap.add_argument("--also-factors", type=float, nargs="+", default=None,
                    help="one more batched case from these starts after the others (e.g. 1 0.5 2 0.25: the old "
                         "starts, for a before/after on the same card in the same run)")
    ap.add_argument("--patience", type=int, default=None, help="the convergence stop's patience (default: the fit's)")
    ap.add_argument("--profile", action="store_true", help="the per-phase breakdown (module doc)")
    ap.add_argument("--per-copy-renders", action="store_true",
                    help="one more case, last: the largest batch with the renders and loss per copy and frame "
                         "(batched.BATCH_RENDERS off: the before of the batched renders, same run)")
    ap.add_argument("--work", default=None, help="folder for the stage (default: a temporary one)")
    ap.add_argument("--out", default=None, help="write the rows as JSON lines into OUT/batch_fits.jsonl")
    a = ap.parse_args(argv)

    import torch

    from physinteract_usd import api
    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.devices import cpu_threads, device_name
    from physinteract_usd.fit import fit_bumps
    from physinteract_usd.fit.batched import START_FACTORS, Start, fit_bumps_batched
    from physinteract_usd.fit.material import MaterialField
    from physinteract_usd.fit.optimize import golden_uniform_search

    factors = tuple(a.factors) if a.factors else START_FACTORS
    if max(a.copies) > len(factors):
        ap.error(f"--copies up to {max(a.copies)} needs as many --factors (got {len(factors)})")

    def starts(B, seed, fs=None):
        fs = factors if fs is None else fs
        return [Start(float(fs[i]), int(seed) + i) for i in range(B)]

    cpu_threads(a.device)
    cap = Path(a.capture)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="batch_fits_"))
    work.mkdir(parents=True, exist_ok=True)
    stage = work / "scene.usda"
    quiet = lambda *x: None  # noqa: E731
    api.init(stage, cap, grid=a.grid, padding=0.3, youngs_range=(1e3, 6e4), max_poisson=0.4, density=150.0,
             preload=False, force=True, discard_fits=True, log=quiet)
    over = {"confidence_probes": 0}
    if a.patience is not None:
        over["plateau_patience"] = a.patience
    job = prepare_fit(stage, iterations=a.iterations, contact_from=cap / "gt", device=a.device, log=quiet,
                      settings_overrides=over, progress=False)
    s = job.settings
    e_gt = np.load(cap / "gt" / "youngs_modulus.npy")
    dev = device_name(a.device)
    print(f"device: {dev}; torch {torch.__version__}; scene {cap.name} at grid {a.grid}, "
          f"{len(job.scene.particles_positions)} particles, {job.scene.n_frames} frames; "
          f"{s.iterations} iterations per fit, patience {s.plateau_patience}; starts x "
          + ", ".join(f"{f:.4g}" for f in factors[:max(a.copies)]), flush=True)

    prof = Profile(a.device)

    def search(label):
        """The start search from a fresh problem, as a phase."""
        with prof.phase(label):
            prob = make_problem(job)
            st = prob.scene.settings
            mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                                device=prob.tdev)
            mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
            e = golden_uniform_search(prob, mat, s.search_evals, None)
        w, c = prof.acc[(label, ())][:2]
        print(f"{label}: uniform E {e:.4g} Pa in {w:.1f} s wall, {c:.1f} s CPU", flush=True)
        return prob, e

    # the start search (cold: the process's first simulation; profiled: also again, warm) and a warm-up
    prof.install(timing=a.profile)
    prob, e_u = search("start search (cold)")
    e_rung = prob.sim.bound_for(e_u)
    print("the starts' E and substep rungs: " + ", ".join(
        f"x{f:.3g}: {e_u * f:.4g} Pa -> rung {prob.sim.bound_for(e_u * f):.4g}" for f in factors[:max(a.copies)])
        + f" (x1's rung {e_rung:.4g} Pa)", flush=True)
    if a.profile:
        search("start search (warm)")
    prof.uninstall()
    prof.install(timing=False)
    w1 = time.perf_counter()
    fit_bumps(prob, dataclasses.replace(s, iterations=1), progress=False, uniform_e=e_u)
    fit_bumps_batched(prob, dataclasses.replace(s, iterations=1), starts(2, s.seed), uniform_e=e_u, progress=False)
    _sync(a.device)
    print(f"warm-up done ({time.perf_counter() - w1:.1f} s)", flush=True)

    def copy_row(r):
        fm = M.summarize(r.frame_metrics)
        return {"iterations": len(r.loss_history), "final_loss": r.final_loss,
                "ma": M.material_accuracy(r.youngs_gaussian, e_gt) if len(e_gt) == len(r.youngs_gaussian) else None,
                "psnr_masked": fm["psnr_masked"], "median_e": float(np.median(r.youngs)),
                "factor": (r.model.get("start") or {}).get("factor", 1.0),
                "status": (r.model.get("start") or {}).get("status", "interrupted" if r.interrupted else "done")}

    def run_case(B, label, fs=None, per_copy_renders=False):
        from physinteract_usd.fit import batched

        p = make_problem(job)
        _sync(a.device)
        batched.BATCH_RENDERS = not per_copy_renders
        try:
            with prof.phase(label):
                w0, c0 = _clock()
                if B == 1:
                    res = [fit_bumps(p, s, progress=False, uniform_e=e_u)]
                else:
                    res = fit_bumps_batched(p, s, starts(B, s.seed, fs), uniform_e=e_u, progress=False)
                _sync(a.device)
                w1, c1 = _clock()
        finally:
            batched.BATCH_RENDERS = True
        copies = [copy_row(r) for r in res]
        lock = max(c["iterations"] for c in copies)
        return {"case": ("1" if B == 1 else f"B={B}") + (" (also-factors)" if fs else "")
                + (" (renders per copy)" if per_copy_renders else ""), "copies": B,
                "device": dev, "grid": a.grid,
                "particles": len(p.x0), "frames": p.T, "wall_s": w1 - w0, "cpu_s": c1 - c0, "lockstep_iterations": lock,
                "wall_per_iteration_s": (w1 - w0) / max(lock, 1), "cpu_per_iteration_s": (c1 - c0) / max(lock, 1),
                "factors": [c["factor"] for c in copies], "uniform_e": e_u, "x1_rung_e": e_rung,
                "substeps": {str(k): v for k, v in sorted(prof.substeps[label].items())}, "copy": copies,
                "profiled": label.endswith("(profiled)")}

    jsonl = None
    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        jsonl = Path(a.out) / "batch_fits.jsonl"

    def keep(row):      # written as each case ends (a time limit keeps what finished)
        if jsonl is not None:
            with open(jsonl, "a") as fh:
                fh.write(json.dumps(row) + "\n")

    def say(row):
        keep(row)
        print(f"{row['case']}{' (profiled)' if row['profiled'] else ''}: {row['wall_s']:.1f} s wall "
              f"({row['cpu_s']:.1f} s CPU), {row['lockstep_iterations']} iterations, substeps per frame "
              f"(rollouts) {row['substeps']}; "
              + "; ".join(f"[x{c['factor']:.3g}] {c['iterations']} it loss {c['final_loss']:.5f} MA {c['ma']:.3f}"
                          for c in row["copy"]), flush=True)

    rows = []
    for B in [1] + [int(b) for b in a.copies]:
        rows.append(run_case(B, f"case {B}"))
        say(rows[-1])
    prof.uninstall()

    one = rows[0]
    print()
    print(f"### {dev}, {cap.name} at grid {a.grid} ({one['particles']} particles, {one['frames']} frames), "
          f"{s.iterations} iterations per fit, starts x " + ", ".join(f"{f:.3g}" for f in factors[:max(a.copies)])
          + ("" if a.device.startswith("cuda") else " -- CPU: tiling does not pay here (a size check only)"))
    print()
    print("| case | wall s (CPU s) | x one fit | lockstep iterations | wall s / iteration | substeps/frame: rollouts "
          "| per copy: iterations, final loss, MA, masked PSNR |")
    print("|---|---:|---:|---:|---:|---|---|")
    for r in rows:
        per = "; ".join(f"x{c['factor']:.3g}: {c['iterations']} it, {c['final_loss']:.5f}, MA {c['ma']:.3f}, "
                        f"{c['psnr_masked']:.2f} dB" for c in r["copy"])
        sub = ", ".join(f"{k}: {v}" for k, v in r["substeps"].items())
        print(f"| {r['case']} | {r['wall_s']:.1f} ({r['cpu_s']:.1f}) | {r['wall_s'] / one['wall_s']:.2f} | "
              f"{r['lockstep_iterations']} | {r['wall_per_iteration_s']:.3f} | {sub} | {per} |")
    four = next((r for r in rows if r["copies"] == 4), None)
    if four is not None:
        ratio = four["wall_s"] / one["wall_s"]
        print(f"\nfour fits batched: {ratio:.2f}x one fit's time (target <= 2x: {'met' if ratio <= 2 else 'missed'}); "
              f"per fit {four['wall_s'] / 4 / one['wall_s']:.2f}x")

    if a.profile:
        prof.install(timing=True)
        big = max(int(b) for b in a.copies)
        for B in (1, big):
            rows.append(run_case(B, f"case {B} (profiled)"))
            say(rows[-1])
        prof.uninstall()
        print(f"\n### Where the time goes ({dev}; each piece synchronised, inclusive; per iteration = per "
              "lockstep iteration, per probe = per simulator call)")
        for ph in ("start search (cold)", "start search (warm)"):
            probes = prof.acc.get((ph, ("sim forward",)), [0, 0, 0, 0])[2]
            prof.print_table(ph, per=probes, per_label="probe")
        for r in rows:
            if r["profiled"]:
                prof.print_table(f"case {r['copies']} (profiled)", per=r["lockstep_iterations"])

    if a.profile:
        keep({"profile": prof.dump(), "device": dev})
    if a.per_copy_renders:  # the batched renders' before, on the same card in the same run
        big = max(int(b) for b in a.copies)
        prof.install(timing=False)
        r = run_case(big, "case per-copy renders", per_copy_renders=True)
        prof.uninstall()
        say(r)
        same = next(x for x in rows if x["copies"] == big and not x["profiled"])
        print(f"\nB={big}, renders and loss per copy and frame: {r['wall_s']:.1f} s ({r['wall_per_iteration_s']:.3f} s per "
              f"lockstep iteration) against batched {same['wall_s']:.1f} s ({same['wall_per_iteration_s']:.3f} s)")
    if a.also_factors:      # last: a before/after on the same card (the other starts), after the profile
        prof.install(timing=False)
        r = run_case(len(a.also_factors), "case also-factors", tuple(a.also_factors))
        prof.uninstall()
        say(r)
        print(f"\nstarts x {', '.join(f'{f:g}' for f in a.also_factors)}: {r['wall_s']:.1f} s = "
              f"{r['wall_s'] / one['wall_s']:.2f}x one fit ({r['wall_per_iteration_s']:.3f} s per lockstep iteration, "
              f"substeps/frame: rollouts {r['substeps']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
