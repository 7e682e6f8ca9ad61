"""The fitted model's resolution error on stages (issues #22, #24): how far the frames move when the
same fitted model is simulated on a finer grid (`diagnose.resolution`), against the residual and the
rest frame's floor, and which E the finer grids want.

Per stage (its current fit, as `diagnose --starts 1` takes it: the residual with the photometric nuisance
and noise weights): the loss L, the rest frame's floor, the two refinements' changes (cell / 2, / 3), the
Richardson estimate of the coarse model's own error, and a 1-D scan of the E field x s on the first split's grid. One
JSON line per stage:

    python benchmarks/resolution_check.py STAGE [STAGE ...] [--splits 2,3] [--scales 0.7,0.85,1.2,1.4] \\
        [--device cuda] [--out rows.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def check(stage, *, splits, scales, device: str, dtype: str = "float32", max_pixels: int = 6000) -> dict:
    import torch

    from physinteract_usd.app.diagnose import problem_and_base
    from physinteract_usd.app.adapters import effects_with_fitted, read_scene
    from physinteract_usd.diagnose.core import _floor, rest_frames
    from physinteract_usd.diagnose.residual import ImageResidual, loss
    from physinteract_usd.diagnose.resolution import resolution_change, resolution_error

    t0 = time.perf_counter()
    sd = read_scene(stage)
    prob, base = problem_and_base(sd, effects_with_fitted(sd), device=device, dtype=dtype)
    res = ImageResidual(prob, max_pixels=max_pixels)
    with torch.no_grad():
        x0, F0 = prob.sim.simulate(base.E, base.nu, None, effects=base.effects)
    res.set_photometric(x0, F0)
    res.set_noise_weights(x0, F0, rest_frames(prob))
    r0 = res(x0, F0)
    row = {"stage": str(stage), "loss": loss(r0), "floor": _floor(prob, res), "particles": int(len(prob.x0)),
           "cell_mm": 1000 * float(sd.settings.cell_size), "E_median": float(torch.median(base.E))}
    row["resolution"] = resolution_error(prob, base, res, r0, splits=splits)
    if scales:
        emax = float(sd.settings.youngs_max)
        kept = [s for s in scales if float(base.E.max()) * s <= emax]     # the stage's E bound: the substep's CFL
        if len(kept) < len(scales):
            row["scales_over_the_bound"] = [s for s in scales if s not in kept]
        scales = kept
        row["scan"] = resolution_change(prob, base, res, r0, split=splits[0], scales=scales).get("scan")
        with torch.no_grad():
            row["scan_coarse"] = []
            for s in scales:
                x, F = prob.sim.simulate(base.E * float(s), base.nu, None, effects=base.effects)
                row["scan_coarse"].append((float(s), loss(res(x, F))))
    row["seconds"] = round(time.perf_counter() - t0, 1)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stages", nargs="+")
    ap.add_argument("--splits", default="2,3")
    ap.add_argument("--scales", default="")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    scales = [float(s) for s in a.scales.split(",") if s.strip()]
    for st in a.stages:
        try:
            row = check(st, splits=tuple(int(v) for v in a.splits.split(",")), scales=scales, device=a.device)
        except Exception as exc:  # noqa: BLE001 - one stage's failure is a row
            row = {"stage": st, "error": f"{type(exc).__name__}: {exc}"}
        r = row.get("resolution") or {}
        print(json.dumps(row, default=float), flush=True)
        if "loss" in row:
            lv = r.get("levels") or []
            print(f"# {Path(st).name}: L {row['loss']:.3e} floor {row['floor']:.3e} (L/floor {row['loss'] / row['floor']:.2f}); "
                  + "; ".join(f"split {x.get('split')}: change {x.get('change', float('nan')):.3e} "
                              f"(L_fine {x.get('loss_fine', float('nan')):.3e}, {x.get('particles')})" for x in lv)
                  + f"; order {r.get('order')}, error {r.get('error')}, cos {r.get('cos')}", flush=True)
        if a.out:
            with open(a.out, "a") as f:
                f.write(json.dumps(row, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
