"""Where does the pin rule's truth-fit discrepancy sit? (#24, "The clamp band in the suite", docs/benchmarks/fit.md)

Forward only, no fit. Per scene and per TRUTH pin rule (the synth's truth simulated under
PHYSINTERACT_TRUTH_PIN_RULE, `synth.generate.truth_pin_rule`; unset = (4, 0), every capture before), the
capture and stage are made as the suite does (`traj_pin.make_stage`: synth, init at --grid), then per FIT
pin rule (`simulation.PIN_RULE`) the fit's simulation runs with the truth's material (each fit particle
takes its nearest truth particle's E and nu at rest) x a factor, the TRUE contacts, supports and path
(`--contact-from gt`). Each fit particle's displacement is compared with its nearest truth particle's
(`world_simcheck.compare`), per region: `grasp` (within --radius fit cells of a particle the hand holds, at
rest), `support` (within --radius cells of a `fixed` particle), `free` (the others); per frame and over
the frames. Per (truth rule, fit rule) the factor of least error (all particles; parabola in log E):
the E a fit would need to match the truth's motion under that rule. At factor 1 also the fit's image
loss (the renderer, the fit's own loss over frames 1..).

    python benchmarks/pin24.py --scenes foam_bar,basketball --work /tmp/pin24 --frames 10 --grid 16 \
        --truth-rules default,band --rules default,band --factors 0.5,0.71,1,1.41,2 --out rows.jsonl
    python benchmarks/pin24.py --out rows.jsonl --table-only
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def regions(prob, radius_cells: float) -> dict:
    """Boolean masks over the fit's particles: grasp / support / free (a particle near both counts as grasp)."""
    from scipy.spatial import cKDTree

    x0 = np.asarray(prob.x0)
    r = radius_cells * float(prob.sim.grid.dx)
    held = {"grasp": [], "support": []}
    for c in prob.sim.contacts:
        if c.type == "pointAdherent":
            held["grasp"].append(np.asarray(c.indices, int))
        elif c.type == "fixed":
            held["support"].append(np.asarray(c.indices, int))
    out = {}
    for k, idx in held.items():
        if idx:
            d = cKDTree(x0[np.concatenate(idx)]).query(x0)[0]
            out[k] = d <= r
        else:
            out[k] = np.zeros(len(x0), bool)
    out["support"] &= ~out["grasp"]
    out["free"] = ~(out["grasp"] | out["support"])
    return out


def one(scene: str, truth_rule: str, a) -> list[dict]:
    import torch

    torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import simulation
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.errors import SimulationError
    from traj_pin import make_stage
    from world_simcheck import best_factor

    work = Path(a.work) / f"truth_{truth_rule}"
    work.mkdir(parents=True, exist_ok=True)
    os.environ["PHYSINTERACT_TRUTH_PIN_RULE"] = truth_rule        # the synth subprocess's truth
    stage, gt = make_stage(scene, a, work)
    tr = np.load(gt / "particles.npz")
    rest, pos = tr["rest"], tr["positions"]
    g = json.loads((gt / "gt.json").read_text())
    rows = []
    for rule in a.rules.split(","):
        simulation.PIN_RULE = simulation.pin_rule(rule)
        job = prepare_fit(stage, iterations=1, contact_from=gt, device=a.device, log=lambda *x: None, warm=False,
                          progress=False)
        prob = make_problem(job)
        x0 = np.asarray(prob.x0)
        nn = cKDTree(rest).query(x0)[1]
        T = min(prob.T, len(pos))
        reg = regions(prob, a.radius)
        E_t = torch.as_tensor(tr["E"][nn], dtype=prob.tdtype, device=prob.tdev)
        nu_t = torch.as_tensor(tr["nu"][nn], dtype=prob.tdtype, device=prob.tdev)
        disp = pos[:T, nn] - pos[0, nn][None]
        scale = {k: float(np.linalg.norm(disp[1:, m], axis=-1).mean()) if m.any() else None for k, m in reg.items()}
        pairs = []
        per = []
        for f in [float(v) for v in a.factors.split(",")]:
            c0 = time.process_time()
            row = {"scene": scene, "truth_rule": truth_rule, "fit_rule": rule, "factor": f,
                   "truth_pin_rule": g["gt_sim"].get("pin_rule", [4.0, 0.0]), "fit_pin_rule": list(simulation.PIN_RULE),
                   "grid": a.grid, "resolution": list(prob.sim.grid.resolution), "dx": float(prob.sim.grid.dx), "truth_dx": g["gt_sim"]["dx"],
                   "particles": int(len(x0)), "n": {k: int(m.sum()) for k, m in reg.items()},
                   "truth_disp_m": scale, "grasp": g["interaction"]["grasp_frame"],
                   "release": g["interaction"]["release_frame"], "type": g["interaction"]["type"]}
            try:
                with torch.no_grad():
                    x, F = prob.simulate(E_t * f, nu_t)
                    if f == 1.0 and a.loss:
                        row["loss"] = float(prob.loss(E_t, nu_t, simulated=(x, F))["rec"])
                xs = x[:T].detach().cpu().numpy()
                du = xs - x0[None]
                err = np.linalg.norm(du - disp, axis=-1)                 # (T, P)
                row["err_m"] = float(err[1:].mean())
                row["err_region_m"] = {k: float(err[1:, m].mean()) if m.any() else None for k, m in reg.items()}
                row["err_region_frame_m"] = {k: err[:, m].mean(1).round(6).tolist() if m.any() else None
                                             for k, m in reg.items()}
                pairs.append((f, row["err_m"]))
            except SimulationError as exc:
                row["error"] = str(exc).splitlines()[0][:300]
            row["cpu_s"] = round(time.process_time() - c0, 1)
            per.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "err_region_frame_m"}), flush=True)
        bf = best_factor(pairs)
        for row in per:
            row["best_factor"] = bf
        rows += per
        if a.out:
            with open(a.out, "a") as fh:
                for row in per:
                    fh.write(json.dumps(row) + "\n")
    simulation.PIN_RULE = simulation.DEFAULT_PIN_RULE
    return rows


def table(rows: list[dict]) -> str:
    head = ("| scene | truth rule | fit rule | grid | least-error E / truth | error at 1x: all / grasp / support / free (mm) "
            "| truth's mean displacement: grasp / support / free (mm) | loss at 1x |\n" + "|---" * 8 + "|\n")
    out = []
    mm = lambda v: "-" if v is None else f"{1e3 * v:.2f}"  # noqa: E731
    for r in rows:
        if r["factor"] != 1.0 or "err_m" not in r:
            continue
        e, s = r["err_region_m"], r["truth_disp_m"]
        out.append(f"| {r['scene']} | {r['truth_rule']} | {r['fit_rule']} | {r['grid']} | "
                   f"{r['best_factor']:.2f} | {mm(r['err_m'])} / {mm(e['grasp'])} / {mm(e['support'])} / {mm(e['free'])} | "
                   f"{mm(s['grasp'])} / {mm(s['support'])} / {mm(s['free'])} | {r.get('loss', float('nan')):.5f} |")
    return head + "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="foam_bar")
    ap.add_argument("--work", default="out/pin24")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--synth-fit-grid", type=int, default=None)
    ap.add_argument("--grid", default="16")
    ap.add_argument("--transfer-tau", type=float, default=0.0)
    ap.add_argument("--truth-rules", default="default,band")
    ap.add_argument("--rules", default="default,band")
    ap.add_argument("--factors", default="0.5,0.71,1,1.41,2")
    ap.add_argument("--radius", type=float, default=1.5, help="a region's reach about its held particles, fit cells")
    ap.add_argument("--no-loss", dest="loss", action="store_false", help="skip the image loss at 1x")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--table-only", action="store_true")
    a = ap.parse_args(argv)
    if a.table_only:
        print(table([json.loads(x) for x in Path(a.out).read_text().splitlines() if x.strip()]))
        return
    rows = []
    for sc in a.scenes.split(","):
        for tr in a.truth_rules.split(","):
            rows += one(sc, tr, a)
    print(table(rows))


if __name__ == "__main__":
    main()
