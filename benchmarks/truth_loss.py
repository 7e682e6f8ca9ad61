"""Does the truth explain the video better than the fit? (#24)

On a fitted synthetic stage (e.g. `benchmarks/suite.py` wrote it), the fit's own loss per frame
for: the stage's current version (the fit), the truth's E and Poisson's ratio mapped to the
particles (each particle takes its nearest Gaussian's truth at rest) with the fit's trajectories
and with the initial ones (from true contacts: the truth's path), and the best single E (the
truth's `best_uniform_ma` E) with the fit's trajectories. Every model is simulated at one substep
(the stiffest model's rung). If the truth's loss is lower than the fit's, the optimiser stopped
short (a local minimum, a schedule too short); if it is higher, the fit's model cannot reproduce
the video at the true material (discretisation, the contact, rendering) and no optimiser recovers
the truth by lowering this loss.

    python benchmarks/truth_loss.py STAGE GT_DIR [--device cuda] [--out rows.jsonl] [--tag T]
"""

from __future__ import annotations

import argparse
import json
import sys
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def fixed_result(E, nu, traj, effects=None):
    """A FitResult-like record of a given field and hand paths, for `select.frame_losses` (no optimiser)."""
    E = np.asarray(E, np.float64)
    return types.SimpleNamespace(youngs=E, poisson=np.asarray(nu, np.float64), trajectories=traj,
                                 effect_parameters=effects or {}, confidence=np.ones(len(E)), model={},
                                 interrupted=False)


def _compress(e, k):
    """E with its log-contrast scaled by k about its geometric mean (k < 1: less contrast, the same mean log E)."""
    le = np.log(np.asarray(e, np.float64))
    return np.exp(le.mean() + k * (le - le.mean()))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--tag", default="")
    a = ap.parse_args(argv)

    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit, resume_start
    from physinteract_usd.fit.optimize import gaussian_weights
    from physinteract_usd.fit.select import frame_losses
    from physinteract_usd.synth.gt import read_gt_array

    job = prepare_fit(a.stage, iterations=1, contact_from=a.gt, device=a.device, warm=False, progress=False,
                      log=lambda m: None, settings_overrides={"schedule": "bumps"})
    prob = make_problem(job)
    s = job.settings
    e_gt = np.asarray(read_gt_array(a.gt, "youngs_modulus.npy"), np.float64)
    nu_gt = np.asarray(read_gt_array(a.gt, "poisson_ratio.npy"), np.float64)
    g_pos = np.asarray(read_gt_array(a.gt, "gaussian_positions.npy"), np.float64)[0]   # (T, G, 3): at rest
    feats = prob.particle_appearance() if s.appearance > 0 else None
    w, idx = gaussian_weights(prob, feats)

    def per_gaussian(v):
        return np.exp((w * np.log(np.asarray(v, np.float64))[idx]).sum(1))

    names = prob.sim.slot_names()
    P = len(prob.x0)
    x0 = np.asarray(prob.x0.detach().cpu().numpy() if hasattr(prob.x0, "detach") else prob.x0, np.float64)
    _, nn = cKDTree(g_pos).query(x0)
    init_traj = {n: t0.detach().cpu().numpy() for n, t0 in zip(names, prob.initial_trajectories())}

    start, ver, _ = resume_start(a.stage, job.scene, job.contacts)
    fit_traj = {n: np.asarray(start["trajectories"][n]) if n in start.get("trajectories", {}) else init_traj[n]
                for n in names}

    model = fixed_result

    ma_best, e_best = M.best_uniform_ma(e_gt)
    fit_E = np.asarray(start["youngs"], np.float64)
    fit_nu = np.asarray(start["poisson"], np.float64)
    models = {
        "fit (the stage's current version)": model(fit_E, fit_nu, fit_traj, start.get("effects")),
        "truth E, nu; fit's trajectories": model(e_gt[nn], nu_gt[nn], fit_traj),
        "truth E, nu; initial trajectories": model(e_gt[nn], nu_gt[nn], init_traj),
        "fit's E, nu; initial trajectories": model(fit_E, fit_nu, init_traj, start.get("effects")),
        "best single E (truth's nu); fit's traj": model(np.full(P, e_best), nu_gt[nn], fit_traj),
        "truth E x 1.2; fit's trajectories": model(1.2 * e_gt[nn], nu_gt[nn], fit_traj),
        "truth E / 1.2; fit's trajectories": model(e_gt[nn] / 1.2, nu_gt[nn], fit_traj),
        # the fit's kind of error on its own: the truth's contrast halved in log E about its geometric mean
        "truth's contrast halved; fit's traj": model(_compress(e_gt[nn], 0.5), nu_gt[nn], fit_traj),
        "truth's contrast halved; initial traj": model(_compress(e_gt[nn], 0.5), nu_gt[nn], init_traj),
    }
    e_top = max(float(np.max(m.youngs)) for m in models.values())
    frames = list(range(1, prob.T))
    rows = []
    for name, m in models.items():
        fl = frame_losses(prob, m, s, frames, e_top)
        eg = per_gaussian(m.youngs)
        row = {"tag": a.tag, "stage": a.stage, "model": name, "loss": float(np.mean(fl)), "frames": fl,
               "ma": M.material_accuracy(eg, e_gt), "median_e": float(np.median(m.youngs)), "version": ver}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "frames"}), flush=True)
    print(f"\n{a.stage}: truth E range {e_gt.min():.4g}-{e_gt.max():.4g} Pa, best single E {e_best:.4g} (MA {ma_best:.3f})")
    print(f"{'model':42s} {'loss':>9s} {'MA':>6s} {'median E':>9s}  per frame")
    for r in rows:
        print(f"{r['model'][:42]:42s} {r['loss']:9.5f} {r['ma']:6.3f} {r['median_e']:9.4g}  "
              + " ".join(f"{v:.4f}" for v in r["frames"]))
    if a.out:
        with open(a.out, "a") as fh:
            for r in rows:
                fh.write(json.dumps(r, default=float) + "\n")


if __name__ == "__main__":
    main()
