"""Our simulator against the world generator's, in 3-D, with everything else true (#24).

The truth sweep (world_bias.py) finds that on several development captures our model's best uniform E
is far below the truth's, with a sharp minimum. Is that the simulators' difference (our MPM, its grasp
as particle kinematics, its clamp rule, its grid) or the loss (renderer, masks)? This script leaves
the renderer out: our particles are simulated with the TRUE interaction (contacts, supports and
hand path from the ground truth, the floor from it as the `ground` effect) and the truth's material
(each particle takes the E and nu of the nearest truth particle at rest), scaled by a factor, and
their motion is compared with the truth's particles' (each of ours against its nearest truth particle
at rest, displacement against displacement). Per factor and per pin rule (the default and the clamp
band, `simulation.PIN_RULE`): the mean displacement error over the frames of the interaction and
over the frames after the release, against the truth's mean displacement.

    python benchmarks/world_simcheck.py --work data/world_dev --seeds 6 --factors 0.125,0.25,0.5,1,2 --device cuda

A tuning tool: it refuses the validation split. Results in docs/benchmarks/world_fits.md.
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
from physinteract_usd.errors import SimulationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from world_bias import gt_dir, per_capture, prepare_stage  # noqa: E402
from world_fit import add_ground  # noqa: E402

# "gain1": the world generator's own blend (a node moves with the held share of its mass, pin_gain 1)
RULES = {"default": simulation.PIN_RULE, "band": simulation.CLAMP_BAND, "gain1": (1.0, 0.0)}


def compare(x: np.ndarray, x0: np.ndarray, truth: np.ndarray, nn: np.ndarray) -> np.ndarray:
    """(T,) mean distance between our particles' displacement and their nearest truth particle's."""
    du = x - x0[None]
    dt = truth[:, nn] - truth[0, nn][None]
    return np.linalg.norm(du - dt, axis=-1).mean(axis=1)


def one(work: Path, n: str, cap_n: int, factors: list[float], rules: list[str], device: str, scratch: Path,
        log=print) -> list[dict]:
    from scipy.spatial import cKDTree

    from physinteract_usd.app.fit import make_problem, prepare_fit

    gt = gt_dir(work, n)
    g = json.loads((gt / "gt.json").read_text())
    out = scratch / f"{n}_{cap_n}"
    gc = prepare_stage(work / n, gt, out, cap_n)
    stage = out / "scene.usda"
    if g.get("floor"):
        add_ground(stage, g["floor"]["height"], g["floor"].get("friction", 0.5))
    tr = np.load(gt / "particles.npz")
    rest, pos = tr["rest"], tr["positions"]
    it = g["interaction"]
    grasp, release = it.get("grasp_frame"), it.get("release_frame")
    rows = []
    for rule in rules:
        simulation.PIN_RULE = RULES[rule]
        job = prepare_fit(stage, iterations=1, contact_from=gt, device=device, log=lambda *a: None, warm=False)
        prob = make_problem(job)
        x0 = np.asarray(prob.x0)
        nn = cKDTree(rest).query(x0)[1]
        T = min(prob.T, len(pos))
        E_t = torch.as_tensor(tr["E"][nn], dtype=prob.tdtype, device=prob.tdev)
        nu_t = torch.as_tensor(tr["nu"][nn], dtype=prob.tdtype, device=prob.tdev)
        scale = float(np.linalg.norm(pos[:T] - pos[0][None], axis=-1).mean())
        inter = list(range(max(1, grasp or 1), (release if release is not None else T)))
        after = list(range(release + 1, T)) if release is not None else []
        for f in factors:
            t0 = time.perf_counter()
            row = {"scene": n, "cap": cap_n, "grid": gc.get("grid"), "cells_across": gc.get("cellsAcross"),
                   "particles": len(x0), "truth_particles": len(rest), "rule": rule, "factor": f,
                   "e_true": float(np.median(tr["E"])), "truth_mean_disp_m": scale,
                   "shape": g.get("world", {}).get("shape"), "scenario": g.get("world", {}).get("scenario"),
                   "type": it.get("type"), "grasp": grasp, "release": release}
            try:
                with torch.no_grad():
                    x, _ = prob.simulate(E_t * f, nu_t)
                err = compare(x[:T].detach().cpu().numpy(), x0, pos[:T], nn)
                row.update({"err_all_m": float(err[1:].mean()),
                            "err_interaction_m": float(err[inter].mean()) if inter else None,
                            "err_after_m": float(err[after].mean()) if after else None,
                            "err_per_frame_m": err.tolist()})
            except SimulationError as exc:
                row["error"] = str(exc).splitlines()[0][:160]
            row["sim_s"] = time.perf_counter() - t0
            rows.append(row)
            log(json.dumps({k: v for k, v in row.items() if k != "err_per_frame_m"}), flush=True)
    simulation.PIN_RULE = RULES["default"]
    return rows


def table(rows: list[dict]) -> str:
    """One line per (capture, rule): the error at each factor (mm), the factor with the least."""
    out = ["| capture | what | particles (truth) | rule | mean truth displacement | error (mm) at E x factor: all / interaction / after release | best factor (all / after) |",
           "|---|---|---|---|---:|---|---|"]
    keys = sorted({(r["scene"], r["rule"]) for r in rows}, key=lambda k: (k[0], k[1]))
    for sc, rule in keys:
        rs = sorted([r for r in rows if r["scene"] == sc and r["rule"] == rule], key=lambda r: r["factor"])
        ok = [r for r in rs if "err_all_m" in r]
        cells = []
        for r in rs:
            if "err_all_m" not in r:
                cells.append(f"x{r['factor']:g}: unstable")
                continue
            ea = r["err_after_m"]
            cells.append(f"x{r['factor']:g}: {1e3 * r['err_all_m']:.1f} / {1e3 * (r['err_interaction_m'] or 0):.1f} / "
                         + (f"{1e3 * ea:.1f}" if ea is not None else "-"))
        best_all = min(ok, key=lambda r: r["err_all_m"])["factor"] if ok else None
        aft = [r for r in ok if r["err_after_m"] is not None]
        best_after = min(aft, key=lambda r: r["err_after_m"])["factor"] if aft else None
        r0 = rs[0]
        out.append(f"| {sc} | {r0.get('shape')} {r0.get('scenario')}, {r0.get('type')} | {r0['particles']} ({r0['truth_particles']}) "
                   f"| {rule} | {1e3 * r0['truth_mean_disp_m']:.1f} mm | {'; '.join(cells)} | {best_all} / {best_after} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--seeds", required=True)
    ap.add_argument("--cap", type=int, default=15000, help="init's --max-particles (grid auto)")
    ap.add_argument("--factors", default="0.125,0.25,0.5,1,2")
    ap.add_argument("--rules", default="default,band")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    ap.add_argument("--scratch", default="/tmp/world_simcheck")
    a = ap.parse_args(argv)
    factors = [float(f) for f in a.factors.split(",")]
    rules = [r for r in a.rules.split(",") if r]
    bad = [r for r in rules if r not in RULES]
    if bad:
        print(f"world_simcheck.py: error: --rules: unknown {bad[0]!r} (default, band, gain1)", file=sys.stderr)
        return 2
    return per_capture("world_simcheck.py", Path(a.work), a.seeds,
                       lambda n: one(Path(a.work), n, a.cap, factors, rules, a.device, Path(a.scratch), log=lambda *x, **k: None),
                       a.json, table, show=lambda r: json.dumps({k: v for k, v in r.items() if k != "err_per_frame_m"}))

if __name__ == "__main__":
    sys.exit(main())
