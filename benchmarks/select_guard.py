"""The guard and the unconstrained fill against the default fit, on one fitted stage (#24).

The stage's current version is the default fit (e.g. `benchmarks/suite.py --schedule bumps` wrote
it). On the same capture this runs the bumps schedule with the guard (`select.fit_guarded`: the
field and the uniform model on the training frames, the field kept only if its held-back loss is
clearly lower) and then the unconstrained fill (`select.fill_unconstrained`) on its result and on
the default's. For every model: MA over all Gaussians (the design's metric) and over the
constrained ones only (a Gaussian whose particles are mostly constrained; "constrained" from one
common rollout, the guard's uniform model, so every model is graded on the same Gaussians, and from
the model's own rollout), the training and held-back losses (the guard's frames, one substep), the
median E. Rows to --out (jsonl) and a table on stdout.

    python benchmarks/select_guard.py STAGE GT_DIR [--iterations 20] [--device cpu] [--out rows.jsonl]
        [--tag T] [--floor 0.1] [--dump per_particle.npz]
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--tag", default="")
    ap.add_argument("--floor", type=float, default=None, help="the exposure floor (default select.EXPOSURE_FLOOR)")
    ap.add_argument("--dump", default=None, help="an .npz of per-particle E of every model, the truth, the masks")
    a = ap.parse_args()

    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit, resume_start
    from physinteract_usd.fit.optimize import gaussian_weights
    from physinteract_usd.fit.select import (EXPOSURE_FLOOR, _result_inputs, fill_unconstrained, fit_guarded,
                                             frame_losses, strain_exposure, unconstrained_particles)
    from physinteract_usd.synth.gt import read_gt_array

    floor = EXPOSURE_FLOOR if a.floor is None else a.floor
    log = lambda m: print(m, flush=True)  # noqa: E731
    job = prepare_fit(a.stage, iterations=a.iterations, contact_from=a.gt, device=a.device, warm=False,
                      progress=False, log=log, settings_overrides={"schedule": "bumps"})
    prob = make_problem(job)
    s = job.settings
    e_gt = read_gt_array(a.gt, "youngs_modulus.npy")
    feats = prob.particle_appearance() if s.appearance > 0 else None
    w, idx = gaussian_weights(prob, feats)
    held = np.asarray(prob.held_particles(), bool)

    def per_gaussian(v):
        return np.exp((w * np.log(np.asarray(v, np.float64))[idx]).sum(1))

    # the default: the stage's current version
    start, ver, _ = resume_start(a.stage, job.scene, job.contacts)
    names = prob.sim.slot_names()
    P = len(prob.x0)
    default = types.SimpleNamespace(
        youngs=np.asarray(start["youngs"], np.float64), poisson=np.asarray(start["poisson"], np.float64),
        trajectories={n: np.asarray(start["trajectories"][n]) for n in names if n in start.get("trajectories", {})},
        effect_parameters=start.get("effects") or {}, confidence=np.ones(P), model={}, interrupted=False)
    default.youngs_gaussian = per_gaussian(default.youngs)
    if len(default.trajectories) != len(names):       # a trajectory the stage lacks: the initial one
        for n, t0 in zip(names, prob.initial_trajectories()):
            default.trajectories.setdefault(n, t0.detach().cpu().numpy())
    log(f"the default: the stage's {ver}, median E {np.median(default.youngs):.4g} Pa")

    cands: dict = {}
    c0 = time.process_time()
    t0 = time.perf_counter()
    rg = fit_guarded(prob, s, progress=False, log=log, candidates=cands)
    guard_cpu, guard_wall = round(time.process_time() - c0, 1), round(time.perf_counter() - t0, 1)
    g = rg.model.get("guard") or {}
    train, val = g.get("training_frames", []), g.get("held_back_frames", [])
    models = {"default (bumps, all frames; the stage)": default}
    if "uniform" in cands:
        models["guard: uniform (training frames)"] = cands["uniform"]
        models["guard: field = bumps (training frames)"] = cands["field"]
    models[f"guard: final ({g.get('chosen', '?')})"] = rg
    c0 = time.process_time()
    filled = {"guard final + fill": fill_unconstrained(prob, copy.deepcopy(rg), s, floor, log=log),
              "default + fill": fill_unconstrained(prob, copy.deepcopy(default), s, floor, log=log)}
    fill_cpu = round(time.process_time() - c0, 1)
    models.update(filled)

    # one "constrained" mask for every model: from the guard's uniform model's rollout
    common = cands.get("uniform", default)
    _, trajs, eff = _result_inputs(prob, common, s)
    expo_c = strain_exposure(prob, common.youngs, common.poisson, trajs, eff, e_bound=float(np.max(common.youngs)))
    unc_c = unconstrained_particles(expo_c, held, floor) if expo_c is not None else held.copy()

    def con_gauss(unc):
        return (w * (~unc)[idx].astype(np.float64)).sum(1) >= 0.5 * w.sum(1)

    e_top = max(float(np.max(m.youngs)) for m in models.values())
    every = sorted(set(train) | set(val))
    rows, dump = [], {"x0": np.asarray(prob.x0), "held": held, "unconstrained_common": unc_c}
    gm0 = np.asarray(rg.gaussian_means[0])
    _, nn = cKDTree(gm0).query(np.asarray(rg.positions[0]))
    dump["e_true"] = e_gt[nn]
    for name, m in models.items():
        fl = dict(zip(every, frame_losses(prob, m, s, every, e_top))) if every else {}
        _, tr, ef = _result_inputs(prob, m, s)
        ex = strain_exposure(prob, m.youngs, m.poisson, tr, ef, e_bound=float(np.max(m.youngs)))
        unc_own = unconstrained_particles(ex, held, floor) if ex is not None else held.copy()
        eg = np.asarray(m.youngs_gaussian)
        gc, go = con_gauss(unc_c), con_gauss(unc_own)
        row = {"tag": a.tag, "model": name, "ma": M.material_accuracy(eg, e_gt),
               "ma_constrained": M.material_accuracy(eg[gc], e_gt[gc]) if gc.any() else None,
               "ma_constrained_own": M.material_accuracy(eg[go], e_gt[go]) if go.any() else None,
               "constrained_gaussians": int(gc.sum()), "gaussians": int(len(gc)),
               "unconstrained_particles_own": int(unc_own.sum()), "particles": int(P),
               "training": float(np.mean([fl[k] for k in train])) if train else None,
               "held_back": float(np.mean([fl[k] for k in val])) if val else None,
               "held_back_frames": [fl[k] for k in val], "median_e": float(np.median(m.youngs)),
               "ma_best_uniform": M.best_uniform_ma(e_gt)[0]}
        if name.startswith("guard: final"):
            row.update(guard_cpu_s=guard_cpu, guard_wall_s=guard_wall, guard_test=(g.get("test") or {}).get("why"))
        if name in filled:
            row.update(fill=m.model.get("unconstrained"), fill_cpu_s=fill_cpu)
        rows.append(row)
        key = name.split(" (")[0].replace(" ", "_").replace(":", "").replace("=", "")
        dump[f"E__{key}"] = np.asarray(m.youngs)
        print(json.dumps({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()
                          if k not in ("held_back_frames", "fill")}), flush=True)
    print(f"{'model':48s} {'MA':>6s} {'MA con':>7s} {'MA own':>7s} {'held-back':>10s} {'training':>9s} {'median E':>9s}")
    for r in rows:
        f = lambda v, d=3: "-" if v is None else f"{v:.{d}f}"  # noqa: E731
        print(f"{r['model'][:48]:48s} {f(r['ma']):>6s} {f(r['ma_constrained']):>7s} {f(r['ma_constrained_own']):>7s} "
              f"{f(r['held_back'], 5):>10s} {f(r['training'], 5):>9s} {r['median_e']:9.4g}")
    print(f"best single E: MA {rows[0]['ma_best_uniform']:.3f}; guard {guard_wall} s wall, {guard_cpu} CPU s; "
          f"constrained Gaussians {rows[0]['constrained_gaussians']} of {rows[0]['gaussians']}")
    if a.dump:
        np.savez(a.dump, **dump)
    if a.out:
        with open(a.out, "a") as fh:
            for r in rows:
                fh.write(json.dumps(r, default=float) + "\n")


if __name__ == "__main__":
    main()
