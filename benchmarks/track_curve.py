"""Does the video's point-track term pin E down? The uniform-E curves of the image loss and of the
track term (fit/tracks_loss.py) side by side, with the true interaction (`--gt`), forward only, on
development data (refuses the validation split).

    python benchmarks/track_curve.py STAGE --gt CAPTURE/gt [--points 9] [--lo 0.25 --hi 4]

Prints per uniform E (multiples of the truth's median E): the image loss (L1 + SSIM + silhouette),
the track term, the mean track error in pixels, and the minimum of each curve (a parabola in log E
through the best point and its neighbours)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch


def parabola_min(x, y):
    j = int(np.clip(np.argmin(y), 1, len(y) - 2))
    a, b, _ = np.polyfit(np.log(x[j - 1:j + 2]), y[j - 1:j + 2], 2)
    return float(np.exp(-b / (2 * a))) if a > 0 else float(x[int(np.argmin(y))])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("--gt", required=True)
    ap.add_argument("--points", type=int, default=9)
    ap.add_argument("--lo", type=float, default=0.25)
    ap.add_argument("--hi", type=float, default=4.0)
    a = ap.parse_args()
    if "validation" in str(Path(a.gt).resolve()) or (Path(a.gt).parent / "SPLIT").exists():
        sys.exit("refused: the validation split is never used to tune anything")
    from physinteract_usd.app.fit import make_problem, prepare_fit

    t0 = time.process_time()
    job = prepare_fit(a.stage, iterations=1, contact_from=a.gt, settings_overrides={"track_weight": 1.0},
                      log=lambda *x: None, progress=False)
    prob = make_problem(job)
    prob.weights.track = 1.0
    e_true = float(np.median(np.load(Path(a.gt) / "youngs_modulus.npy")))
    P = len(prob.x0)
    nu = torch.full((P,), float(np.median(job.scene.poisson_ratio)), dtype=prob.tdtype)
    fs = np.exp(np.linspace(np.log(a.lo), np.log(a.hi), a.points))
    img, trk, px = [], [], []
    print(f"{a.stage}: {prob.tracks.n_tracks} tracks, noise scale {prob.tracks.sigma:.2f} px, "
          f"outline scale {prob.tracks.scale:.4f}; true median E {e_true:.4g} Pa")
    print("| E / E_true | image loss | track term | track error px |")
    print("|---:|---:|---:|---:|")
    for f in fs:
        with torch.no_grad():
            try:
                x, F = prob.simulate(torch.full((P,), e_true * f, dtype=prob.tdtype), nu)
            except Exception as exc:  # noqa: BLE001 - an unstable probe is reported, not fatal
                print(f"| {f:.3f} | unstable ({type(exc).__name__}) | | |")
                img.append(np.inf), trk.append(np.inf), px.append(np.nan)
                continue
            li, lt, e = [], [], []
            for k in range(1, prob.T):
                out = prob.render_frame(k, x[k], F[k])
                parts = prob.frame_loss(k, out)
                li.append(float(parts["total"] - parts["track"]))
                lt.append(float(parts["track"]))
                err = prob.tracks.errors_px(k, out["means"])
                if len(err):
                    e.append(float(err.mean()))
        img.append(np.mean(li)), trk.append(np.mean(lt)), px.append(np.mean(e))
        print(f"| {f:.3f} | {img[-1]:.5f} | {trk[-1]:.5f} | {px[-1]:.3f} |", flush=True)
    img, trk = np.array(img), np.array(trk)
    print(f"minimum (parabola in log E): image {parabola_min(fs, img):.3f} x E_true, "
          f"tracks {parabola_min(fs, trk):.3f} x E_true; CPU {time.process_time() - t0:.0f} s")


if __name__ == "__main__":
    main()
