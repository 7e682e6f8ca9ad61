"""Where does the bumps schedule stop short? (#24, foam_bar)

On a synthetic stage and its gt/ (true contacts), in process, every loss at one substep (the stage's
E range top's rung) and with the fit's own terms: the reconstruction loss ("rec", what truth_loss.py
reports) and the material field's smoothness term ("reg", lambda_smooth x edge-aware mean squared
log-E difference over neighbour pairs, what the optimiser also pays), for:
- the fit (a bumps fit run here, default settings unless --set, its loss history printed);
- the truth's E and nu per particle (each particle: its nearest Gaussian's truth at rest);
- the truth projected onto the fit's finest basis (8 bumps in position + colour space): can the
  parametrisation hold the truth at all;
- the line from the fit's E to the truth's (log E and nu linear in t, the true path): is it monotone;
- `--from-truth`: a bumps fit resumed from the projected truth (the finest basis, all iterations):
  does the optimiser stay there, and `--from-half`: from halfway along the line.

    python benchmarks/bumps_stall.py STAGE GT_DIR [--iterations 20] [--line 0,0.25,0.5,0.75,1]
        [--from-truth] [--from-half] [--set key=value ...] [--out rows.jsonl] [--tag T]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def parse_set(items):
    out = {}
    for it in items or []:
        k, v = it.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
        if isinstance(out[k], list):
            out[k] = tuple(out[k])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--line", default="0,0.25,0.5,0.75,1")
    ap.add_argument("--from-truth", action="store_true")
    ap.add_argument("--from-half", action="store_true")
    ap.add_argument("--no-fit", action="store_true", help="skip the fit (truth, projection only)")
    ap.add_argument("--set", action="append", help="FitSettings overrides, key=json")
    ap.add_argument("--out", default=None)
    ap.add_argument("--tag", default="")
    a = ap.parse_args(argv)

    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit.material import MaterialField, neighbour_pairs, pair_weights
    from physinteract_usd.fit.optimize import fit_bumps, gaussian_weights
    from physinteract_usd.fit.parts_start import parts_start_hook
    from physinteract_usd.fit.select import pinned_substep
    from physinteract_usd.synth.gt import read_gt_array

    over = {"schedule": "bumps", **parse_set(a.set)}
    job = prepare_fit(a.stage, iterations=a.iterations, contact_from=a.gt, device=a.device, warm=False,
                      progress=False, log=lambda m: None, settings_overrides=over)
    prob = make_problem(job)
    s = job.settings
    st = prob.scene.settings
    e_gt = np.asarray(read_gt_array(a.gt, "youngs_modulus.npy"), np.float64)
    nu_gt = np.asarray(read_gt_array(a.gt, "poisson_ratio.npy"), np.float64)
    g_pos = np.asarray(read_gt_array(a.gt, "gaussian_positions.npy"), np.float64)[0]
    feats = prob.particle_appearance() if s.appearance > 0 else None
    w, idx = gaussian_weights(prob, feats)
    x0 = np.asarray(prob.x0.detach().cpu().numpy() if hasattr(prob.x0, "detach") else prob.x0, np.float64)
    _, nn = cKDTree(g_pos).query(x0)
    Et, nut = e_gt[nn], nu_gt[nn]
    names = prob.sim.slot_names()
    T0 = [t.detach().clone() for t in prob.initial_trajectories()]
    pairs_np = neighbour_pairs(x0, 1.6 * st.particle_spacing)
    pw = pair_weights(pairs_np, feats, s.appearance)
    lam = prob.weights.smooth if feats is not None else prob.weights.smooth_plain
    e_top = st.youngs_max
    dt = prob.tdtype

    def ma(E):
        return M.material_accuracy(np.exp((w * np.log(np.asarray(E, np.float64))[idx]).sum(1)), e_gt)

    def reg(E):
        le = np.log(np.asarray(E, np.float64))
        d2 = (le[pairs_np[:, 0]] - le[pairs_np[:, 1]]) ** 2
        return float(lam * (pw * d2).mean()) if len(pairs_np) else 0.0

    def rec(E, nu, trajs=None):
        t = (lambda v: torch.as_tensor(np.asarray(v, np.float64), dtype=dt, device=prob.tdev))
        tr = [torch.as_tensor(np.asarray(v), dtype=dt, device=prob.tdev) for v in trajs] if trajs else T0
        with torch.no_grad(), pinned_substep(prob, e_top):
            out = prob.loss(t(E), t(nu), tr)
        return float(out["rec"]), float(out["reg_traj"])

    def mat_field():
        return MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=dt, device=prob.tdev,
                             seed=s.seed, width=s.basis_width, features=feats, appearance=s.appearance,
                             centre_mask=~prob.held_particles())

    rows = []

    def row(name, E, nu, trajs=None, **extra):
        r_, rt = rec(E, nu, trajs)
        rg = reg(E)
        d = {"tag": a.tag, "model": name, "rec": r_, "reg": rg, "reg_traj": rt, "total": r_ + rg + rt,
             "ma": ma(E), "median_e": float(np.median(E)), **extra}
        rows.append(d)
        print(json.dumps(d), flush=True)
        return d

    # the truth, and its projection onto the finest basis
    row("truth (true path)", Et, nut)
    K = int(max(s.levels))
    mf = mat_field()
    mf.set_basis(K)
    mf.nu_basis = mf.B
    mf.w_nu = torch.zeros(K, dtype=dt, device=prob.tdev)
    mf.set_values(Et, nut)
    with torch.no_grad():
        Ep, nup = mf.youngs().cpu().numpy(), mf.poisson().cpu().numpy()
    row(f"truth projected on {K} bumps (true path)", Ep, nup)
    row("truth E, nu 0.3 uniform... (true path)", Et, np.full_like(nut, float(np.median(nut))))

    def run_fit(name, start=None):
        hist = []
        t0 = time.process_time()
        r = fit_bumps(prob, s, progress=False, log=lambda m: print("  log:", m, flush=True), start=start,
                      on_iteration=lambda it, lv, mat, trajs: hist.append(lv),
                      before_finest=parts_start_hook(s.parts_start) if s.parts_start > 0 and start is None else None)
        cpu = time.process_time() - t0
        trajs = [r.trajectories[n] for n in names]
        d = row(name, r.youngs, r.poisson, trajs, cpu_s=round(cpu, 1), history=[round(v, 6) for v in hist],
                final_loss=r.final_loss)
        row(name + "; its E on the true path", r.youngs, r.poisson)
        return r, d

    fit = None
    if not a.no_fit:
        fit, _ = run_fit(f"bumps fit ({a.iterations} it)")
        le_f, le_t = np.log(fit.youngs), np.log(Et)
        for tt in [float(v) for v in a.line.split(",") if v.strip()]:
            row(f"line t={tt:g} (fit -> truth, true path)", np.exp((1 - tt) * le_f + tt * le_t),
                (1 - tt) * fit.poisson + tt * nut)
    if a.from_truth:
        run_fit("bumps resumed from the projected truth",
                start={"youngs": Ep, "poisson": nup, "trajectories": {n: t.cpu().numpy() for n, t in zip(names, T0)}})
    if a.from_half and fit is not None:
        Eh = np.exp(0.5 * (np.log(fit.youngs) + np.log(Et)))
        run_fit("bumps resumed from halfway fit -> truth",
                start={"youngs": Eh, "poisson": 0.5 * (fit.poisson + nut),
                       "trajectories": {n: t.cpu().numpy() for n, t in zip(names, T0)}})
    print(f"\n{a.stage}: truth E {e_gt.min():.4g}-{e_gt.max():.4g} Pa; losses at the {e_top:.3g} Pa rung")
    print(f"{'model':52s} {'rec':>9s} {'reg':>9s} {'total':>9s} {'MA':>6s} {'median E':>9s}")
    for r in rows:
        print(f"{r['model'][:52]:52s} {r['rec']:9.5f} {r['reg']:9.5f} {r['total']:9.5f} {r['ma']:6.3f} "
              f"{r['median_e']:9.4g}")
    if a.out:
        with open(a.out, "a") as fh:
            for r in rows:
                fh.write(json.dumps(r, default=float) + "\n")


if __name__ == "__main__":
    main()
