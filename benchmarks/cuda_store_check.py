"""CUDA-only check of the rollout's backward paths (no CPU Warp needed, unlike check_sim_cuda.py):
stored substep states (sim/rollout.py STORE_STATES_BYTES) vs replaying them, each with and without
captured graphs, on bench_sim's scene (2k particles, 32^3, 3 frames x 20 substeps, float32). The
second call of each rollout replays its captured graphs. Prints the largest position and gradient
differences against the eager replay path and PASS when the gradients agree within 1e-5 (relative
to the largest).

    python3 benchmarks/cuda_store_check.py
"""

import os
import sys

import torch
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, ".."))
from bench_sim import make_scene  # noqa: E402

import physinteract_usd.sim.rollout as R  # noqa: E402
from physinteract_usd.sim import Rollout  # noqa: E402

wp.config.quiet = True


def main():
    out = {}
    m, ctrl = make_scene(2000, 32, 3, 20, "cuda:0")
    fb = Rollout(m, ctrl)._frame_bytes()
    # every frame stored, one of three (the others replayed: a budget of two frames' states, one of
    # them the replay buffer), none
    for store in (1 << 40, 2 * fb, 0):
        R.STORE_STATES_BYTES = store
        for graphs in (True, False):
            ro = Rollout(m, ctrl, graphs=graphs)
            for _ in range(2):          # the second call replays the captured graphs
                E = torch.full((m.n_particles,), 1e4, device="cuda:0", requires_grad=True)
                x, F = ro(E)
                (x[-1, :, 1].sum() + 0.1 * F[-1].sum()).backward()
            out[(store, graphs)] = (x.detach().clone(), E.grad.clone())
    ref = out[(0, False)]
    ok = True
    for k, (x, g) in out.items():
        dx = float((x - ref[0]).abs().max())
        dg = float((g - ref[1]).abs().max() / ref[1].abs().max())
        ok &= dg < 1e-5
        print(f"stored={ {1 << 40: 'all', 0: 'none'}.get(k[0], '1 of 3 frames') } graphs={k[1]}: max |x - x_ref| {dx:.3g}, max grad diff / max grad {dg:.3g}")
    print("RESULT:", "PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
