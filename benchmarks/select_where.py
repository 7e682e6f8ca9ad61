"""Where is a fitted field wrong? (#24) Reads the per-particle arrays of `select_candidates.py --dump`
and tabulates, for each candidate, the per-particle log-E error against the truth and the share
within the MA tolerance (20%), by the particles' strain exposure (quartiles of the rotation-free
strain's mean square over the clip under the true material, or a model's own), by the motion parts,
by bands of the true E, and for the hand's grasped particles.

    python benchmarks/select_where.py DUMP.npz [--exposure truth|uniform|...] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

TOL = 0.2


def table(d, exposure: str = "truth") -> dict:
    e_t = d["e_true"]
    free = ~d["held"]
    cands = [k[3:] for k in d.files if k.startswith("E__")]
    expo = d[f"strain_ms__{exposure}"]
    q = np.quantile(expo[free], [0.25, 0.5, 0.75])
    band = np.digitize(expo, q)                      # 0 (least strained) .. 3
    tb = np.digitize(np.log(e_t), np.quantile(np.log(e_t[free]), [1 / 3, 2 / 3]))
    groups = {f"exposure Q{b + 1}": free & (band == b) for b in range(4)}
    groups.update({f"true E band {b} ({np.exp(np.log(e_t[free & (tb == b)]).mean()):.3g} Pa)": free & (tb == b)
                   for b in range(3)})
    if "labels_parts" in d.files:
        lab = d["labels_parts"]
        groups.update({f"motion part {k}": free & (lab == k) for k in range(int(lab.max()) + 1)})
    groups["grasped"] = free & d["grasped"]
    groups["all free"] = free
    y = d["x0"][:, 1]
    out = {"exposure": exposure, "exposure_quartiles": q.tolist(), "groups": {}}
    for g, m in groups.items():
        if not m.any():
            continue
        row = {"n": int(m.sum()), "y": [round(float(y[m].min()), 3), round(float(y[m].max()), 3)],
               "exposure_median": float(np.median(expo[m])), "true_e_median": float(np.median(e_t[m]))}
        for c in cands:
            r = np.log(d[f"E__{c}"][m] / e_t[m])
            row[c] = {"within20": float(np.mean(np.abs(np.exp(r) - 1) <= TOL)), "mean_log_err": float(r.mean()),
                      "median_e": float(np.median(d[f"E__{c}"][m]))}
        out["groups"][g] = row
    # the error's rank correlation with the exposure, per candidate
    from scipy.stats import spearmanr

    out["spearman_abs_err_vs_exposure"] = {
        c: float(spearmanr(np.abs(np.log(d[f"E__{c}"][free] / e_t[free])), expo[free])[0]) for c in cands}
    if "score_uniform" in d.files:
        out["spearman_abs_score_vs_exposure"] = float(spearmanr(np.abs(d["score_uniform"][free]), expo[free])[0])
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dump")
    ap.add_argument("--exposure", default="truth")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    d = np.load(a.dump)
    t = table(d, a.exposure)
    if a.json:
        print(json.dumps(t))
        return
    cands = [k[3:] for k in d.files if k.startswith("E__")]
    print(f"exposure: {t['exposure']} (quartiles {', '.join(f'{v:.2e}' for v in t['exposure_quartiles'])})")
    print("group | n | y | exposure | true E | " + " | ".join(f"{c}: within 20% / mean log err / E" for c in cands))
    for g, r in t["groups"].items():
        print(f"{g} | {r['n']} | {r['y'][0]:.3f}..{r['y'][1]:.3f} | {r['exposure_median']:.2e} | {r['true_e_median']:.4g} | "
              + " | ".join(f"{r[c]['within20']:.2f} / {r[c]['mean_log_err']:+.2f} / {r[c]['median_e']:.4g}" for c in cands))
    print("spearman |log err| vs exposure:", {k: round(v, 2) for k, v in t["spearman_abs_err_vs_exposure"].items()})
    if "spearman_abs_score_vs_exposure" in t:
        print("spearman |score| vs exposure:", round(t["spearman_abs_score_vs_exposure"], 2))


if __name__ == "__main__":
    main()
