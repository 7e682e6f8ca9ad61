"""The fit's start search (fit/optimize.py `golden_uniform_search`: 7 uniform-E probes) on the README demo's
problem on one thread and on two (simulation.py SIM_THREADS: the first two probes at once, then each probe
with the one most likely to follow it, fit/search.py), wall and process CPU seconds per round, alternating,
a fresh problem each round (as in a fit: every rung's rollout new), and whether the two searches' probes,
values and answer are the same (docs/benchmarks/cpu.md, #26).

    python benchmarks/cpu_probe_threads.py [--stage DIR] [--rounds 3] [--evals 7] [--json F]

The stage is cpu_sim_demo.py's (built there when missing). Wall time is what the second core buys: run it
on an otherwise idle machine (on a loaded one both threads wait for cores).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", default=str(ROOT / "out" / "cpu_sim_demo"))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--evals", type=int, default=7, help="the search's probes (the demo's search_evals: 7)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from cpu_sim_demo import build_stage
    stage = build_stage(Path(args.stage), ROOT)
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from physinteract_usd import simulation
    from physinteract_usd.app import fit as app_fit
    from physinteract_usd.fit.material import MaterialField
    from physinteract_usd.fit.optimize import golden_uniform_search

    job = app_fit.prepare_fit(stage, log=lambda *a, **k: None, progress=False)

    def search(n):
        simulation.SIM_THREADS = n
        prob = app_fit.make_problem(job)
        st = prob.scene.settings
        mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                            device=prob.tdev)
        mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        lines, seen = [], {}
        w0, c0 = time.perf_counter(), time.process_time()
        e, loss = golden_uniform_search(prob, mat, args.evals, lines.append, with_loss=True, seen=seen)
        return time.perf_counter() - w0, time.process_time() - c0, (e, loss, seen), lines

    search(1)        # warm-up: module loads
    rows = {1: [], 2: []}
    answers, notes = {}, {}
    for _ in range(args.rounds):
        for n in (1, 2):
            w, c, ans, lines = search(n)
            rows[n].append((w, c))
            answers.setdefault(n, ans)
            assert answers[n] == ans
            notes[n] = [ln for ln in lines if ln.startswith("start search on two threads")]
    same = answers[1] == answers[2]
    print(f"P {len(job.scene.particles_positions)}, evals {args.evals}, "
          f"rounds {args.rounds}; E {answers[1][0]:.5g} Pa, loss {answers[1][1]:.6f}")
    print("| threads | wall s (median, min) | CPU s (median, min) |\n|---|---:|---:|")
    out = {}
    for n, rr in rows.items():
        w, c = np.array(rr).T
        out[n] = {"wall": w.tolist(), "cpu": c.tolist()}
        print(f"| {n} | {np.median(w):.2f}, {w.min():.2f} | {np.median(c):.2f}, {c.min():.2f} |")
    print(f"same probes, values and answer: {same}; {notes[2][0] if notes[2] else ''}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": out, "same": same, "note": notes[2]}, indent=1))
    if not same:
        sys.exit(1)


if __name__ == "__main__":
    main()
