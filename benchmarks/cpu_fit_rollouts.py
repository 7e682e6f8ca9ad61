"""A whole fit (`api.fit`, no profiler around it) with a count of its rollouts: per rollout its substeps, forwards,
backwards, graph sets captured and the seconds those captures took, and the fit's wall time (docs/benchmarks/cpu.md
the 18th session: what the simulator's two lanes pay at capture against what they save per pass).

    python benchmarks/cpu_fit_rollouts.py STAGE [--iterations N]        (PHYSINTERACT_SIM_LANES=1 / 2 to compare)

STAGE: a stage `init` made (e.g. demo.sh's init into a scratch folder); the fit writes a version into it.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stage")
    ap.add_argument("--iterations", type=int, default=None)
    args = ap.parse_args()
    from physinteract_usd import api
    from physinteract_usd.sim import rollout as R

    stats = defaultdict(lambda: {"substeps": 0, "forwards": 0, "backwards": 0, "graph_sets": 0, "capture_s": 0.0})
    ensure, fwd, bwd = R.Rollout._ensure_graphs, R.Rollout.run_forward, R.Rollout.run_backward

    def ensure_counted(self, graphs, fn):
        n0, w0 = len(graphs), time.perf_counter()
        out = ensure(self, graphs, fn)
        if len(graphs) > n0:
            st = stats[id(self)]
            st["graph_sets"] += 1
            st["capture_s"] += time.perf_counter() - w0
        return out

    def fwd_counted(self, store=False, start=0):
        st = stats[id(self)]
        st["substeps"], st["forwards"] = self.S, st["forwards"] + 1
        return fwd(self, store, start)

    def bwd_counted(self, generation=None):
        stats[id(self)]["backwards"] += 1
        return bwd(self, generation)

    R.Rollout._ensure_graphs, R.Rollout.run_forward, R.Rollout.run_backward = ensure_counted, fwd_counted, bwd_counted
    t0, c0 = time.perf_counter(), time.process_time()
    out = api.fit(Path(args.stage), iterations=args.iterations, progress=False, log=lambda *a, **k: None)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    lanes = os.environ.get("PHYSINTERACT_SIM_LANES", "default")
    print(f"fit {wall:.1f} s wall, {cpu:.1f} s CPU, loss {out.result.final_loss:.6g}, lanes {lanes}, "
          f"{len(stats)} rollouts, load average {os.getloadavg()[0]:.2f}")
    print("| substeps | forwards | backwards | graph sets captured | capture s |\n|---:|---:|---:|---:|---:|")
    for st in sorted(stats.values(), key=lambda s: -s["forwards"]):
        print(f"| {st['substeps']} | {st['forwards']} | {st['backwards']} | {st['graph_sets']} | {st['capture_s']:.1f} |")


if __name__ == "__main__":
    main()
