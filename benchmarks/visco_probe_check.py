"""Why `diagnose` never names a hidden viscoelasticity on foam_bar (issue #22): is the candidate probed,
how much of the loss can any Maxwell probe explain, and how much of the hidden effect did the base fit
leave in the residual at all. **Development data** (a synth capture with a known hidden Maxwell branch).

For a fitted stage (the base model, no effects) whose capture's gt.json names a hidden viscoelasticity:
1. the diagnosis's loss of the base (the residual `diagnose` scores) and, with `--control STAGE` (the same
   scene, noise seed and fit with nothing hidden), the control's: the excess is what the hidden effect left
   in the residual after the base fit absorbed what it could (E field, nu, the path);
2. the viscoelasticity candidate's score test as `diagnose` runs it (its 4 probes + the refined secant):
   p-value and predicted share of the loss;
3. the same test on single probes over a grid of (tau, E_v) around the truth, the truth's own (E_v, tau)
   among them (an oracle: the best any probe of this model could do), each as the Gauss-Newton share and
   as the share when taken whole (the base re-adjusted linearly; negative: the whole branch raises the loss).
Prints a table and writes JSON (`--out`, and `$OUT/visco_probe_check.json` when `$OUT` is set).

CPU (foam_bar small, 16 frames, fit grid 16: ~1,600 particles): ~30 forwards, ~10-20 min on a busy 2-core box.
GPU: the same with `--device cuda` on the GPU's own stages (`diagnose_floor_rule.py`'s work/ folder):

    python benchmarks/visco_probe_check.py /tmp/dfr7/work/foam_bar_viscoelasticity@2_frames.usda \\
        --capture /tmp/dfr7/work/foam_bar_viscoelasticity@2_frames --control /tmp/dfr7/work/foam_bar_none_s0.usda \\
        --device cuda
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def problem(stage, device: str):
    """The stage's diagnosis problem and base, as `app.diagnose.diagnose` builds them (superset effects)."""
    from physinteract_usd.app.adapters import effects_with_fitted, read_scene
    from physinteract_usd.app.diagnose import problem_and_base

    sd = read_scene(Path(stage))
    prob, base = problem_and_base(sd, effects_with_fitted(sd), device=device)
    return sd, prob, base


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("--capture", required=True, help="the synth capture (its gt/gt.json names the hidden effect)")
    ap.add_argument("--control", default=None, help="the control's fitted stage (same scene and noise seed)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--taus", default="0.05,0.1,0.15,0.25,0.4")
    ap.add_argument("--moduli", default="0.5,1,2", help="E_v as these x the truth's")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import numpy as np

    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem
    from physinteract_usd.diagnose import score as S
    from physinteract_usd.diagnose.core import Probe, _pad, test_candidate

    t0, c0 = time.perf_counter(), time.process_time()
    gt = json.loads((Path(a.capture) / "gt" / "gt.json").read_text())
    he = (gt.get("hidden_effect") or {})
    truth = he.get("parameters") or {}
    if "modulus" not in truth:
        print(f"visco_probe_check.py: error: {a.capture}/gt/gt.json: no hidden viscoelasticity", file=sys.stderr)
        return 2
    out = {"stage": a.stage, "truth": truth, "frames_d2_over_sigma2": he.get("frames_d2_over_sigma2")}
    quiet = lambda *_a: None  # noqa: E731
    if a.control:
        _, pc, bc = problem(a.control, a.device)
        dc = diagnose_problem(pc, bc, DiagnoseSettings(candidates=(), confirmed=True), log=quiet)
        out["control_loss"] = dc.loss
    sd, prob, base = problem(a.stage, a.device)
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=("viscoelasticity",), confirmed=True), log=quiet)
    cr = d.results[0]
    ctx = d._ctx
    L0, r0, r0a, Ja, run = d.loss, ctx["r0"], ctx["r0a"], d._J, ctx["run"]
    blocks, nb = ctx["blocks"], int(ctx["n_blocks"])
    if len(r0a) > len(r0):          # the trajectory prior's rows: their own block, as diagnose_problem adds them
        blocks = np.concatenate([blocks, np.full(len(r0a) - len(r0), nb, np.int64)])
        nb += 1
    s = ctx["settings"]
    out.update(loss=L0, floor=d.floor, median_E=float(base.E.median()),
               candidate={"p": cr.p_value, "share": cr.relative_drop, "best_probe": cr.probes[cr.best].label
                          if cr.best >= 0 else None, "probes": [p.label for p in cr.probes],
                          "estimate": cr.estimate})
    if "control_loss" in out:
        out["excess_over_control"] = (L0 - out["control_loss"]) / out["control_loss"]
    e_med = float(base.E.median())
    rows = []
    for tau in [float(v) for v in a.taus.split(",")]:
        for m in [float(v) for v in a.moduli.split(",")]:
            ev = m * float(truth["modulus"])
            amp = ev / e_med
            col = (run.r(effects={"viscoelasticity": {"modulus": ev, "relaxationTime": tau}}) - r0) / amp
            t = test_candidate("viscoelasticity", [Probe(f"tau={tau:g},Ev={m:g}x", col, +1)], r0a, Ja, blocks, nb, s,
                               len(r0))
            jp = S.project_out(Ja, _pad(col * amp, len(r0a)))
            whole = -float(2.0 * (r0a @ jp) + jp @ jp)      # |P r|^2 - |P r + j_perp|^2: the branch taken whole
            rows.append({"tau": tau, "E_v": ev, "E_v_over_truth": m, "p": t.p_value, "share": t.drop / L0,
                         "step_over_probe": t.step / amp if amp else None, "whole_share": whole / len(r0) / L0,
                         "truth": abs(m - 1.0) < 1e-9 and abs(tau - float(truth.get("relaxationTime", -1))) < 1e-9})
            print(f"tau {tau:5.3f} s, E_v {ev:8.1f} Pa ({m:g}x truth): p {t.p_value:.3g}, share "
                  f"{100 * t.drop / L0:5.2f}% (Gauss-Newton), taken whole {100 * whole / len(r0) / L0:6.2f}%",
                  flush=True)
    out["grid"] = rows
    out["cpu_s"] = round(time.process_time() - c0, 1)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(f"loss {L0:.4g} (floor {d.floor:.3g}); median E {e_med:.4g} Pa; truth E_v {truth['modulus']:.4g} Pa, tau "
          f"{truth.get('relaxationTime')} s")
    if "control_loss" in out:
        print(f"control loss {out['control_loss']:.4g}: excess {100 * out['excess_over_control']:.2f}% of it")
    print(f"diagnose's candidate: p {cr.p_value:.3g}, share {100 * cr.relative_drop:.2f}% (best probe "
          f"{out['candidate']['best_probe']}); best on the grid {100 * max(r['share'] for r in rows):.2f}%; "
          f"{out['cpu_s']} CPU s")
    text = json.dumps(out, indent=1, default=float)
    if a.out:
        Path(a.out).write_text(text)
    if os.environ.get("OUT"):
        Path(os.environ["OUT"], "visco_probe_check.json").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
