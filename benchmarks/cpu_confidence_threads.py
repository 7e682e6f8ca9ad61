"""The confidence's finite differences (fit/optimize.py `confidence(method="fd")`: 1 + K forwards) on the
README demo's problem, on one thread and on two (simulation.py SIM_THREADS), wall and process CPU seconds
per round, alternating, and whether the diagonals are bitwise equal (docs/benchmarks/cpu.md, #26).

    python benchmarks/cpu_confidence_threads.py [--stage DIR] [--rounds 3] [--K 8] [--E 2.5e4] [--fresh]

--fresh: a new problem for every estimate, as in a fit (the rung's rollout new: its first forward eager, its
graphs captured inside the estimate); without it one problem, warmed up (graphs captured before the timing).

The stage is cpu_sim_demo.py's (built there when missing). Wall time is what the second core buys: run it
on an otherwise idle machine (on a loaded one both threads wait for cores).
"""

from __future__ import annotations

import argparse
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
    ap.add_argument("--K", type=int, default=8, help="basis functions (the demo's level 2: 8)")
    ap.add_argument("--E", type=float, default=2.5e4)
    ap.add_argument("--fresh", action="store_true")
    args = ap.parse_args()
    from cpu_sim_demo import build_stage
    stage = build_stage(Path(args.stage), ROOT)
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from physinteract_usd import simulation
    from physinteract_usd.app import fit as app_fit
    from physinteract_usd.fit.material import MaterialField
    from physinteract_usd.fit.optimize import confidence

    job = app_fit.prepare_fit(stage, log=lambda *a, **k: None, progress=False)

    def problem():
        prob = app_fit.make_problem(job)
        st = prob.scene.settings
        mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                            device=prob.tdev)
        mat.set_uniform(args.E, 0.3)
        mat.refine(args.K)
        with torch.no_grad():
            mat.theta += torch.linspace(-0.2, 0.2, mat.K, dtype=mat.theta.dtype)
        return prob, mat

    prob, mat = problem()
    rows = {1: [], 2: []}
    diags = {}
    confidence(prob, mat, [], probes=4, method="fd")          # warm-up: module loads, graph capture
    for r in range(args.rounds):
        for n in (1, 2):
            simulation.SIM_THREADS = n
            if args.fresh:
                prob, mat = problem()
            w0, c0 = time.perf_counter(), time.process_time()
            _, d, used = confidence(prob, mat, [], probes=4, method="fd", return_diag=True)
            rows[n].append((time.perf_counter() - w0, time.process_time() - c0))
            assert used == "fd"
            if n in diags:
                assert np.array_equal(diags[n], d)
            diags[n] = d
    print(f"P {len(prob.x0)}, substeps/frame {prob.sim.substeps}, K {mat.K}, rounds {args.rounds}"
          f"{', a fresh problem each' if args.fresh else ''}")
    print("| threads | wall s (median, min) | CPU s (median, min) |\n|---|---:|---:|")
    for n, rr in rows.items():
        w, c = np.array(rr).T
        print(f"| {n} | {np.median(w):.2f}, {w.min():.2f} | {np.median(c):.2f}, {c.min():.2f} |")
    print(f"diagonals bitwise equal: {bool(np.array_equal(diags[1], diags[2]))}")


if __name__ == "__main__":
    main()
