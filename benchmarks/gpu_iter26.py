"""Where one iteration of the CLI's small fit goes (issue #26: iterations 2-54 at 0.259 s median on an H200).

Runs the `fit` verb's optimiser in-process on the demo's stage (`init samples/foam_bar --grid G` with the demo's
flags, then `api.fit(..., contact_from=samples/foam_bar/gt)`), three fits in one process:

    warm      a short fit (module loads, graph bodies' first runs): not reported
    plain     the fit as the CLI runs it, only the iteration callbacks time-stamped: the per-iteration wall
              (median of iterations 2..), the figure the breakdown must add up to
    timed     the same fit with every phase of an iteration wrapped: host and device synchronised at each phase's
              entry and exit (and around each captured frame graph), so each phase's wall includes its device
              work. The syncs add a little: its per-iteration total against `plain` says how much
    count     the same fit counting, per iteration and phase: Warp launches (by kernel), graph launches, copies,
              memsets, Warp allocations, torch ops (a TorchDispatchMode; views and metadata ops apart), and the
              host reads (`.item()`/`float()`/`bool()` of a tensor, `.cpu()`, `.numpy()` of a Warp array, explicit
              synchronisations), each read by its call site

Phases (nested ones are listed inside their parent): material (the field's E, nu from its coefficients), sim
forward (input checks with their host read, the rest frame's eager launches, the frame graphs, the status and box
read-backs, the outputs' copies), render+loss (the binding's deformation, the rasterizer's pass for all frames, the
reconstruction loss), traj prior, smoothness, backward (the torch autograd pass: the loss's and deformation's ops,
the rasterizer's backward, the simulator's adjoint graphs), clean grads, adam step, tracker (the CLI's checkpoint
callback), other (the loop's own work: the best iterate's copy, the progress bar, the plateau check).

    python benchmarks/gpu_iter26.py --device cuda --grid 24 --iterations 60 --json $OUT/iter26.json    # ~1-2 min, H200
    python benchmarks/gpu_iter26.py --device cpu --grid 8 --iterations 3 --modes count                # CPU smoke / counts

On the CPU `--cuda-paths` (default on) forces the CUDA code paths (fused kernels, fused zeroing, the grid box, frame
graphs as Warp CPU graphs, frames rendered in one batched pass), so the counts are what a CUDA run issues; times on the
CPU say nothing about a GPU's. `--profile N` (CUDA) also runs N iterations under torch.profiler (CUDA activity): the
device's kernel time per iteration by kernel against the wall, i.e. how much of the iteration the GPU is busy.
"""

from __future__ import annotations

import argparse
import collections
import json
import shutil
import sys
import tempfile
import time
import weakref
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

VIEW_OPS = {"view", "_unsafe_view", "as_strided", "expand", "permute", "t", "transpose", "select", "slice",
            "unsqueeze", "squeeze", "detach", "alias", "reshape", "unbind", "split", "split_with_sizes",
            "chunk", "narrow", "diagonal", "view_as_real", "lift_fresh", "_reshape_alias", "unfold", "numpy_T",
            "expand_as", "view_as", "_local_scalar_dense", "is_nonzero", "set_", "resize_", "result_type",
            "_to_copy_noop", "sym_size", "sym_stride", "sym_numel", "sym_storage_offset", "is_same_size",
            "_has_compatible_shallow_copy_type", "empty_strided_noop"}


class Recorder:
    """Phase stack, per-iteration records (times and counts per phase path)."""

    def __init__(self, mode: str, device: str):
        self.mode = mode                      # "plain", "timed", "count"
        self.cuda = str(device).startswith("cuda")
        self.stack: list[str] = []
        self.iters: list[dict] = []
        self.cur: dict | None = None
        self.t_iter = None
        self.active = False                   # inside the optimiser's loop (after the start search)
        self.frame_t: list = []

    def sync(self):
        if self.mode != "timed":
            return
        import torch
        import warp as wp
        if self.cuda:
            torch.cuda.synchronize()
            wp.synchronize()

    def new_iter(self):
        self.cur = {"time": collections.defaultdict(float), "count": collections.defaultdict(collections.Counter),
                    "sites": collections.Counter()}

    def key(self):
        return " > ".join(self.stack) if self.stack else "other"

    def add(self, what: str, n: int = 1):
        if self.active and self.cur is not None:
            self.cur["count"][self.key()][what] += n

    def site(self, what: str):
        if not (self.active and self.cur is not None):
            return
        f = sys._getframe(2)
        while f is not None and ("physinteract_usd" not in f.f_code.co_filename or
                                 f.f_code.co_filename.endswith("gpu_iter26.py")):
            f = f.f_back
        loc = "?" if f is None else f"{Path(f.f_code.co_filename).relative_to(ROOT)}:{f.f_lineno} ({f.f_code.co_name})"
        self.cur["sites"][f"{what} @ {loc} [{self.key()}]"] += 1

    def wrap(self, owner, attr, name):
        fn = getattr(owner, attr)
        rec = self

        def wrapped(*a, **k):
            if not rec.active:
                return fn(*a, **k)
            rec.stack.append(name)
            rec.sync()
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                rec.sync()
                if rec.cur is not None:
                    rec.cur["time"][rec.key()] += time.perf_counter() - t0
                rec.stack.pop()

        wrapped.__wrapped_orig__ = fn
        setattr(owner, attr, wrapped)
        return (owner, attr, fn)


def run_fit(stage_dir: Path, a, mode: str, iterations: int, rec_box: list):
    import torch
    import warp as wp

    from physinteract_usd import api
    from physinteract_usd.app import fit_checkpoint as FC
    from physinteract_usd.fit import adamw as AW
    from physinteract_usd.fit import material as MAT
    from physinteract_usd.fit import optimize as O
    from physinteract_usd.fit import problem as PR
    from physinteract_usd.render import deform as DF
    from physinteract_usd.render import function as RF
    from physinteract_usd.render import rasterizer as RZ
    from physinteract_usd.sim import rollout as RO
    from physinteract_usd.sim import solver as SO
    from physinteract_usd import simulation as SIM

    rec = Recorder(mode, a.device)
    rec_box.append(rec)
    undo = []
    orig_search = O.golden_uniform_search

    def search(*aa, **kk):
        try:
            return orig_search(*aa, **kk)
        finally:
            rec.sync()
            rec.active = True
            rec.new_iter()
            rec.t_iter = time.perf_counter()
    O.golden_uniform_search = search
    undo.append((O, "golden_uniform_search", orig_search))
    orig_call = FC.FitTracker.__call__

    def tracked(self, it, *aa, **kk):
        if not rec.active:
            return orig_call(self, it, *aa, **kk)
        rec.stack.append("tracker")
        t0 = time.perf_counter()
        try:
            return orig_call(self, it, *aa, **kk)
        finally:
            rec.sync()
            now = time.perf_counter()
            rec.cur["time"]["tracker"] += now - t0
            rec.stack.pop()
            rec.cur["wall"] = now - rec.t_iter
            rec.cur["it"] = it
            rec.iters.append(rec.cur)
            rec.new_iter()
            rec.t_iter = time.perf_counter()
    FC.FitTracker.__call__ = tracked
    undo.append((FC.FitTracker, "__call__", orig_call))

    orig_rf = RO.Rollout.run_forward

    def run_forward(self, *aa, **kk):
        if rec.active and rec.cur is not None:
            rec.cur["shape"] = {"frames": self.T, "substeps": self.S, "particles": self.P,
                                "grid": [int(v) for v in self.solver.res] if hasattr(self.solver, "res") else None,
                                "fused_kernels": bool(self.solver.fused_kernels), "grid_box": bool(self.solver.grid_box),
                                "rate_transfer": bool(self.solver.rate_f > 0), "effects_flags": int(self.solver.flags),
                                "block_dim": int(getattr(self.solver, "block_dim", 256)),
                                "frame_graphs": bool(self.graphs and self.frame_graphs)}
        return orig_rf(self, *aa, **kk)
    RO.Rollout.run_forward = run_forward
    undo.append((RO.Rollout, "run_forward", orig_rf))
    orig_conf = O.confidence

    def conf(*aa, **kk):
        rec.active = False
        return orig_conf(*aa, **kk)
    O.confidence = conf
    undo.append((O, "confidence", orig_conf))

    if mode == "timed":
        for owner, attr, name in [
                (MAT.MaterialField, "youngs", "material"), (MAT.MaterialField, "poisson", "material"),
                (SIM.Simulation, "simulate", "sim forward"), (RO.Rollout, "_inputs", "input checks"),
                (RO._SimulateFn, "forward", "torch op"), (RO.Rollout, "_rest_prelude", "rest prelude"),
                (RO.Rollout, "_left_box", "box read-back"), (SO.MPMSolver, "raise_on_status", "status read-back"),
                (RO.Rollout, "_update_box", "box update"),
                (PR.FitProblem, "frames_rec", "render+loss"), (DF.GaussianBinding, "apply", "deform"),
                (RF.RasterizeGaussians, "forward", "rasterize"), (PR, "reconstruction_loss_batch", "loss"),
                (RF.RasterizeGaussians, "backward", "rasterize backward"),
                (RO._SimulateFn, "backward", "sim backward"), (RO.Rollout, "run_backward", "run_backward"),
                (PR.FitProblem, "trajectory_prior", "traj prior"), (MAT.MaterialField, "smoothness", "smoothness"),
                (torch.Tensor, "backward", "backward"), (O, "clean_gradients", "clean grads"),
                (AW.AdamW, "step", "adam step"), (AW.AdamW, "zero_grad", "zero_grad")]:
            undo.append(rec.wrap(owner, attr, name))
        orig_cl = wp.capture_launch

        def cl(*aa, **kk):
            if not rec.active:
                return orig_cl(*aa, **kk)
            rec.stack.append("frame graph")
            rec.sync()
            t0 = time.perf_counter()
            try:
                return orig_cl(*aa, **kk)
            finally:
                rec.sync()
                rec.cur["time"][rec.key()] += time.perf_counter() - t0
                rec.stack.pop()
        wp.capture_launch = cl
        undo.append((wp, "capture_launch", orig_cl))
    mode_ctx = None
    if mode == "count":
        for owner, attr, name in [
                (MAT.MaterialField, "youngs", "material"), (MAT.MaterialField, "poisson", "material"),
                (SIM.Simulation, "simulate", "sim forward"), (RO.Rollout, "_inputs", "input checks"),
                (RO.Rollout, "_rest_prelude", "rest prelude"),
                (PR.FitProblem, "frames_rec", "render+loss"), (DF.GaussianBinding, "apply", "deform"),
                (RF.RasterizeGaussians, "forward", "rasterize"), (PR, "reconstruction_loss_batch", "loss"),
                (RF.RasterizeGaussians, "backward", "rasterize backward"),
                (RO._SimulateFn, "backward", "sim backward"),
                (PR.FitProblem, "trajectory_prior", "traj prior"), (MAT.MaterialField, "smoothness", "smoothness"),
                (torch.Tensor, "backward", "backward"), (O, "clean_gradients", "clean grads"),
                (AW.AdamW, "step", "adam step"), (AW.AdamW, "zero_grad", "zero_grad")]:
            undo.append(rec.wrap(owner, attr, name))

        def counted(owner, attr, what, site=False, name_of=None):
            fn = getattr(owner, attr)

            def w(*aa, **kk):
                if rec.active:
                    rec.add(what if name_of is None else f"{what}:{name_of(aa, kk)}")
                    if site:
                        rec.site(what)
                return fn(*aa, **kk)
            setattr(owner, attr, w)
            undo.append((owner, attr, fn))

        def kname(aa, kk):
            k = aa[0] if aa else kk.get("kernel")
            return getattr(k, "key", str(k)).replace("_build__locals__", "").split(".")[-1]
        counted(wp, "launch", "warp launch", name_of=kname)
        counted(wp, "launch_tiled", "warp launch", name_of=kname)
        counted(wp, "capture_launch", "graph launch")
        counted(wp, "copy", "warp copy")
        counted(wp.array, "zero_", "warp memset")
        counted(wp.array, "fill_", "warp memset")
        counted(wp, "empty", "warp alloc")
        counted(wp, "zeros", "warp alloc")
        counted(wp.utils, "radix_sort_pairs", "warp radix sort (several launches)")
        counted(wp.utils, "array_scan", "warp scan (several launches)")
        counted(wp.array, "numpy", "HOST READ warp .numpy()", site=True)
        counted(wp, "synchronize", "HOST READ wp.synchronize", site=True)
        counted(wp, "synchronize_device", "HOST READ wp.synchronize_device", site=True)
        counted(torch.Tensor, "cpu", "HOST READ tensor .cpu()", site=True)
        counted(torch.Tensor, "tolist", "HOST READ tensor .tolist()", site=True)
        counted(RO, "_torch_sync", "HOST READ torch.cuda.synchronize (rollout hand-over)", site=True)
        counted(RO, "_warp_sync", "HOST READ wp.synchronize_device (rollout hand-over)", site=True)
        from torch.utils._python_dispatch import TorchDispatchMode

        cpu_tensors: weakref.WeakSet = weakref.WeakSet()
        on_cpu = not rec.cuda

        class Count(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                out = func(*args, **(kwargs or {}))
                if rec.active:
                    name = func.__name__.split(".")[0]
                    if name == "_local_scalar_dense":
                        t = args[0]
                        dev = getattr(t, "device", None)
                        if on_cpu or (dev is not None and dev.type != "cpu"):
                            rec.add("HOST READ scalar (item/float/bool)")
                            rec.site("HOST READ scalar")
                    elif name in VIEW_OPS:
                        rec.add("torch view/metadata op")
                    else:
                        dev_args = [x for x in list(args) + list((kwargs or {}).values())
                                    if isinstance(x, torch.Tensor)]
                        host = bool(dev_args) and all(x.device.type == "cpu" for x in dev_args) and not on_cpu
                        rec.add("torch op (host tensors)" if host else "torch op")
                        rec.add(f"op:{name}")
                        rec.site(f"torch op {name}")
                return out
        mode_ctx = Count()
        del cpu_tensors

    try:
        d = Path(tempfile.mkdtemp(prefix="iter26_"))
        shutil.copytree(stage_dir, d, dirs_exist_ok=True)   # same depth: the stage's relative paths hold
        wp.synchronize()
        t0 = time.perf_counter()
        if mode_ctx is not None:
            with mode_ctx:
                out = api.fit(d / "scene.usda", iterations=iterations, contact_from=str(a.contact_from),
                              device=a.device, progress=True, log=lambda *x, **k: None)
        else:
            out = api.fit(d / "scene.usda", iterations=iterations, contact_from=str(a.contact_from),
                          device=a.device, progress=True, log=lambda *x, **k: None)
        wp.synchronize()
        wall = time.perf_counter() - t0
    finally:
        for owner, attr, fn in reversed(undo):
            setattr(owner, attr, fn)
    shutil.rmtree(d, ignore_errors=True)
    return {"mode": mode, "fit_wall_s": wall, "loss_history": [float(v) for v in out.result.loss_history],
            "final_loss": float(out.result.final_loss), "rec": rec}


def summarise(run: dict) -> dict:
    rec = run["rec"]
    its = rec.iters[1:]       # iteration 1 holds the captures
    res = {"mode": run["mode"], "fit_wall_s": round(run["fit_wall_s"], 3), "iterations": len(rec.iters),
           "final_loss": run["final_loss"]}
    if rec.iters:
        res["iteration_1_s"] = round(rec.iters[0]["wall"], 4)
    if its:
        walls = [r["wall"] for r in its]
        res["iteration_median_s"] = round(float(np.median(walls)), 5)
        res["iteration_walls_s"] = [round(w, 5) for w in walls]
        shapes = [r.get("shape") for r in its if r.get("shape")]
        if shapes:
            res["sim_shape"] = shapes[len(shapes) // 2]
            res["substeps_per_iteration"] = [r["shape"]["substeps"] for r in its if r.get("shape")]
        if run["mode"] == "timed":
            keys = sorted({k for r in its for k in r["time"]})
            res["phase_median_ms"] = {k: round(1e3 * float(np.median([r["time"].get(k, 0.0) for r in its])), 3)
                                      for k in keys}
            top = [k for k in keys if " > " not in k]
            sh = [r.get("shape") for r in its if r.get("shape")]
            if sh:
                n_sub = float(np.median([x["frames"] * x["substeps"] for x in sh]))
                for lab, root in (("forward", "sim forward"), ("backward (adjoint)", "backward")):
                    g = float(np.median([sum(v for k, v in r["time"].items() if k.startswith(root + " >")
                                             and k.endswith("frame graph")) for r in its]))
                    res[f"graph_us_per_substep_{lab.split()[0]}"] = round(1e6 * g / max(n_sub, 1), 2)
            res["phase_median_ms"]["(other: not in a phase)"] = round(
                1e3 * float(np.median([r["wall"] - sum(r["time"].get(k, 0.0) for k in top) for r in its])), 3)
        if run["mode"] == "count":
            # counts per iteration: the median over iterations 2.. (they are alike; the max shows where not)
            allk = collections.defaultdict(set)
            for r in its:
                for ph, c in r["count"].items():
                    allk[ph] |= set(c)
            counts = {}
            for ph in sorted(allk):
                counts[ph] = {w: float(np.median([r["count"].get(ph, {}).get(w, 0) for r in its])) for w in
                              sorted(allk[ph])}
            res["counts_median"] = counts
            tot = collections.Counter()
            for ph, c in counts.items():
                for w, v in c.items():
                    if not w.startswith("op:") and ":" in w:
                        tot[w.split(":")[0]] += v
                    elif not w.startswith("op:"):
                        tot[w] += v
            res["totals_median"] = dict(sorted(tot.items()))
            sites = collections.Counter()
            for r in its:
                sites.update(r["sites"])
            res["sites_per_iteration"] = {k: round(v / len(its), 2) for k, v in sites.most_common()}
    return res


def print_summary(s: dict, plain_median: float | None):
    print(f"\n## {s['mode']}: fit {s['fit_wall_s']:.2f} s wall, {s['iterations']} iterations, iteration 1 "
          f"{s.get('iteration_1_s')} s, iterations 2.. median {s.get('iteration_median_s')} s, final loss "
          f"{s['final_loss']!r}")
    if s.get("sim_shape"):
        print(f"simulation: {s['sim_shape']}; substeps per frame over iterations 2..: "
              f"{sorted(set(s['substeps_per_iteration']))}")
    if "phase_median_ms" in s:
        print("| phase (median over iterations 2..; nested ones inside their parent) | ms |\n|---|---:|")
        for k, v in s["phase_median_ms"].items():
            print(f"| {k} | {v:.2f} |")
        if "graph_us_per_substep_forward" in s:
            print(f"frame graphs: forward {s['graph_us_per_substep_forward']} us / substep, backward "
                  f"{s['graph_us_per_substep_backward']} us / substep (each graph launch synchronised)")
        if plain_median:
            print(f"(the plain fit's iteration median: {1e3 * plain_median:.1f} ms; the timed one's syncs add the "
                  f"difference)")
    if "totals_median" in s:
        print("| per iteration (median over iterations 2..) | count |\n|---|---:|")
        for k, v in s["totals_median"].items():
            print(f"| {k} | {v:g} |")
        print("| phase | what | count |\n|---|---|---:|")
        for ph, c in s["counts_median"].items():
            for w, v in c.items():
                if v and not w.startswith("op:"):
                    print(f"| {ph} | {w} | {v:g} |")
        print("host reads by call site (per iteration):")
        for k, v in s["sites_per_iteration"].items():
            if k.startswith("HOST READ"):
                print(f"  {v:g} x {k}")
        ops = collections.Counter()
        for k, v in s["sites_per_iteration"].items():
            if k.startswith("torch op"):
                ops[k] += v
        print("torch ops by call site (per iteration, top 40):")
        for k, v in ops.most_common(40):
            print(f"  {v:g} x {k}")


def profile(stage_dir: Path, a, n: int) -> dict:
    """N iterations under torch.profiler: the device's kernel time by kernel per iteration."""
    import torch
    from torch.profiler import ProfilerActivity, profile as tprof

    from physinteract_usd import api
    from physinteract_usd.app import fit_checkpoint as FC

    orig_call = FC.FitTracker.__call__
    state = {"i": 0, "prof": None, "t": []}
    cuda = str(a.device).startswith("cuda")
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])

    def sync():
        if cuda:
            torch.cuda.synchronize()

    def tracked(self, it, *aa, **kk):
        r = orig_call(self, it, *aa, **kk)
        state["i"] += 1
        if state["i"] == 2:
            sync()
            state["prof"] = tprof(activities=acts)
            state["prof"].__enter__()
            state["t"].append(time.perf_counter())
        elif state["i"] == 2 + n and state["prof"] is not None:
            sync()
            state["t"].append(time.perf_counter())
            state["prof"].__exit__(None, None, None)
        return r
    FC.FitTracker.__call__ = tracked
    d = Path(tempfile.mkdtemp(prefix="iter26p_"))
    shutil.copytree(stage_dir, d, dirs_exist_ok=True)   # same depth: the stage's relative paths hold
    try:
        api.fit(d / "scene.usda", iterations=max(a.iterations, n + 4), contact_from=str(a.contact_from),
                device=a.device, progress=True, log=lambda *x, **k: None)
    finally:
        FC.FitTracker.__call__ = orig_call
        shutil.rmtree(d, ignore_errors=True)
    p = state["prof"]
    if p is None or len(state["t"]) < 2:
        return {}
    wall = (state["t"][1] - state["t"][0]) / n
    kern = []
    for e in p.key_averages():     # the device's own events (kernels, memcpy / memset): device type CUDA
        if getattr(getattr(e, "device_type", None), "name", "") != "CUDA":
            continue
        dt = 0.0
        for attr in ("self_device_time_total", "device_time_total", "self_cuda_time_total", "cuda_time_total"):
            dt = float(getattr(e, attr, 0.0) or 0.0)
            if dt:
                break
        if dt:
            kern.append((e.key, dt / n / 1e3, e.count / n))
    busy = sum(ms for _, ms, _ in kern)
    kern.sort(key=lambda r: -r[1])
    print(f"\n## torch.profiler over {n} iterations: wall {1e3 * wall:.1f} ms / iteration, device kernel time "
          f"{busy:.1f} ms / iteration (sum over kernels; profiled)")
    print("| kernel | ms / iteration | launches / iteration |\n|---|---:|---:|")
    for k, ms, c in kern[:30]:
        print(f"| {k[:90]} | {ms:.3f} | {c:g} |")
    return {"wall_ms": 1e3 * wall, "device_ms": busy, "kernels": [[k, ms, c] for k, ms, c in kern[:60]]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--grid", type=int, default=24)
    ap.add_argument("--iterations", type=int, default=60, help="the plain fit's iterations (the CLI's)")
    ap.add_argument("--phase-iterations", type=int, default=12, help="the timed and count fits' iterations")
    ap.add_argument("--warm-iterations", type=int, default=2)
    ap.add_argument("--modes", default="plain,timed,count", help="which fits after the warm one, in order")
    ap.add_argument("--profile", type=int, default=0, help="also N iterations under torch.profiler (CUDA activity on a "
                                                          "GPU: the device's kernel time against the wall)")
    ap.add_argument("--contact-from", default=str(ROOT / "samples" / "foam_bar" / "gt"))
    ap.add_argument("--no-cuda-paths", action="store_true", help="on the CPU: keep the CPU's own code paths")
    ap.add_argument("--block-dims", default="", help="CUDA: also the plain fit at each of these solver block dims "
                                                      "(sim.solver.BLOCK_DIM; each after a warm fit that compiles "
                                                      "and loads its kernels' variant), e.g. 256,128,64,32")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    import warp as wp

    from physinteract_usd import api
    from physinteract_usd.fit import problem as PR
    from physinteract_usd.sim import rollout as RO
    from physinteract_usd.sim import solver as SO

    if not str(a.device).startswith("cuda") and not a.no_cuda_paths:
        SO.FUSED_ZERO = SO.FUSED_KERNELS = SO.GRID_BOX = True
        RO.FRAME_GRAPHS = True
        PR.BATCH_FRAMES = True
    tmp = Path(tempfile.mkdtemp(prefix="iter26_init_"))
    api.init(tmp / "scene.usda", ROOT / "samples" / "foam_bar", grid=a.grid, padding=0.3,
             youngs_range=(1e3, 6e4), max_poisson=0.4, density=150.0, log=lambda *x, **k: None)   # as scripts/demo.sh
    out = {"device": str(wp.get_device(a.device)), "grid": a.grid, "runs": []}
    try:
        import torch
        if str(a.device).startswith("cuda"):
            out["device_name"] = torch.cuda.get_device_name()
    except Exception:   # noqa: BLE001
        pass
    print(f"device {out.get('device_name', out['device'])}, grid {a.grid}")
    box: list = []
    if a.warm_iterations > 0:
        run_fit(tmp, a, "plain", a.warm_iterations, box)
    plain_median = None
    for m in [x.strip() for x in a.modes.split(",") if x.strip()]:
        n = a.iterations if m == "plain" else a.phase_iterations
        r = run_fit(tmp, a, m, n, box)
        s = summarise(r)
        s["loss_history"] = r["loss_history"]
        if m == "plain":
            plain_median = s.get("iteration_median_s")
        print_summary(s, plain_median)
        out["runs"].append(s)
    hist = [tuple(r["loss_history"][:a.phase_iterations]) for r in out["runs"]]
    print(f"\nloss histories equal across the fits (first {a.phase_iterations}): {len(set(hist)) == 1}")
    dims = [int(x) for x in a.block_dims.split(",") if x.strip()]
    if dims:
        sweep = []
        for bd in dims:
            SO.BLOCK_DIM = bd
            t0 = time.perf_counter()
            run_fit(tmp, a, "plain", a.warm_iterations or 1, box)     # the variant's modules: compiled / loaded
            warm = time.perf_counter() - t0
            s = summarise(run_fit(tmp, a, "plain", a.iterations, box))
            row = {"block_dim": bd, "warm_fit_s": round(warm, 2), "fit_wall_s": s["fit_wall_s"],
                   "iterations": s["iterations"], "iteration_median_s": s.get("iteration_median_s"),
                   "final_loss": s["final_loss"], "substeps": sorted(set(s.get("substeps_per_iteration", [])))}
            sweep.append(row)
            print(f"block_dim {bd}: {row}")
        SO.BLOCK_DIM = None
        print("\n| solver block_dim | fit s (in-process) | iterations | iteration median ms | final loss |")
        print("|---:|---:|---:|---:|---|")
        for r in sweep:
            print(f"| {r['block_dim']} | {r['fit_wall_s']:.2f} | {r['iterations']} | "
                  f"{1e3 * (r['iteration_median_s'] or 0):.1f} | {r['final_loss']:.6g} |")
        out["block_dims"] = sweep
    if a.profile:
        out["profile"] = profile(tmp, a, a.profile)
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(out, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
