"""The fit's interaction check's counterfactuals on the README demo's problem, in process CPU and wall seconds
(docs/benchmarks/cpu.md, #26): the release shifted one frame either way and the contact moved four ways, as the
demo's check runs them (`fit.interaction_check.confirm`), timed three ways in alternating rounds:

- `before`: every variant a whole forward of its own twin, the model as fitted simulated once per suspect
  (the code before #26's change: 8 eager forwards on the demo);
- `after`: the model as fitted simulated once for both suspects, a shifted release simulated only from the
  earlier of its two frames on (`Counterfactuals`, `Simulation.simulate_from`);
- `after, 2 threads`: the same with `simulation.SIM_THREADS` = 2 (the variants' forwards on two threads).

Every way's losses must be equal (asserted); the table gives the median CPU and wall seconds per way.

    python benchmarks/cpu_interaction_check.py [--stage DIR] [--rounds 3] [--json F]

--stage: a demo stage with its contacts extracted (default: built into out/cpu_interaction_check as
benchmarks/cpu_sim_demo.py builds its own). The fit it checks is a 1-iteration fit of that stage (the check's
cost does not depend on how good the fit is).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def before(prob, result, c):
    """The check's counterfactuals as they ran before #26: each suspect's variants, its own reference
    among them, each a whole forward of its own twin."""
    import torch

    from physinteract_usd.contacts import moved_contact
    from physinteract_usd.fit.interaction_check import _fitted_inputs

    E, nu, tr, names, eff = _fitted_inputs(prob, result)

    def losses(variants):
        out = {}
        for key, (cs, offsets) in variants.items():
            trk = None if tr is None else [t + torch.as_tensor(np.asarray(offsets.get(n, np.zeros(3))), dtype=t.dtype)
                                           for n, t in zip(names, tr)]
            sim = prob.sim.forward_twin(cs)
            with torch.no_grad():
                x, F = sim.simulate(E, nu, trk, effects=eff)
                out[key] = float(prob.loss(E, nu, trk, effects=eff, simulated=(x, F))["rec"])
        return out

    r = int(c.release_frame)
    shifted = losses({d: ([dataclasses.replace(x, release_frame=r + d) if x.name == c.name else x
                           for x in prob.contacts], {}) for d in (0, -1, 1)})
    x0 = np.asarray(prob.x0.detach().cpu().numpy() if hasattr(prob.x0, "detach") else prob.x0, float)
    w2c = prob.cameras[0].w2c_cv()[:3, :3]
    d = 2.0 * float(prob.scene.settings.particle_spacing)
    variants = {"0": (list(prob.contacts), {})}
    for lab, axis in (("right", w2c[0]), ("up", -w2c[1])):
        v = axis / max(np.linalg.norm(axis), 1e-12)
        for sgn in (1, -1):
            off = sgn * d * v
            nc = moved_contact(c, off, x0, prob.contacts)
            variants[f"{lab}{'+' if sgn > 0 else '-'}"] = ([nc if x.name == c.name else x for x in prob.contacts],
                                                          {c.name: off})
    return shifted, losses(variants)


def after(prob, result, c):
    from physinteract_usd.fit.interaction_check import Counterfactuals, moved_losses, shifted_losses

    cf = Counterfactuals(prob, result)
    return shifted_losses(prob, result, c, "release_frame", cf=cf), moved_losses(prob, result, c, cf=cf)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", default=str(ROOT / "out" / "cpu_interaction_check"))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from cpu_sim_demo import build_stage

    stage = build_stage(Path(args.stage), ROOT)
    import torch

    torch.set_num_threads(1)
    from physinteract_usd import simulation as simulation_mod
    from physinteract_usd.app.fit import prepare_fit, run_fit

    job = prepare_fit(stage, iterations=1, log=lambda *a, **k: None, progress=False,
                      settings_overrides={"confidence_probes": 0})
    result = run_fit(job, progress=False, log=lambda *a, **k: None)
    prob = job.problem
    c = [c for c in job.contacts if c.type != "fixed"][0]
    print(f"demo problem: {len(prob.x0)} particles, {prob.T} frames, {prob.sim.substeps} substeps per frame; "
          f"contact {c.name}: grasp {c.grasp_frame}, release {c.release_frame}")
    ways = {"before": (before, 1), "after": (after, 1), "after, 2 threads": (after, 2)}
    times = {w: [] for w in ways}
    ref = None
    for r in range(args.rounds):
        for w, (fn, threads) in ways.items():
            simulation_mod.SIM_THREADS = threads
            c0, w0 = time.process_time(), time.perf_counter()
            got = fn(prob, result, c)
            times[w].append((time.process_time() - c0, time.perf_counter() - w0))
            if ref is None:
                ref = got
                print("losses:", got)
            assert got == ref, (w, got, ref)
    print("| way | CPU s (median) | wall s (median) | rounds |\n|---|---:|---:|---:|")
    out = {}
    for w, ts in times.items():
        cpu, wall = np.median([t[0] for t in ts]), np.median([t[1] for t in ts])
        out[w] = {"cpu": float(cpu), "wall": float(wall), "rounds": ts}
        print(f"| {w} | {cpu:.2f} | {wall:.2f} | {len(ts)} |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
