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
replays only the per-frame ones)."""

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
    a = ap.parse_args(argv)

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


if __name__ == "__main__":
    sys.exit(main())
