"""The fit's loss (renderer and all) against a uniform E with the TRUE interaction, per pin rule: does the loss's
minimum move with the rule as the 3-D error's does (world_simcheck.py)? A few forwards, not the sweep (#24, CPU).

    python benchmarks/world_loss_rule.py --work data/world_stiff --seed 269 --cap 1500 --factors 0.5,1,2 --rules default,band

Per rule and factor of the true median E: the loss over every frame but the first (the fit's, as the truth sweep's),
as the truth sweep scores it. A tuning tool: refuses the validation split. docs/benchmarks/world_fits.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

import physinteract_usd  # noqa: F401
from physinteract_usd import simulation

sys.path.insert(0, str(Path(__file__).resolve().parent))

from world_bias import gt_dir, per_capture, prepare_stage  # noqa: E402
from world_fit import add_ground  # noqa: E402
from world_simcheck import RULES  # noqa: E402


def one(work: Path, n: str, cap: int, factors, rules, device: str, scratch: Path) -> list[dict]:
    from physinteract_usd.app.fit import make_problem, prepare_fit

    gt = gt_dir(work, n)
    g = json.loads((gt / "gt.json").read_text())
    e_true = float(np.median(np.load(gt / "youngs_modulus.npy")))
    out = scratch / f"{n}_{cap}"
    gc = prepare_stage(work / n, gt, out, cap)
    stage = out / "scene.usda"
    if g.get("floor"):
        add_ground(stage, g["floor"]["height"], g["floor"].get("friction", 0.5))
    rows = []
    for rule in rules:
        simulation.PIN_RULE = RULES[rule]
        try:
            job = prepare_fit(stage, iterations=1, contact_from=gt, device=device, log=lambda *a: None, warm=False)
            prob = make_problem(job)
            st = job.scene.settings
            nu = min(st.poisson_default, 0.98 * st.poisson_max)
            P = len(prob.x0)
            for f in factors:
                t0 = time.process_time()
                row = {"scene": n, "rule": rule, "factor": f, "e_true": e_true, "grid": gc.get("grid"), "particles": P}
                try:
                    with torch.no_grad():
                        res = prob.loss(torch.full((P,), e_true * f, dtype=prob.tdtype, device=prob.tdev),
                                        torch.full((P,), nu, dtype=prob.tdtype, device=prob.tdev))
                    row["loss"] = float(res["rec"])
                except Exception as exc:  # noqa: BLE001 - a row
                    row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
                row["cpu_s"] = time.process_time() - t0
                print(json.dumps(row), file=sys.stderr, flush=True)
                rows.append(row)
        finally:
            simulation.PIN_RULE = RULES["default"]
    return rows


def table(rows):
    out = ["| capture | rule | loss at E x factor | least at |", "|---|---|---|---|"]
    for key in sorted({(r["scene"], r["rule"]) for r in rows}):
        rs = sorted([r for r in rows if (r["scene"], r["rule"]) == key], key=lambda r: r["factor"])
        ok = [r for r in rs if "loss" in r]
        cells = "; ".join(f"x{r['factor']:g}: " + (f"{r['loss']:.5f}" if "loss" in r else "failed") for r in rs)
        best = min(ok, key=lambda r: r["loss"])["factor"] if ok else "-"
        out.append(f"| {key[0]} | {key[1]} | {cells} | x{best} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--seed", required=True)
    ap.add_argument("--cap", type=int, default=15000)
    ap.add_argument("--factors", default="0.5,1,2")
    ap.add_argument("--rules", default="default,band")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    ap.add_argument("--scratch", default="/tmp/world_loss_rule")
    a = ap.parse_args(argv)
    rules = [r for r in a.rules.split(",") if r]
    if any(r not in RULES for r in rules):
        print(f"world_loss_rule.py: error: --rules: unknown {[r for r in rules if r not in RULES][0]!r}", file=sys.stderr)
        return 2
    factors = [float(f) for f in a.factors.split(",")]
    return per_capture("world_loss_rule.py", Path(a.work), a.seed,
                       lambda n: one(Path(a.work), n, a.cap, factors, rules, a.device, Path(a.scratch)), a.json, table)


if __name__ == "__main__":
    sys.exit(main())
