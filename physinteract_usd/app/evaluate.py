"""`evaluate`: score a fitted stage against a synthetic capture's ground truth (the design's
metrics): MA (and the best single E's MA), PSNR (full and masked), SSIM, silhouette IoU from
re-rendering the stage's animation, and the Gaussians' 3D position error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .. import metrics as M
from ..devices import torch_device
from ..errors import InputError
from ..render import covariance_from_scales_quats, estimate_background, render
from ..synth.gt import read_ground_truth, read_gt_array
from ..usd.fit_io import read_splat_animation
from .adapters import hand_masks, load_observations, read_scene, true_hand_masks


def _truth_cell(gt_dir: Path) -> tuple[float | None, str | None]:
    """(The truth simulation's grid cell from gt.json's gt_sim, why it could not be read or None). Only the
    resolution note depends on it, so an unreadable gt.json is said, not fatal; an older capture's gt.json
    without gt_sim.dx is silently unchecked."""
    try:
        return float(read_ground_truth(gt_dir)["gt_sim"]["dx"]), None
    except InputError as exc:
        return None, f"{exc}: the truth's resolution was not checked"
    except (KeyError, TypeError, ValueError):
        return None, None


def evaluate(stage_path, gt_dir, device="cpu") -> dict:
    """{"ma", "ma_best_uniform", "best_uniform_e", "psnr", "psnr_masked", "ssim", "iou",
    "position_error_m", "frames": [per-frame metrics], "by_truth_level": [where MA is lost, per material
    of the truth, with the truth's strain there], "calibration": {the fit's confidence against its hits},
    "truth_resolution": {whether the truth was simulated finer than this fit (`metrics.truth_resolution`)},
    "truth_resolution_unchecked": why gt.json could not say it, or None}."""
    gt_dir = Path(gt_dir)
    for f in ("youngs_modulus.npy", "gaussian_positions.npy"):
        if not (gt_dir / f).exists():
            raise InputError(gt_dir / f, "file not found (is this a synth capture's gt/ folder?)")
    sd = read_scene(stage_path)
    anim = read_splat_animation(stage_path)
    if anim["youngsModulus"] is None or not anim["times"]:
        raise InputError(stage_path, "has no fitted material or animation: run `physinteract-usd fit` first")
    e_gt = read_gt_array(gt_dir, "youngs_modulus.npy")
    if len(e_gt) != len(anim["youngsModulus"]):
        raise InputError(gt_dir / "youngs_modulus.npy", f"{len(e_gt)} Gaussians, the stage has {len(anim['youngsModulus'])}")
    obs = load_observations(sd, with_hand_masks=False)
    T = min(len(anim["times"]), sd.n_frames)
    hands = true_hand_masks(gt_dir, T)
    if hands is None:
        hands = hand_masks(sd, T)
    pos_gt = read_gt_array(gt_dir, "gaussian_positions.npy")[:T]
    pos = np.stack(anim["positions"][:T])
    dev = torch_device(device)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)  # noqa: E731
    cover = obs.masks
    bg = t(estimate_background(obs.frames, cover, dilate=2) if cover is not None else np.median(obs.frames, axis=0))
    g0 = sd.gaussians
    col, op = t(g0.colors), t(g0.opacities)
    frames = []
    for k in range(T):
        cov = covariance_from_scales_quats(t(anim["scales"][k]), t(anim["quats"][k]))
        with torch.no_grad():
            out = render(t(pos[k]), cov, col, op, sd.camera.at(k), background=bg)
        pred = out["rgb"].cpu().numpy()
        sil = out["alpha"].cpu().numpy() > 0.5
        true_sil = obs.masks[k] if obs.masks is not None else sil
        d = M.frame_metrics(pred, obs.frames[k], sil, true_sil, None if hands is None else hands[k])
        d["frame"] = k
        frames.append(d)
    summary = M.summarize(frames)
    ma_uniform, e_uniform = M.best_uniform_ma(e_gt)
    e_fit = anim["youngsModulus"]
    exposure = M.peak_green_strain(pos_gt[0], pos_gt)
    conf = anim["confidence"]
    truth_cell, unchecked = _truth_cell(gt_dir)
    return {"truth_resolution": M.truth_resolution(truth_cell, float(sd.settings.cell_size)),
            "truth_resolution_unchecked": unchecked,
            "by_truth_level": M.ma_by_truth_level(e_fit, e_gt, conf, exposure),
            "calibration": None if conf is None else M.confidence_calibration(e_fit, e_gt, conf),
            "ma": M.material_accuracy(anim["youngsModulus"], e_gt), "ma_best_uniform": ma_uniform,
            "best_uniform_e": e_uniform, "psnr": summary["psnr"], "psnr_masked": summary["psnr_masked"],
            "ssim": summary["ssim"], "iou": summary["iou"], "position_error_m": M.position_error_m(pos, pos_gt),
            "frames": frames}
