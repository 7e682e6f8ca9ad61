"""Why a stiff capture goes non-finite at the TRUE interaction (#24): where, when and how.

world_simcheck.py's set-up (our particles, the truth's contacts, hand path, supports, floor, per-particle E x
factor), then, instead of a score, a post-mortem of the rollout:

- per frame up to the failure: the largest particle speed and its CFL number (speed x dt / dx), the range of
  J = det F and of F's singular values, per group (held by a support, grasped / under the hand, the rest), and
  for a sphere collider: its speed x dt / dx and how deep it sits inside our particles and the truth's (the
  hand moving through the object);
- the failing frame replayed substep by substep from its start (eagerly, the whole grid): the first substep
  with a non-finite or runaway particle (speed > 10 x the frame's start max), which particles, their group,
  their distance to the support / the hand, and their J, stretch and speed over the substeps just before.

    python benchmarks/stiff_blowup.py --work data/world_stiff --seed 141 --cap 1500 --factor 1 --rule default

A diagnosis tool for the development split (refuses validation). Results in docs/benchmarks/world_fits.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import world_simcheck as wsc  # noqa: E402
from physinteract_usd import simulation  # noqa: E402
from physinteract_usd.errors import SimulationError  # noqa: E402
from world_bias import gt_dir, prepare_stage  # noqa: E402
from world_fit import add_ground  # noqa: E402


def fstats(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(F).all(axis=(1, 2))
    J = np.full(len(F), np.nan)
    sv = np.full((len(F), 3), np.nan)
    J[ok] = np.linalg.det(F[ok])
    sv[ok] = np.linalg.svd(F[ok], compute_uv=False)
    return J, sv


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--cap", type=int, default=1500)
    ap.add_argument("--factor", type=float, default=1.0)
    ap.add_argument("--rule", default="default", choices=list(wsc.RULES))
    ap.add_argument("--steps", default="fit", choices=("fit", "truth"))
    ap.add_argument("--substeps", type=int, default=0, help="force this many substeps a frame (0: --steps)")
    ap.add_argument("--padding", type=float, default=0.0,
                    help="init's --padding instead of the capture's suggested one (0: the suggested; a check of the domain)")
    ap.add_argument("--scratch", default="/tmp/stiff_blowup")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if "val" in str(a.work):
        print("stiff_blowup.py: error: --work: refuses the validation split", file=sys.stderr)
        return 2
    from scipy.spatial import cKDTree

    from physinteract_usd.app.fit import make_problem, prepare_fit

    work, n = Path(a.work), f"dev_{a.seed:04d}"
    gt = gt_dir(work, n)
    g = json.loads((gt / "gt.json").read_text())
    out = Path(a.scratch) / f"{n}_{a.cap}"
    if a.padding > 0:     # the same stage on a larger domain (same dx: grid auto counts the thinnest part)
        import world_bias
        from physinteract_usd import api
        init0 = api.init
        world_bias.api = type("A", (), {"init": staticmethod(lambda *x, **k: init0(*x, **{**k, "padding": a.padding}))})
    prepare_stage(work / n, gt, out, a.cap)
    stage = out / "scene.usda"
    if g.get("floor"):
        add_ground(stage, g["floor"]["height"], g["floor"].get("friction", 0.5))
    tr = np.load(gt / "particles.npz")
    rest, pos = tr["rest"], tr["positions"]
    simulation.PIN_RULE = wsc.RULES[a.rule]
    nsub = a.substeps or (int(g["gt_sim"]["substeps_per_frame"]) if a.steps == "truth" else None)
    with wsc.forced(nsub, "rate"):
        job = prepare_fit(stage, iterations=1, contact_from=gt, device="cpu", log=lambda *x: None, warm=False)
        prob = make_problem(job)
        x0 = np.asarray(prob.x0)
        nn = cKDTree(rest).query(x0)[1]
        E_t = torch.as_tensor(tr["E"][nn], dtype=prob.tdtype) * a.factor
        nu_t = torch.as_tensor(tr["nu"][nn], dtype=prob.tdtype)
        sim = prob.sim
        err = None
        try:
            with torch.no_grad():
                prob.simulate(E_t, nu_t)
        except SimulationError as exc:
            err = exc
    ro, model = sim.rollout, sim.model
    dt, dx, S = float(model.dt), float(model.grid.dx), int(model.substeps)
    fps = float(sim.scene.fps)
    P = len(x0)
    held = np.zeros(P, bool)
    grasped = np.zeros(P, bool)
    col = None
    for c in sim.control.contacts:
        if c.type == "fixed":
            held[np.asarray(c.indices, int)] = True
        elif c.type == "pointAdherent":
            grasped[np.asarray(c.indices, int)] = True
        elif c.type == "pointNonAdherent":
            col = c
    hand_tr = None
    for c in sim.control.contacts:
        if c.trajectory is not None:
            t = c.trajectory
            hand_tr = t.detach().cpu().numpy() if torch.is_tensor(t) else np.asarray(t)
    sup = g.get("supports") or []
    sup_c = np.asarray(sup[0]["centre"]) if sup else None
    it = g["interaction"]
    head = {"scene": n, "factor": a.factor, "rule": a.rule, "steps": a.steps, "particles": P, "dx": dx, "dt": dt,
            "substeps": S, "fps": fps, "e_median": float(np.median(E_t.numpy())), "held": int(held.sum()),
            "grasped": int(grasped.sum()), "grasp": it.get("grasp_frame"), "release": it.get("release_frame"),
            "error": None if err is None else str(err).splitlines()[0][:200],
            "p_wave_cfl_at_E": float(np.sqrt(E_t.max().item() * (1 - nu_t.max().item()) / ((1 + nu_t.max().item()) * (1 - 2 * nu_t.max().item()))
                                             / float(sim.scene.settings.density)) * dt / dx)}
    print(json.dumps(head))
    ck = {k: v.detach().cpu().numpy() for k, v in ro.ck.t.items()}
    X, V, Fs = ck["x"], ck["v"], ck["F"]
    T = X.shape[0]
    fail = getattr(err, "frame", None) if err is not None else None
    last = (fail if fail is not None else T) - 1
    vlo, vhi = np.asarray(model.grid.valid_lower), np.asarray(model.grid.valid_upper)
    head["grid_valid"] = [vlo.round(4).tolist(), vhi.round(4).tolist()]
    print(json.dumps({"grid_valid": head["grid_valid"]}))
    groups = {"held": held, "grasped": grasped, "rest": ~(held | grasped)}
    rows = []
    for k in range(0, min(last + 2, T)):
        J, sv = fstats(Fs[k])
        sp = np.linalg.norm(V[k], axis=1)
        r = {"frame": k, "finite": bool(np.isfinite(X[k]).all() and np.isfinite(V[k]).all())}
        xk = X[k][np.isfinite(X[k]).all(axis=1)]
        if len(xk):     # the nearest particle to the valid box's faces, in cells (0: at the wall)
            r["wall_cells"] = float(min((xk - vlo).min(), (vhi - xk).min()) / dx)
        for gname, m in groups.items():
            if not m.any():
                continue
            s = np.where(np.isfinite(sp[m]), sp[m], np.inf)
            r[gname] = {"vmax": float(s.max()), "cfl": float(s.max() * dt / dx), "Jmin": float(np.nanmin(J[m])),
                        "Jmax": float(np.nanmax(J[m])), "svmax": float(np.nanmax(sv[m])), "svmin": float(np.nanmin(sv[m]))}
        if hand_tr is not None and k < len(hand_tr):
            hv = np.linalg.norm(hand_tr[k] - hand_tr[k - 1]) * fps if k else 0.0
            r["hand_v"] = float(hv)
            r["hand_cfl"] = float(hv * dt / dx)
            if col is not None:
                d_our = np.linalg.norm(X[k] - hand_tr[k], axis=1)
                d_tru = np.linalg.norm(pos[min(k, len(pos) - 1)] - hand_tr[k], axis=1)
                r["inside_ours"] = int((d_our < col.radius).sum())
                r["inside_truth"] = int((d_tru < col.radius).sum())
                r["depth_ours_mm"] = float(1e3 * (col.radius - np.nanmin(d_our)))
                r["depth_truth_mm"] = float(1e3 * (col.radius - d_tru.min()))
        if k < len(pos):
            # frame-difference speeds (the truth has no velocities): ours the same way, comparable
            r["truth_vmax"] = float(np.linalg.norm(pos[k] - pos[k - 1], axis=1).max() * fps) if k else 0.0
            if k and r["finite"]:
                r["fd_vmax"] = float(np.linalg.norm(X[k] - X[k - 1], axis=1).max() * fps)
        rows.append(r)
        print(json.dumps(r))
    if fail is None:    # world_simcheck's 3-D error (mean |our displacement - the nearest truth particle's|)
        Tn = min(T, len(pos))
        e = wsc.compare(X[:Tn], x0, pos[:Tn], nn)
        rel = it.get("release_frame")
        head["err_all_mm"] = float(1e3 * e[1:].mean())
        head["err_after_mm"] = float(1e3 * e[rel + 1:].mean()) if rel is not None and rel + 1 < Tn else None
        print(json.dumps({"err_all_mm": head["err_all_mm"], "err_after_mm": head["err_after_mm"]}))
    sub = []
    if fail is not None:
        k = fail - 1
        sol = ro.solver
        sol.set_box(None)
        sol.clear_all()
        a_, b_ = ro._pp
        a_.assign(ro.ck.frame(k))
        s0 = a_.numpy()
        v_ref = max(float(np.linalg.norm(s0["v"], axis=1).max()), 1e-6)
        hist = []
        first = None
        for s in range(S):
            sol.step(a_, b_, k, s)
            a_, b_ = b_, a_
            st = a_.numpy()
            sp = np.linalg.norm(st["v"], axis=1)
            bad = ~np.isfinite(sp) | (sp > 10 * v_ref) | ~np.isfinite(st["F"]).all(axis=(1, 2))
            hist.append({"x": st["x"], "v": st["v"], "F": st["F"]})
            if len(hist) > 160:
                hist.pop(0)
            if bad.any() and first is None:
                first = (s, np.nonzero(bad)[0])
                break
        if first is None:
            print(json.dumps({"replay": "no runaway in the replayed frame", "frame": fail}))
        else:
            s, idx = first
            xi = s0["x"][idx]
            info = {"replay_frame": fail, "substep": s, "of": S, "n_bad": int(len(idx)), "frame_start_vmax": v_ref,
                    "bad_held": int(held[idx].sum()), "bad_grasped": int(grasped[idx].sum()),
                    "bad_idx": idx[:20].tolist()}
            if sup_c is not None:
                dsup = np.linalg.norm(xi - sup_c, axis=1)
                info["bad_dist_support_mm"] = [float(np.min(dsup) * 1e3), float(np.median(dsup) * 1e3), float(np.max(dsup) * 1e3)]
                info["support_radius_mm"] = float(sup[0]["radius"] * 1e3)
                info["all_dist_support_mm_median"] = float(np.median(np.linalg.norm(s0["x"] - sup_c, axis=1)) * 1e3)
            if hand_tr is not None:
                dh = np.linalg.norm(xi - hand_tr[min(k, len(hand_tr) - 1)], axis=1)
                info["bad_dist_hand_mm"] = [float(np.min(dh) * 1e3), float(np.median(dh) * 1e3), float(np.max(dh) * 1e3)]
            info["bad_pos_frame_start"] = s0["x"][idx[:5]].round(4).tolist()
            info["bad_wall_cells"] = float(min((s0["x"][idx] - vlo).min(), (vhi - s0["x"][idx]).min()) / dx)
            info["bad_rest_pos"] = x0[idx[:5]].round(4).tolist()
            info["rest_bbox"] = [x0.min(0).round(3).tolist(), x0.max(0).round(3).tolist()]
            tl = []
            for j in list(range(max(0, len(hist) - 150), len(hist) - 4, 10)) + list(range(max(0, len(hist) - 4), len(hist))):
                h = hist[j]
                J, sv = fstats(h["F"][idx])
                spd = np.linalg.norm(h["v"][idx], axis=1)
                tl.append({"substep": s - len(hist) + 1 + j, "vmax": float(np.nanmax(np.where(np.isfinite(spd), spd, np.inf))),
                           "cfl": float(np.nanmax(np.where(np.isfinite(spd), spd, np.inf)) * dt / dx),
                           "Jmin": float(np.nanmin(J)) if np.isfinite(J).any() else None,
                           "Jmax": float(np.nanmax(J)) if np.isfinite(J).any() else None,
                           "svmax": float(np.nanmax(sv)) if np.isfinite(sv).any() else None,
                           "svmin": float(np.nanmin(sv)) if np.isfinite(sv).any() else None,
                           # signed: < 0 past the valid box's face (the stencil clamped to the grid's last nodes)
                           "wall_cells": float(min((h["x"][idx] - vlo).min(), (vhi - h["x"][idx]).min()) / dx)})
            info["timeline"] = tl
            # the whole body at the substep before: the worst J anywhere, where
            J, sv = fstats(hist[-2]["F"] if len(hist) > 1 else s0["F"])
            w = int(np.nanargmax(np.abs(np.log(np.where(np.isfinite(J) & (J > 0), J, 1e-9)))))
            info["worst_J_before"] = {"idx": w, "J": float(J[w]), "held": bool(held[w]), "grasped": bool(grasped[w])}
            print(json.dumps(info))
            sub.append(info)
    if a.json:
        Path(a.json).write_text(json.dumps({"head": head, "frames": rows, "replay": sub}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
