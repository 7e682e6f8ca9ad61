"""select's candidates beside bumps' own field, on the same held-back frames (#24).

One stage (initialised, e.g. by benchmarks/suite.py) and its capture's gt/: runs the select
schedule once, keeping every candidate model it fitted on the training frames (uniform, parts,
the field nested on the kept model, the field from uniform), then the bumps schedule's own fit
(its full ladder and budget) on the same training frames only, and, for reference, bumps on all
frames. For each: training and held-back loss (mean and per frame), MA against the truth (per
Gaussian, the design's metric) and the fit's CPU seconds. With --parts, the parts' particles and
their true E (the truth per particle: the nearest Gaussian's).

    python benchmarks/select_candidates.py STAGE GT_DIR [--iterations 20] [--device cpu] [--out rows.jsonl]
        [--set key=value ...]  (FitSettings overrides for select, e.g. select_field_from_uniform_ladder=true)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _val(v: str):
    try:
        return json.loads(v)
    except json.JSONDecodeError:
        return v


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--tag", default="")
    ap.add_argument("--set", action="append", default=[], help="key=value FitSettings override (select only)")
    ap.add_argument("--skip-bumps-all", action="store_true", help="no reference bumps fit on all frames")
    ap.add_argument("--skip-bumps", action="store_true", help="select only")
    ap.add_argument("--field-uniform-iterations", type=int, default=None,
                    help="select's field from uniform: this many iterations (default: the field step's; 15 = what "
                         "the bumps ladder spends on its 8-bump level at 20 iterations)")
    ap.add_argument("--attach-grasped", action="store_true",
                    help="select's motion parts: the hand's grasped particles join the nearest free cluster")
    ap.add_argument("--section-cut", action="store_true",
                    help="select's motion parts: the score averaged over the object's thickness before the cut")
    ap.add_argument("--exposure-floor", type=float, default=0.0,
                    help="select's motion parts: particles strained less than this x the median (mean square "
                         "Hencky strain, the uniform model's rollout) get no part of their own (0.1: select's "
                         "EXPOSURE_FLOOR)")
    ap.add_argument("--dump", default=None,
                    help="an .npz of per-particle arrays (#24, where is the field wrong): every candidate's E, the "
                         "truth per particle, the parts' labels, the grasped / held particles, the uniform model's "
                         "score, and each model's strain exposure (rotation-free Hencky strain from its rollout, "
                         "max and mean square over the frames), also under the true material")
    a = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit.optimize import fit_bumps
    from physinteract_usd.fit.select import FrameView, fit_select, frame_losses
    from physinteract_usd.synth.gt import read_gt_array

    over = {k: _val(v) for k, v in (x.split("=", 1) for x in a.set)}
    log = lambda m: print(m, flush=True)  # noqa: E731
    job = prepare_fit(a.stage, iterations=a.iterations, contact_from=a.gt, device=a.device, warm=False,
                      progress=False, log=log, settings_overrides={"schedule": "select", **over})
    prob = make_problem(job)
    s = job.settings
    e_gt = read_gt_array(a.gt, "youngs_modulus.npy")
    rows = []

    results = []

    def row(name, r, train, val, cpu, **extra):
        results.append((name, r, train, val, cpu, extra))

    def emit(e_top):
        """Every model's losses at one substep (the stiffest model's: `select.pinned_substep`)."""
        for name, r, train, val, cpu, extra in results:
            tl, vl = frame_losses(prob, r, s, train, e_top), frame_losses(prob, r, s, val, e_top)
            out = {"tag": a.tag, "stage": str(a.stage), "candidate": name,
                   "ma": M.material_accuracy(r.youngs_gaussian, e_gt), "training": float(np.mean(tl)),
                   "held_back": float(np.mean(vl)), "held_back_frames": vl, "median_e": float(np.median(r.youngs)),
                   "cpu_s": cpu, "judged_at_e": e_top, **extra}
            rows.append(out)
            print(json.dumps({k: (round(v, 6) if isinstance(v, float) else v) for k, v in out.items()
                              if k != "stage"}), flush=True)

    cands: dict = {}
    c0 = time.process_time()
    rs = fit_select(prob, s, progress=False, log=log, candidates=cands,
                    field_uniform_iterations=a.field_uniform_iterations, attach_grasped=a.attach_grasped,
                    section_cut=a.section_cut, exposure_floor=a.exposure_floor)
    c_sel = round(time.process_time() - c0, 1)
    m = rs.model
    train, val = m["training_frames"], m["held_back_frames"]
    print(f"training frames {train}, held back {val}; chosen {m['chosen']}", flush=True)
    for name, r in cands.items():
        row(name, r, train, val, None)
    row("select (final, all frames)", rs, train, val, c_sel, chosen=m["chosen"],
        tests={k: v.get("why") for k, v in (m.get("tests") or {}).items()},
        select_losses={k: v.get("held_back") for k, v in (m.get("models") or {}).items()})
    # the truth per particle: the nearest Gaussian's at rest
    gm0 = np.asarray(rs.gaussian_means[0])
    _, nn = cKDTree(gm0).query(np.asarray(rs.positions[0]))
    e_p = e_gt[nn]
    if "parts" in cands:
        lab = np.asarray(cands["parts"].regions, np.int64)
        ys = np.asarray(prob.x0)[:, 1]
        parts = []
        for k in range(int(lab.max()) + 1):
            sel = lab == k
            parts.append({"part": k, "particles": int(sel.sum()), "fitted_e": float(np.median(cands["parts"].youngs[sel])),
                          "true_e_median": float(np.median(e_p[sel])), "true_e_p10_p90": [float(np.percentile(e_p[sel], 10)),
                                                                                         float(np.percentile(e_p[sel], 90))],
                          "y_range": [float(ys[sel].min()), float(ys[sel].max())]})
        print("parts vs truth: " + json.dumps(parts), flush=True)
        rows.append({"tag": a.tag, "candidate": "parts_vs_truth", "parts": parts,
                     "kind": (m.get("parts") or {}).get("kind")})
    if not a.skip_bumps:
        sb = dataclasses.replace(s, schedule="bumps")
        for k in over:       # the bumps schedule as the default runs it
            setattr(sb, k, getattr(type(s)(), k))
        c0 = time.process_time()
        rb = fit_bumps(FrameView(prob, train), sb, progress=False, log=None)
        row("bumps on the training frames", rb, train, val, round(time.process_time() - c0, 1))
        if not a.skip_bumps_all:
            c0 = time.process_time()
            ra = fit_bumps(prob, sb, progress=False, log=None)
            row("bumps on all frames (reference)", ra, train, val, round(time.process_time() - c0, 1))
    emit(max(float(np.max(r.youngs)) for _, r, *_ in results))
    if a.dump:
        dump(a.dump, prob, s, cands, results, e_p, rs)
    if a.out:
        with open(a.out, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")


def strain_exposure(prob, youngs, poisson, trajectories, effects=None) -> tuple[np.ndarray, np.ndarray]:
    """(max over frames, mean square over frames) of each particle's rotation-free strain (the norm
    of the Hencky strain log V, F = V R), from a rollout of the given material at its own rung."""
    import torch

    from physinteract_usd.fit.select import SimulationError, pinned_substep

    t = lambda v: torch.as_tensor(np.asarray(v), dtype=prob.tdtype, device=prob.tdev)  # noqa: E731
    with torch.no_grad(), pinned_substep(prob, float(np.max(youngs))):
        try:
            _, F = prob.simulate(t(youngs), t(poisson), trajectories, effects)
        except SimulationError:
            nan = np.full(len(prob.x0), np.nan)
            return nan, nan
    Fs = np.stack([np.asarray(F[k].detach().cpu(), np.float64) for k in range(1, prob.T)])   # (T-1, P, 3, 3)
    h = np.sqrt((np.log(np.clip(np.linalg.svd(Fs, compute_uv=False), 1e-6, None)) ** 2).sum(-1))
    return h.max(0), (h ** 2).mean(0)


def dump(path, prob, s, cands, results, e_p, rs):
    """The per-particle arrays of `--dump` (module doc)."""
    from physinteract_usd.fit.select import _result_inputs, grasped_particles, part_score

    out = {"x0": np.asarray(prob.x0), "e_true": np.asarray(e_p), "held": np.asarray(prob.held_particles(), bool),
           "grasped": grasped_particles(prob), "training": np.asarray(rs.model["training_frames"]),
           "held_back": np.asarray(rs.model["held_back_frames"])}
    if "parts" in cands:
        out["labels_parts"] = np.asarray(cands["parts"].regions, np.int64)
    if "uniform" in cands:
        sc = part_score(prob, cands["uniform"], s, rs.model["training_frames"])
        if sc is not None:
            out["score_uniform"] = sc
    for name, r, *_ in results:
        key = name.split(" (")[0].replace(" ", "_")
        out[f"E__{key}"] = np.asarray(r.youngs)
        _, trajs, eff = _result_inputs(prob, r, s)
        mx, ms = strain_exposure(prob, r.youngs, r.poisson, trajs, eff)
        out[f"strain_max__{key}"], out[f"strain_ms__{key}"] = mx, ms
        if name == "uniform":    # the truth's material on the uniform model's hand path and nu
            mx, ms = strain_exposure(prob, e_p, r.poisson, trajs, eff)
            out["strain_max__truth"], out["strain_ms__truth"] = mx, ms
    np.savez(path, **out)
    print(f"per-particle arrays: {path}", flush=True)


if __name__ == "__main__":
    main()
