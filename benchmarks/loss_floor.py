"""Where is a synthetic scene's loss floor? The fit's frame 0 (rest) and frame 1 against the video (#24).

On a stage init made from a synth capture (true contacts from its gt/), the fit's own loss terms
(L1, lambda_ssim (1 - SSIM), lambda_mask |M^ - M|^2; `FitProblem.frame_loss`) and the masked PSNR of:

  frame 0 (no simulation: the Gaussians bound to the particles at rest, F = I):
    fit            the fit's render (its background estimated from the video) vs the video
    fit, true bg   the same Gaussians over the synth's own background image
    truth (clean)  the video less its sensor noise (regenerated from gt.json's seed: the noise-free
                   truth render, to 8-bit rounding) vs the video: what a perfect model scores
    fit vs clean   the fit's render vs the noise-free truth: the model's own error
  frame 1 (one simulated frame at the truth's E and nu, each particle its nearest Gaussian's):
    the same rows, and "fit, no motion" (frame 0's render against frame 1's video) and the truth's
    and the model's motion at frame 1 in pixels (gravity sag before contact).

The loss terms are split by where the pixels lie: inside the union of the silhouettes, on a 2-px
band outside it (where the background estimate shows), and elsewhere. PNGs of each image and the
per-pixel error go to --out.

With --curve, the whole clip's loss at the truth's E times each scale (true path), rendered as the
fit renders (frame k's instant) and with the synth's shutter (motion blur), against the video and
its noise-free frames: does the noise or the shutter move the best E?

    python benchmarks/loss_floor.py STAGE GT_DIR [--out DIR] [--device cpu] [--no-frame1] [--json F]
        [--curve 0.5,0.7,1,1.4,2]
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


def terms(prob, k, rgb, alpha, weight_only=None) -> dict:
    """The fit's frame-k loss terms of an (H, W, 3) image and (H, W) alpha against the video."""
    import torch

    out = {"rgb": torch.as_tensor(rgb, dtype=prob.tdtype), "alpha": torch.as_tensor(alpha, dtype=prob.tdtype)}
    r = prob.frame_loss(k, out)
    w8 = prob.weights
    d = {"total": float(r["total"]), "l1": float(r["l1"]), "ssim_term": w8.ssim * (1 - float(r["ssim"])),
         "mask_term": w8.mask * float(r.get("mask", 0.0))}
    return d


def split_terms(prob, k, rgb, alpha, target, regions: dict) -> dict:
    """L1 and the silhouette term's share from each region (sums over the region / all weighted pixels)."""
    w = np.ones(rgb.shape[:2]) if prob.obs.hand_masks is None else (~prob.obs.hand_masks[k]).astype(float)
    l1 = np.abs(rgb - target).mean(-1) * w
    m = prob.obs.masks[k].astype(float)
    sq = (alpha - m) ** 2 * w
    n = w.sum()
    return {name: {"l1": float(l1[r].sum() / n), "mask": float(prob.weights.mask * sq[r].sum() / n),
                   "pixels": int((r & (w > 0)).sum())} for name, r in regions.items()}


def psnr_in(pred, true, sil_pred, sil_true, hand):
    from physinteract_usd import metrics as M

    keep = ~hand if hand is not None else np.ones(sil_true.shape, bool)
    return M.psnr(pred, true, (sil_pred | sil_true) & keep)


def save(path: Path, img: np.ndarray):
    from physinteract_usd.frames import write_image

    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.clip(img, 0, 1).astype(np.float32))


def upscale(img, s=4):
    return np.repeat(np.repeat(img, s, 0), s, 1)


def heat(err, scale):
    """|err| (H, W) as a white-to-red image, saturating at `scale`."""
    t = np.clip(err / scale, 0, 1)
    return np.stack([np.ones_like(t), 1 - t, 1 - t], -1)


def loss_curve(a, prob, job, scales, clean, render_with, bg) -> list[dict]:
    """The fit's loss (mean over frames 1..T-1, true path) at the truth's E x each scale, with the
    frames rendered at frame k's instant (the fit's renderer) and with the synth's shutter (the mean
    of renders at k - 0.5, k - 0.25, k, states interpolated linearly: `synth.generate._render_all`),
    against the video and against its noise-free frames. Where each curve's minimum lies says whether
    noise or the shutter moves the best E."""
    import torch
    from scipy.spatial import cKDTree

    from physinteract_usd.synth.gt import read_ground_truth, read_gt_array

    blur = int((read_ground_truth(a.gt).get("noise") or {}).get("blur_samples") or 1)
    e_gt = read_gt_array(a.gt, "youngs_modulus.npy")
    nu_gt = read_gt_array(a.gt, "poisson_ratio.npy")
    _, nn = cKDTree(read_gt_array(a.gt, "gaussian_positions.npy")[0]).query(np.asarray(prob.x0))
    t = lambda v: torch.as_tensor(v, dtype=prob.tdtype)  # noqa: E731
    out = []
    e_top = float(np.max(e_gt)) * max(scales)
    from physinteract_usd.fit.select import pinned_substep

    from physinteract_usd.errors import SimulationError

    for sc in scales:
        row = {"scale": sc}
        try:
            with torch.no_grad(), pinned_substep(prob, e_top):
                x, F = prob.simulate(t(e_gt[nn] * sc), t(nu_gt[nn]))
        except SimulationError as exc:
            row["error"] = str(exc).split(";")[0]
            out.append(row)
            print("curve " + json.dumps(row), flush=True)
            continue
        for shutter in ("instant", "synth"):
            for target in ("video", "clean"):
                if target == "clean" and clean is None:
                    continue
                tot = []
                for k in range(1, prob.T):
                    if shutter == "instant":
                        rgb, al = render_with(k, x[k], F[k], bg)
                    else:
                        acc = 0.0
                        for s in np.linspace(-0.5, 0.0, blur):
                            w = 1.0 + s
                            rgb_s, al_s = render_with(k, x[k] * w + x[k - 1] * (1 - w), F[k] * w + F[k - 1] * (1 - w), bg)
                            acc = acc + rgb_s
                        rgb, al = acc / blur, al_s          # the masks: the frame's instant (as the synth's)
                    if target == "clean":
                        saved = prob.frames[k].clone()
                        prob.frames[k] = t(clean[k])
                    tot.append(terms(prob, k, rgb, al)["total"])
                    if target == "clean":
                        prob.frames[k] = saved
                row[f"{shutter}_{target}"] = float(np.mean(tot))
        out.append(row)
        print("curve " + json.dumps(row), flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None, help="folder for the PNGs")
    ap.add_argument("--no-frame1", action="store_true", help="frame 0 only (no simulation)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--curve", default=None, help="scales of the truth's E (e.g. 0.5,0.7,1,1.4,2): the loss over the "
                    "whole clip (true path) with the fit's instantaneous frames and with the synth's shutter")
    a = ap.parse_args(argv)

    import cv2
    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from scipy.spatial import cKDTree

    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit.problem import FitProblem, Observations
    from physinteract_usd.render import render
    from physinteract_usd.synth.generate import background_image, noise_free_frames
    from physinteract_usd.synth.gt import read_ground_truth, read_gt_array

    t0 = time.process_time()
    gt = read_ground_truth(a.gt)
    job = prepare_fit(a.stage, iterations=1, contact_from=a.gt, device=a.device, warm=False, progress=False,
                      log=lambda m: None)
    prob = make_problem(job)
    obs = prob.obs
    H, W = obs.frames.shape[1:3]
    true_bg = background_image(W, H, int(gt.get("seed", 0)))
    clean = noise_free_frames(gt, obs.frames)
    out = Path(a.out) if a.out else None
    rows, info = [], {"stage": a.stage, "gt": a.gt, "noise_sigma": (gt.get("noise") or {}).get("sigma"),
                      "blur_samples": (gt.get("noise") or {}).get("blur_samples"),
                      "particles": int(len(prob.x0)), "grid": list(prob.grid.resolution)}
    bg_fit = prob.background.cpu().numpy()
    x0 = torch.as_tensor(np.asarray(prob.x0), dtype=prob.tdtype)
    I = torch.eye(3, dtype=prob.tdtype).expand(len(x0), 3, 3).contiguous()

    def render_with(k, x, F, bg):
        means, covs = prob.gaussians_at(x, F)
        with torch.no_grad():
            r = render(means, covs, prob.colors, prob.opacities, prob.cameras[k],
                       background=torch.as_tensor(bg, dtype=prob.tdtype))
        return r["rgb"].cpu().numpy(), r["alpha"].cpu().numpy()

    def report(k, name, rgb, alpha, target_name="video"):
        target = obs.frames[k] if target_name == "video" else clean[k]
        if target_name != "video":       # score against the clean frame: swap it in for the row
            saved = prob.frames[k].clone()
            prob.frames[k] = torch.as_tensor(target, dtype=prob.tdtype)
        d = terms(prob, k, rgb, alpha)
        if target_name != "video":
            prob.frames[k] = saved
        sil = alpha > 0.5
        hand = None if obs.hand_masks is None else obs.hand_masks[k]
        union = sil | obs.masks[k]
        band = cv2.dilate(union.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        regions = {"in_silhouettes": union, "band_2px": band & ~union, "elsewhere": ~band}
        row = {"frame": k, "model": name, "against": target_name, **d,
               "psnr_masked": psnr_in(rgb, target, sil, obs.masks[k], hand),
               "split": split_terms(prob, k, rgb, alpha, target, regions)}
        rows.append(row)
        sp = row["split"]
        print(f"{k:5d} {name:26s} {target_name:6s} {d['total']:8.5f} {d['l1']:8.5f} {d['ssim_term']:8.5f} "
              f"{d['mask_term']:8.5f} {row['psnr_masked']:7.2f}   "
              + "  ".join(f"{n}: L1 {v['l1']:.5f} M {v['mask']:.5f}" for n, v in sp.items()), flush=True)
        return row

    print(f"{a.stage}: {info['particles']} particles, grid {info['grid']}, noise sigma {info['noise_sigma']}, "
          f"blur samples {info['blur_samples']}")
    print(f"{'frame':5s} {'model':26s} {'vs':6s} {'total':>8s} {'L1':>8s} {'.2(1-S)':>8s} {'mask':>8s} {'PSNRm':>7s}")
    # ---------------------------------------------------------------- frame 0: the static render
    rgb0, al0 = render_with(0, x0, I, bg_fit)
    rgb0t, _ = render_with(0, x0, I, true_bg)
    report(0, "fit", rgb0, al0)
    report(0, "fit, true background", rgb0t, al0)
    if clean is not None:
        # the truth's clean frame 0 with the fit's alpha (the same Gaussians at rest: the same alpha)
        report(0, "truth (noise-free)", clean[0], al0)
        report(0, "fit", rgb0, al0, target_name="clean")
        report(0, "fit, true background", rgb0t, al0, target_name="clean")
    info["background_error"] = {
        "mean_abs_all": float(np.abs(bg_fit - true_bg).mean()),
        "mean_abs_in_band": float(np.abs(bg_fit - true_bg).mean(-1)[
            (cv2.dilate(obs.masks[0].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & ~obs.masks[0]].mean())}
    if out is not None:
        s = 4
        save(out / "f0_video.png", upscale(obs.frames[0], s))
        save(out / "f0_fit.png", upscale(rgb0, s))
        save(out / "f0_fit_truebg.png", upscale(rgb0t, s))
        save(out / "f0_err_fit.png", upscale(heat(np.abs(rgb0 - obs.frames[0]).mean(-1), 0.1), s))
        save(out / "f0_err_fit_truebg.png", upscale(heat(np.abs(rgb0t - obs.frames[0]).mean(-1), 0.1), s))
        save(out / "f0_bg_fit.png", upscale(bg_fit, s))
        save(out / "f0_bg_err.png", upscale(heat(np.abs(bg_fit - true_bg).mean(-1), 0.1), s))
        save(out / "f0_alpha_vs_mask.png", upscale(np.stack([al0, obs.masks[0].astype(float), np.zeros_like(al0)], -1), s))
        if clean is not None:
            save(out / "f0_clean.png", upscale(clean[0], s))
            save(out / "f0_err_fit_vs_clean.png", upscale(heat(np.abs(rgb0 - clean[0]).mean(-1), 0.1), s))

    # ---------------------------------------------------------------- frame 1: one simulated frame
    if not a.no_frame1:
        e_gt = read_gt_array(a.gt, "youngs_modulus.npy")
        nu_gt = read_gt_array(a.gt, "poisson_ratio.npy")
        gpos = read_gt_array(a.gt, "gaussian_positions.npy")
        _, nn = cKDTree(gpos[0]).query(np.asarray(prob.x0))
        # a two-frame problem (frames 0-1: one simulated frame), the 14-frame problem's background
        o2 = Observations(obs.frames[:2], None if obs.masks is None else obs.masks[:2],
                          None if obs.hand_masks is None else obs.hand_masks[:2])
        cs = [dataclasses.replace(c, trajectory=None if c.trajectory is None else np.asarray(c.trajectory)[:2])
              for c in job.contacts]
        p2 = FitProblem(job.scene, o2, cs, effects=job.effects, device=a.device)
        p2.background = prob.background
        t1 = time.process_time()
        with torch.no_grad():
            x, F = p2.simulate(torch.as_tensor(e_gt[nn], dtype=p2.tdtype), torch.as_tensor(nu_gt[nn], dtype=p2.tdtype))
        info["sim_frame1_cpu_s"] = time.process_time() - t1
        info["substeps"] = int(p2.sim.substeps)
        rgb1, al1 = render_with(1, x[1], F[1], bg_fit)
        rgb1t, _ = render_with(1, x[1], F[1], true_bg)
        report(1, "fit at truth E", rgb1, al1)
        report(1, "fit at truth E, true bg", rgb1t, al1)
        report(1, "fit, no motion (rest)", rgb0, al0)
        if clean is not None:
            report(1, "truth (noise-free)", clean[1], al1)
            report(1, "fit at truth E", rgb1, al1, target_name="clean")
            report(1, "fit, no motion (rest)", rgb0, al0, target_name="clean")
        # motion at frame 1 in pixels: the truth's Gaussians and the model's
        cam = prob.cameras[1]
        means1, _ = prob.gaussians_at(x[1], F[1])
        u_t1, _ = cam.project(gpos[1])
        u_t0, _ = cam.project(gpos[0])
        u_m1, _ = cam.project(means1.detach().cpu().numpy().astype(np.float64))
        info["motion_px_frame1"] = {"truth_mean": float(np.linalg.norm(u_t1 - u_t0, axis=1).mean()),
                                    "truth_max": float(np.linalg.norm(u_t1 - u_t0, axis=1).max()),
                                    "model_mean": float(np.linalg.norm(u_m1 - u_t0, axis=1).mean()),
                                    "model_vs_truth_mean": float(np.linalg.norm(u_m1 - u_t1, axis=1).mean()),
                                    "truth_sag_mm_max": float(1000 * np.abs(gpos[1] - gpos[0])[:, 1].max())}
        if out is not None:
            save(out / "f1_video.png", upscale(obs.frames[1], s))
            save(out / "f1_fit_truthE.png", upscale(rgb1, s))
            save(out / "f1_err_fit.png", upscale(heat(np.abs(rgb1 - obs.frames[1]).mean(-1), 0.1), s))
            if clean is not None:
                save(out / "f1_err_fit_vs_clean.png", upscale(heat(np.abs(rgb1 - clean[1]).mean(-1), 0.1), s))
                save(out / "f1_err_rest_vs_clean.png", upscale(heat(np.abs(rgb0 - clean[1]).mean(-1), 0.1), s))
    # ---------------------------------------------------------------- the loss over E: noise and shutter
    if a.curve:
        curve = loss_curve(a, prob, job, [float(v) for v in a.curve.split(",")], clean, render_with, bg_fit)
        info["curve"] = curve
    info["cpu_s"] = time.process_time() - t0
    print(json.dumps(info, indent=None, default=float))
    if a.json:
        Path(a.json).write_text(json.dumps({"info": info, "rows": rows}, indent=1, default=float))


if __name__ == "__main__":
    main()
