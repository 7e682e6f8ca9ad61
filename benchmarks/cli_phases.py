"""Where the CLI's fit spends its time, by phase (issue #26: "the GPU small fit in seconds").

Runs the `fit` verb in-process through `physinteract_usd.cli.main([...])` (the CLI's own path, less
the interpreter's start and its `os._exit`) on a fresh copy of a stage, `--repeats` times in one
process, and times each phase in wall clock and process CPU (all threads):

    import cli        `import physinteract_usd.cli` (the package, pxr, the verbs' parsers)
    import fit        `api.fit`'s module: torch, Warp, the fit's modules (the first run only)
    prepare           app.fit.prepare_fit: the stage, frames, masks, contacts, the cost check
    problem           app.fit.make_problem: FitProblem (the simulation, its kernels, the renderer's
                      inputs; on a GPU the first CUDA work: contexts, module loads)
    optimise          the optimiser, split into
      search            the uniform-E start search (optimize.golden_uniform_search)
      iteration 1       from the search's end to the first iteration's callback
      iterations 2..    the rest of the loop (median per iteration in the JSON)
      confidence        the confidence estimate (optimize.confidence)
      (graphs)          of which in Rollout._ensure_graphs: the frame graphs' warm-up and capture
    interaction       app.fit.interaction_notes (the residual's check)
    write             usd.fit_io.write_fit_layer (the new version)
    other             the rest of cli.main (argument parsing, device check, the summary)

The first run is what a CLI process pays after its interpreter starts; a later run in the same
process is the "in-process" fit (modules imported, Warp modules loaded, graph bodies warm). Also
printed: how many modules the run imported and whether torch._dynamo is among them.

    python benchmarks/cli_phases.py --stage-dir DIR --contact-from samples/foam_bar/gt --iterations 60 \\
        --device cuda --repeats 2 --json OUT/phases.json

DIR holds scene.usda and its layers (as `init` wrote them); each run fits a fresh copy of it.
CPU timings on the 2-core dev VM are shared with other work: compare process CPU there, not wall.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Clock:
    def __init__(self):
        self.t = {}          # phase -> [wall, cpu]
        self.marks = []      # (label, wall) iteration callbacks

    def add(self, name, wall, cpu):
        w = self.t.setdefault(name, [0.0, 0.0])
        w[0] += wall
        w[1] += cpu

    def wrap(self, owner, attr, name):
        fn = getattr(owner, attr)
        clock = self

        def timed(*a, **k):
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                clock.add(name, time.perf_counter() - w0, time.process_time() - c0)

        timed.__wrapped__ = fn
        setattr(owner, attr, timed)
        return fn


def _stage_in(d: Path) -> Path:
    for name in ("scene.usda", "s.usda"):
        if (d / name).exists():
            return d / name
    found = sorted(d.glob("*.usda"))
    if not found:
        raise SystemExit(f"{d}: no .usda stage here")
    return found[0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stage-dir", required=True, help="a folder with the stage init wrote (copied per run)")
    ap.add_argument("--contact-from", default="samples/foam_bar/gt")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=2, help="fits in this process (the first pays the imports)")
    ap.add_argument("--json", default=None, help="write the runs here")
    ap.add_argument("--profile-problem", action="store_true",
                    help="cProfile the first run's FitProblem build (its phase time then includes the profiler's "
                         "overhead) and print its top functions")
    a = ap.parse_args(argv)
    src = Path(a.stage_dir)
    stage_name = _stage_in(src).name

    w0, c0 = time.perf_counter(), time.process_time()
    n0 = len(sys.modules)
    import physinteract_usd.cli as cli
    imp_cli = (time.perf_counter() - w0, time.process_time() - c0)
    w0, c0 = time.perf_counter(), time.process_time()
    from physinteract_usd import api

    api.fit     # noqa: B018  (loads app.fit: torch, Warp, the fit's modules)
    imp_fit = (time.perf_counter() - w0, time.process_time() - c0)

    import physinteract_usd.app.fit as AF
    import physinteract_usd.fit.optimize as O
    from physinteract_usd.app.fit_checkpoint import FitTracker
    from physinteract_usd.sim.rollout import Rollout

    runs = []
    for r in range(a.repeats):
        ck = Clock()
        ck.wrap(AF, "prepare_fit", "prepare")
        if a.profile_problem and r == 0:
            import cProfile
            import io
            import pstats

            plain_make = AF.make_problem
            prof = cProfile.Profile()

            def profiled_make(*aa, **kk):
                prof.enable()
                try:
                    return plain_make(*aa, **kk)
                finally:
                    prof.disable()

            AF.make_problem = profiled_make
        ck.wrap(AF, "make_problem", "problem")
        ck.wrap(AF, "optimise", "optimise")
        ck.wrap(AF, "interaction_notes", "interaction")
        ck.wrap(AF, "write_fit_layer", "write")
        ck.wrap(O, "golden_uniform_search", "search")
        ck.wrap(O, "confidence", "confidence")
        ck.wrap(Rollout, "_ensure_graphs", "graphs")
        search_end = []
        orig_search = O.golden_uniform_search

        def search_marked(*aa, **kk):
            try:
                return orig_search(*aa, **kk)
            finally:
                search_end.append(time.perf_counter())

        O.golden_uniform_search = search_marked
        orig_call = FitTracker.__call__

        def tracked(self, *aa, **kk):
            ck.marks.append(time.perf_counter())
            return orig_call(self, *aa, **kk)

        FitTracker.__call__ = tracked
        work = Path(tempfile.mkdtemp(prefix="cli_phases_"))
        d = work / "stage"
        shutil.copytree(src, d)
        for stale in list(d.glob("*.versions")) + list(d.glob("*.report")):
            shutil.rmtree(stale, ignore_errors=True)
        argv_fit = ["fit", str(d / stage_name), "--contact-from", a.contact_from, "--iterations", str(a.iterations),
                    "--device", a.device]
        m_before = set(sys.modules)
        w0, c0 = time.perf_counter(), time.process_time()
        code = cli.main(argv_fit)
        main_w, main_c = time.perf_counter() - w0, time.process_time() - c0
        new_mods = set(sys.modules) - m_before
        # undo the wrappers (the next run wraps afresh)
        FitTracker.__call__ = orig_call
        O.golden_uniform_search = orig_search
        for owner, attr in ((AF, "prepare_fit"), (AF, "make_problem"), (AF, "optimise"), (AF, "interaction_notes"),
                            (AF, "write_fit_layer"), (O, "golden_uniform_search"), (O, "confidence"),
                            (Rollout, "_ensure_graphs")):
            f = getattr(owner, attr)
            while hasattr(f, "__wrapped__") and getattr(f, "__name__", "") == "timed":
                f = f.__wrapped__
            setattr(owner, attr, f)
        if a.profile_problem and r == 0:
            AF.make_problem = plain_make
            buf = io.StringIO()
            pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(35)
            print("FitProblem build, profiled (first run):")
            print("\n".join(ln for ln in buf.getvalue().splitlines() if ln.strip())[:8000])
        shutil.rmtree(work, ignore_errors=True)
        t = {k: {"wall_s": round(v[0], 3), "cpu_s": round(v[1], 3)} for k, v in ck.t.items()}
        marks = ck.marks
        it1 = its = None
        if marks and search_end:
            it1 = marks[0] - search_end[0]
            gaps = [b - b0 for b0, b in zip(marks, marks[1:])]
            its = {"n": len(gaps), "total_s": round(sum(gaps), 3),
                   "median_s": round(sorted(gaps)[len(gaps) // 2], 4) if gaps else None}
        top = sum(ck.t.get(k, [0, 0])[0] for k in ("prepare", "problem", "optimise", "interaction", "write"))
        run = {"repeat": r + 1, "exit": code, "main_wall_s": round(main_w, 3), "main_cpu_s": round(main_c, 3),
               "phases": t, "iteration_1_wall_s": None if it1 is None else round(it1, 3), "iterations_2_on": its,
               "other_wall_s": round(main_w - top, 3), "modules_imported": len(new_mods),
               "torch_dynamo_loaded": "torch._dynamo" in sys.modules,
               "unused_heavy_loaded": sorted(m for m in ("torch._dynamo", "sympy", "matplotlib", "trimesh", "triton")
                                             if m in sys.modules)}
        if r == 0:
            run["import_cli"] = {"wall_s": round(imp_cli[0], 3), "cpu_s": round(imp_cli[1], 3)}
            run["import_fit"] = {"wall_s": round(imp_fit[0], 3), "cpu_s": round(imp_fit[1], 3)}
            run["modules_imported"] += len(sys.modules) - n0 - len(new_mods)
        runs.append(run)

    rows = [("import cli", "import_cli"), ("import fit", "import_fit"), ("prepare", "prepare"), ("problem", "problem"),
            ("optimise", "optimise"), ("  search", "search"), ("  iteration 1", None), ("  iterations 2..", None),
            ("  confidence", "confidence"), ("  (graphs)", "graphs"), ("interaction", "interaction"),
            ("write", "write"), ("other", None)]
    head = "| phase | " + " | ".join(f"run {r['repeat']} wall s | cpu s" for r in runs) + " |"
    print(f"device {a.device}, {a.iterations} iterations, stage {src}")
    print(head)
    print("|---|" + "---:|---:|" * len(runs))
    for label, key in rows:
        cells = []
        for r in runs:
            if key in ("import_cli", "import_fit"):
                v = r.get(key)
                cells += [f"{v['wall_s']:.2f}", f"{v['cpu_s']:.2f}"] if v else ["-", "-"]
            elif key is not None:
                v = r["phases"].get(key)
                cells += [f"{v['wall_s']:.2f}", f"{v['cpu_s']:.2f}"] if v else ["-", "-"]
            elif label.strip() == "iteration 1":
                cells += [f"{r['iteration_1_wall_s']:.2f}" if r["iteration_1_wall_s"] is not None else "-", ""]
            elif label.strip() == "iterations 2..":
                it = r["iterations_2_on"]
                cells += [f"{it['total_s']:.2f} ({it['n']} x {it['median_s']})" if it else "-", ""]
            else:
                cells += [f"{r['other_wall_s']:.2f}", ""]
        print(f"| {label} | " + " | ".join(cells) + " |")
    tot = " | ".join(f"{r['main_wall_s'] + (r['import_cli']['wall_s'] + r['import_fit']['wall_s'] if 'import_cli' in r else 0):.2f} | "
                     f"{r['main_cpu_s'] + (r['import_cli']['cpu_s'] + r['import_fit']['cpu_s'] if 'import_cli' in r else 0):.2f}"
                     for r in runs)
    print(f"| **total** | {tot} |")
    print("modules imported per run:", [r["modules_imported"] for r in runs],
          "torch._dynamo loaded:", runs[-1]["torch_dynamo_loaded"], "of torch._dynamo, sympy, matplotlib, trimesh, "
          "triton loaded:", runs[-1]["unused_heavy_loaded"], "exit:", [r["exit"] for r in runs])
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"device": a.device, "iterations": a.iterations, "runs": runs}, indent=1))
    return 0 if all(r["exit"] == 0 for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
