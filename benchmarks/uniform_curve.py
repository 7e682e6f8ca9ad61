"""The uniform-E loss curve of a synthetic scene from true contacts (forward passes only): where
its minimum lies against the truth's best single E, per frame, and on training / held-back frames.
What it answers: is the uniform start's bias in the search (a needle missed by a coarse sweep) or
in the loss itself (its minimum away from the truth: model error, the silhouette term, weighting).

    python benchmarks/uniform_curve.py toy_rope --frames 14 --points 25 --out out/uniform_curve
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--points", type=int, default=25)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="out/uniform_curve")
    ap.add_argument("--truth-e", type=float, default=None,
                    help="synthesise the scene with this one E everywhere (its parts' E replaced): a loss minimum "
                         "away from it is then the fit's model error (resolution, renderer), not heterogeneity")
    ap.add_argument("--grid", type=int, default=None, help="init grid (default: the capture's suggested one)")
    ap.add_argument("--range", default=None, help="lo,hi Pa of the sweep (default: the stage's range)")
    a = ap.parse_args(argv)
    from physinteract_usd import api, metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.synth.gt import read_gt_array

    work = Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    cap = work / (a.scene if a.truth_e is None else f"{a.scene}_uniform{a.truth_e:g}")
    if a.truth_e is not None:
        import dataclasses

        from physinteract_usd.synth import scenes as S

        spec = S.SCENES[a.scene]
        S.SCENES[a.scene] = dataclasses.replace(spec, youngs=lambda p, part: np.full(len(p), a.truth_e))
    if not (cap / "gt" / "gt.json").exists():
        api.synth(a.scene, cap, size=a.size, frames=a.frames, device=a.device, force=True, log=lambda *x: None)
    gt = json.loads((cap / "gt" / "gt.json").read_text())
    sug = gt["suggested_init"]
    st = work / f"{cap.name}{'' if a.grid is None else f'_grid{a.grid}'}.usda"
    api.init(st, cap, grid=a.grid or sug["grid"], padding=sug["padding"], youngs_range=tuple(sug["youngs_range"]),
             max_poisson=sug["max_poisson"], density=sug["density"], force=True)
    job = prepare_fit(st, contact_from=cap / "gt", device=a.device, log=lambda *x: None)
    prob = make_problem(job)
    e_gt = read_gt_array(cap / "gt", "youngs_modulus.npy")
    ma_u, e_u = M.best_uniform_ma(e_gt)
    P = len(prob.x0)
    s = job.scene.settings
    nu = torch.full((P,), min(s.poisson_default, 0.98 * s.poisson_max), dtype=prob.tdtype, device=prob.tdev)
    rows = []
    t0, c0 = time.perf_counter(), time.process_time()
    lo, hi = (float(v) for v in a.range.split(",")) if a.range else (s.youngs_min, s.youngs_max)
    for le in np.linspace(math.log(lo), math.log(hi), a.points):
        E = torch.full((P,), math.exp(le), dtype=prob.tdtype, device=prob.tdev)
        with torch.no_grad():
            x, F = prob.simulate(E, nu)
            per = []
            for k in range(1, prob.T):
                out = prob.render_frame(k, x[k], F[k])
                lw = prob.frame_loss(k, out)
                per.append({n: float(v) for n, v in lw.items()})
        rows.append({"E": math.exp(le), "frames": per})
        print(f"E {math.exp(le):9.4g}  loss {np.mean([p['total'] for p in per]):.5f}", flush=True)
    res = {"scene": a.scene, "frames": prob.T, "particles": P, "best_uniform_e": e_u, "ma_best_uniform": ma_u,
           "gt_e_median": float(np.median(e_gt)), "rows": rows, "wall_s": time.perf_counter() - t0,
           "cpu_s": time.process_time() - c0}
    res["truth_e"] = a.truth_e
    res["grid"] = a.grid or sug["grid"]
    (work / f"{st.stem}_curve.json").write_text(json.dumps(res))
    print(json.dumps({k: v for k, v in res.items() if k != "rows"}))


if __name__ == "__main__":
    main()
