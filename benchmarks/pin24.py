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
loss (the renderer, the fit's own loss over frames 1..; `--loss-all`: at every factor, and the factor of least loss).

    python benchmarks/pin24.py --scenes foam_bar,basketball --work /tmp/pin24 --frames 10 --grid 16 \
        --truth-rules default,band --rules default,band --factors 0.5,0.71,1,1.41,2 --out rows.jsonl
    python benchmarks/pin24.py --out rows.jsonl --table-only
    python benchmarks/pin24.py --scenes foam_bar --truth-rules band --rules band,default --parts-scan \
        --factors 0.71,0.84,1,1.19,1.41 --frames 14 --grid 24 --out parts.jsonl     # a two-part scene's loss plane
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


def append_rows(path, rows: list[dict]) -> None:
    """Append rows to a JSON-lines file (nothing where `path` is None)."""
    if path:
        with open(path, "a") as fh:
            for row in rows:
                fh.write(json.dumps(row) + "\n")


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


def held_mass(x: np.ndarray, vol: np.ndarray, pinned: np.ndarray, lower, dx: float, rule) -> float:
    """The mass the grid holds for a pin under a rule (sum over nodes of w x the node's mass, w = clamp(gain
    (pinned share - floor), 0, 1), the quadratic B-spline P2G of sim/kernels.py) over the pinned particles' own
    mass: > 1 the grip reaches beyond the pinned particles, < 1 it holds less than them."""
    xp = (np.asarray(x, float) - np.asarray(lower, float)) / dx
    base = np.floor(xp - 0.5).astype(np.int64)
    fx = xp - base
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    b0 = base - base.min(0)
    n = b0.max(0) + 3
    vol = np.asarray(vol, float)
    m = np.zeros(int(np.prod(n)))
    pm = np.zeros_like(m)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                wt = w[i][:, 0] * w[j][:, 1] * w[k][:, 2] * vol
                key = ((b0[:, 0] + i) * n[1] + b0[:, 1] + j) * n[2] + b0[:, 2] + k
                m += np.bincount(key, wt, len(m))
                pm += np.bincount(key[pinned], wt[pinned], len(m))
    gain, floor = rule
    ok = (pm > 0) & (m > 0)
    held = np.clip(gain * (pm[ok] / m[ok] - floor), 0.0, 1.0) * m[ok]
    return float(held.sum() / vol[pinned].sum())


def truth_model(scene: str, g: dict, a):
    """The truth's particles, contacts and grid as synth built them (no simulation)."""
    import dataclasses

    from physinteract_usd.synth.generate import SIZES, GroundTruth
    from physinteract_usd.synth.scenes import SCENES

    sz = dataclasses.replace(SIZES[a.size], fit_grid=int(g["suggested_init"]["grid"]))
    return GroundTruth(SCENES[scene], sz, int(g["n_frames"]))


def held_rows(scene: str, a) -> list[dict]:
    """Per pin of the truth (its particles and grid, rebuilt as synth did) and of the fit (the stage's particles
    and grid at --grid, the true contacts): the held mass ratio under the default rule and the band."""
    from physinteract_usd import simulation
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from traj_pin import make_stage

    work = Path(a.work) / "truth_default"
    work.mkdir(parents=True, exist_ok=True)
    os.environ["PHYSINTERACT_TRUTH_PIN_RULE"] = "default"
    stage, gt = make_stage(scene, a, work)
    g = json.loads((gt / "gt.json").read_text())
    truth = truth_model(scene, g, a)
    simulation.PIN_RULE = simulation.DEFAULT_PIN_RULE
    prob = make_problem(prepare_fit(stage, iterations=1, contact_from=gt, device="cpu", log=lambda *x: None,
                                    warm=False, progress=False))
    vol_fit = np.asarray(prob.sim.scene.particles_volumes, float) * np.ones(len(prob.x0))
    pins_fit = {("grasp" if c.type == "pointAdherent" else "support"): np.asarray(c.indices, int)
                for c in prob.sim.contacts if c.type in ("pointAdherent", "fixed")}
    pins_truth = {("grasp" if c.type == "pointAdherent" else "support"): np.asarray(c.indices, int)
                  for c in truth.control.contacts if c.type in ("pointAdherent", "fixed")}
    rows = []
    for side, x, vol, pins, grid in (("truth", truth.x0, np.full(len(truth.x0), truth.spacing ** 3), pins_truth,
                                      truth.grid), ("fit", np.asarray(prob.x0), vol_fit, pins_fit, prob.sim.grid)):
        for kind, idx in pins.items():
            mask = np.zeros(len(x), bool)
            mask[idx] = True
            row = {"scene": scene, "side": side, "pin": kind, "particles": int(mask.sum()), "dx_mm": 1e3 * grid.dx,
                   "size_cells": float(np.ptp(x[mask], axis=0).max() / grid.dx)}
            for name, rule in (("default", simulation.DEFAULT_PIN_RULE), ("band", simulation.CLAMP_BAND)):
                row[f"held_{name}"] = held_mass(x, vol, mask, grid.lower, grid.dx, rule)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def one(scene: str, truth_rule: str, a) -> list[dict]:
    import torch

    torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import simulation
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.errors import SimulationError
    from traj_pin import make_stage
    from world_simcheck import best_factor, set_rule

    work = Path(a.work) / f"truth_{truth_rule}"
    work.mkdir(parents=True, exist_ok=True)
    os.environ["PHYSINTERACT_TRUTH_PIN_RULE"] = truth_rule        # the synth subprocess's truth
    stage, gt = make_stage(scene, a, work)
    tr = np.load(gt / "particles.npz")
    rest, pos = tr["rest"], tr["positions"]
    g = json.loads((gt / "gt.json").read_text())
    rows = []
    truth = truth_model(scene, g, a)
    pins_truth = {("grasp" if c.type == "pointAdherent" else "support"): np.asarray(c.indices, int)
                  for c in truth.control.contacts if c.type in ("pointAdherent", "fixed")}
    vol_t = np.full(len(rest), truth.spacing ** 3)
    held_truth = {k: [held_mass(pos[f], vol_t, np.isin(np.arange(len(rest)), idx), truth.grid.lower, truth.grid.dx,
                                simulation.pin_rule(truth_rule)) for f in range(len(pos))]
                  for k, idx in pins_truth.items()}
    for rule in a.rules.split(","):
        set_rule(rule)
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
                   "fit_support_rule": list(simulation.SUPPORT_RULE or simulation.PIN_RULE),
                   "grid": a.grid, "resolution": list(prob.sim.grid.resolution), "dx": float(prob.sim.grid.dx), "truth_dx": g["gt_sim"]["dx"],
                   "particles": int(len(x0)), "n": {k: int(m.sum()) for k, m in reg.items()},
                   "truth_disp_m": scale, "grasp": g["interaction"]["grasp_frame"],
                   "release": g["interaction"]["release_frame"], "type": g["interaction"]["type"]}
            try:
                with torch.no_grad():
                    x, F = prob.simulate(E_t * f, nu_t)
                    if (f == 1.0 or a.loss_all) and a.loss:
                        row["loss"] = float(prob.loss(E_t, nu_t, simulated=(x, F))["rec"])
                xs = x[:T].detach().cpu().numpy()
                du = xs - x0[None]
                err = np.linalg.norm(du - disp, axis=-1)                 # (T, P)
                row["err_m"] = float(err[1:].mean())
                if f == 1.0:     # the grid's hold on each pin per frame (`held_mass`), the fit's and the truth's
                    vol = np.asarray(prob.sim.scene.particles_volumes, float) * np.ones(len(x0))
                    row["held_fit_frame"] = {
                        ("grasp" if c.type == "pointAdherent" else "support"):
                        [round(held_mass(xs[k], vol, np.isin(np.arange(len(x0)), c.indices), prob.sim.grid.lower,
                                         prob.sim.grid.dx, (simulation.SUPPORT_RULE or simulation.PIN_RULE)
                                         if c.type == "fixed" else simulation.PIN_RULE), 3) for k in range(T)]
                        for c in prob.sim.contacts if c.type in ("pointAdherent", "fixed")}
                    row["held_truth_frame"] = {k: [round(v, 3) for v in vs[:T]] for k, vs in held_truth.items()}
                row["err_region_m"] = {k: float(err[1:, m].mean()) if m.any() else None for k, m in reg.items()}
                row["err_region_frame_m"] = {k: err[:, m].mean(1).round(6).tolist() if m.any() else None
                                             for k, m in reg.items()}
                pairs.append((f, row["err_m"]))
            except SimulationError as exc:
                row["error"] = str(exc).splitlines()[0][:300]
            row["cpu_s"] = round(time.process_time() - c0, 1)
            per.append(row)
            print(json.dumps({k: v for k, v in row.items() if not k.endswith("_frame_m") and "held" not in k}),
                  flush=True)
        bf = best_factor(pairs)
        bl = best_factor([(r["factor"], r["loss"]) for r in per if "loss" in r]) if a.loss_all else None
        for row in per:
            row["best_factor"] = bf
            row["best_loss_factor"] = bl
        rows += per
        append_rows(a.out, per)
    set_rule("default")
    return rows


def parts_scan(scene: str, truth_rule: str, a) -> list[dict]:
    """The image loss and the 3-D error over a plane of two factors: one on the truth's stiffer particles (E above the
    midpoint of its range), one on the softer (a two-part scene: foam_bar), per fit rule, at the true path."""
    import torch

    torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import simulation
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from traj_pin import make_stage

    work = Path(a.work) / f"truth_{truth_rule}"
    os.environ["PHYSINTERACT_TRUTH_PIN_RULE"] = truth_rule
    stage, gt = make_stage(scene, a, work)
    tr = np.load(gt / "particles.npz")
    rest, pos = tr["rest"], tr["positions"]
    rows = []
    fs = [float(v) for v in a.factors.split(",")]
    for rule in a.rules.split(","):
        simulation.PIN_RULE = simulation.pin_rule(rule)
        prob = make_problem(prepare_fit(stage, iterations=1, contact_from=gt, device=a.device, log=lambda *x: None,
                                        warm=False, progress=False))
        x0 = np.asarray(prob.x0)
        nn = cKDTree(rest).query(x0)[1]
        T = min(prob.T, len(pos))
        e = tr["E"][nn]
        stiff = e > 0.5 * (tr["E"].min() + tr["E"].max())     # the stiffer part (two-valued fields)
        disp = pos[:T, nn] - pos[0, nn][None]
        nu_t = torch.as_tensor(tr["nu"][nn], dtype=prob.tdtype, device=prob.tdev)
        for fa in fs:
            for fb in fs:
                E = torch.as_tensor(np.where(stiff, fa, fb) * e, dtype=prob.tdtype, device=prob.tdev)
                with torch.no_grad():
                    x, F = prob.simulate(E, nu_t)
                    loss = float(prob.loss(E, nu_t, simulated=(x, F))["rec"])
                err = float(np.linalg.norm(x[:T].cpu().numpy() - x0[None] - disp, axis=-1)[1:].mean())
                row = {"scene": scene, "truth_rule": truth_rule, "fit_rule": rule, "stiff_factor": fa,
                       "soft_factor": fb, "loss": loss, "err_m": err}
                rows.append(row)
                print(json.dumps(row), flush=True)
    append_rows(a.out, rows)
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
    ap.add_argument("--loss-all", action="store_true", help="the image loss at every factor (its least: `best_loss_factor`)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--parts-scan", action="store_true", help="the loss over (stiffer part x, softer part x) --factors")
    ap.add_argument("--held", action="store_true", help="only the held mass per pin at rest (truth and fit, both rules)")
    a = ap.parse_args(argv)
    if a.parts_scan:
        for sc in a.scenes.split(","):
            for tr in a.truth_rules.split(","):
                parts_scan(sc, tr, a)
        return
    if a.held:
        rows = [r for sc in a.scenes.split(",") for r in held_rows(sc, a)]
        print("| scene | side | pin | particles | cell (mm) | its extent (cells) | held / pinned mass: default | band |\n"
              + "|---" * 8 + "|")
        for r in rows:
            print(f"| {r['scene']} | {r['side']} | {r['pin']} | {r['particles']} | {r['dx_mm']:.1f} | {r['size_cells']:.1f} | "
                  f"{r['held_default']:.2f} | {r['held_band']:.2f} |")
        return
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
