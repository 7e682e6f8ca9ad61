"""What a fresh machine pays to compile the demo's Warp modules on the CPU (issue #26,
docs/benchmarks/cpu.md): each module built alone into an empty kernel cache, CPU and wall seconds.

    python benchmarks/cpu_warp_compile.py [--rounds N] [--workers K] [--modules sim,render,frames,...]

Each round runs in a fresh subprocess with its own empty WARP_CACHE_PATH (so the precompiled
headers are built too, as on a fresh machine / in CI), builds the kernel namespaces the demo's fit
uses (sim float32: `sim` the substep's module, `sim_adj` the hand-written adjoints; render f32;
the others only when --modules names them) and times
`wp.force_load` of each module, one after another (`--workers 0`), or all together on K threads
(`--workers K`: Warp 1.19 compiles modules unlocked, so K threads use K cores). Prints one table;
`--json FILE` writes the rows.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

NAMES = {   # name -> (Python module, builder, its argument, the Warp module's name: a suffix or "")
    "sim": ("physinteract_usd.sim.kernels", "get_kernels", "float32", "core"),
    "sim_adj": ("physinteract_usd.sim.kernels", "get_kernels", "float32", "adj"),
    "sim_rate": ("physinteract_usd.sim.kernels", "get_kernels", "float32", "rate"),
    "sim_cuda": ("physinteract_usd.sim.kernels", "get_kernels", "float32", "cuda"),
    "sim64": ("physinteract_usd.sim.kernels", "get_kernels", "float64", "core"),
    "sim64_adj": ("physinteract_usd.sim.kernels", "get_kernels", "float64", "adj"),
    "render": ("physinteract_usd.render.rasterizer", "kernels", "wp.float32", ""),
    "render64": ("physinteract_usd.render.rasterizer", "kernels", "wp.float64", ""),
    "frames": ("physinteract_usd.sim.frame_graphs", "get_frame_kernels", "float32", ""),
}


def child(mods: list[str], workers: int) -> dict:
    import importlib

    t0, c0 = time.perf_counter(), time.process_time()
    import physinteract_usd  # noqa: F401
    import warp as wp

    from physinteract_usd import devices
    devices.quiet_warp_init("cpu")
    out = {"import_wall": time.perf_counter() - t0, "import_cpu": time.process_time() - c0}
    modules = []
    for m in mods:
        path, fn, arg, which = NAMES[m]
        mod = importlib.import_module(path)
        k = getattr(mod, fn)(wp.float32 if arg == "wp.float32" else wp.float64 if arg == "wp.float64" else arg)
        if which and hasattr(k, "modules"):
            modules.append((m, wp.get_module(getattr(k.modules, which))))
        else:   # before the split (one sim module) or a module of its own
            kern = next(v for v in vars(k).values() if isinstance(v, wp.Kernel))
            modules.append((m, kern.module))
    if workers:
        w0, c0 = time.perf_counter(), time.process_time()
        wp.force_load(device="cpu", modules=[m for _, m in modules], max_workers=workers)
        out["all_wall"], out["all_cpu"] = time.perf_counter() - w0, time.process_time() - c0
    else:
        for name, m in modules:
            w0, c0 = time.perf_counter(), time.process_time()
            wp.force_load(device="cpu", modules=[m], max_workers=0)
            out[f"{name}_wall"], out[f"{name}_cpu"] = time.perf_counter() - w0, time.process_time() - c0
        out["all_wall"] = sum(out[f"{n}_wall"] for n, _ in modules)
        out["all_cpu"] = sum(out[f"{n}_cpu"] for n, _ in modules)
    return out


def main():
    argv = sys.argv[1:]
    if argv and argv[0] == "child":
        print("ROW " + json.dumps(child(argv[1].split(","), int(argv[2]))))
        return 0
    rounds, workers, mods, jpath = 2, 0, ["sim", "sim_adj", "render"], None
    while argv:
        a = argv.pop(0)
        if a == "--rounds":
            rounds = int(argv.pop(0))
        elif a == "--workers":
            workers = int(argv.pop(0))
        elif a == "--modules":
            mods = argv.pop(0).split(",")
        elif a == "--json":
            jpath = argv.pop(0)
        else:
            raise SystemExit(f"unknown argument {a}")
    rows = []
    for _ in range(rounds):
        with tempfile.TemporaryDirectory(prefix="warp_cold_") as cache:
            env = dict(os.environ, WARP_CACHE_PATH=cache)
            p = subprocess.run([sys.executable, __file__, "child", ",".join(mods), str(workers)],
                               env=env, capture_output=True, text=True)
            line = [ln for ln in p.stdout.splitlines() if ln.startswith("ROW ")]
            if p.returncode or not line:
                raise SystemExit(p.stdout[-2000:] + p.stderr[-2000:])
            rows.append(json.loads(line[0][4:]))
    keys = list(rows[0])
    print(f"{'(median of %d, fresh cache each; workers %d)' % (rounds, workers):44s} {'wall s':>8s} {'cpu s':>8s}")
    for k in [k[:-5] for k in keys if k.endswith("_wall")]:
        w = statistics.median(r[k + "_wall"] for r in rows)
        c = statistics.median(r[k + "_cpu"] for r in rows)
        print(f"{k:44s} {w:8.2f} {c:8.2f}")
    if jpath:
        with open(jpath, "w") as f:
            json.dump({"modules": mods, "workers": workers, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
