"""Metrics, in one place (numpy; no torch, no USD).

- PSNR over the full frame, and inside the union of the true and rendered silhouettes (the honest
  one: a mostly-background frame cannot inflate it).
- SSIM is ``skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1, channel_axis=-1)``: 11x11 Gaussian window (sigma 1.5,
  truncated at 3.5 sigma), K1 = 0.01, K2 = 0.03, mean over the map cropped by the window radius.
- Silhouette IoU; 2D track error in pixels; 3D position error in metres.
- Material accuracy MA: the share of Gaussians whose predicted E is within 20% of the truth,
  and the MA of the best uniform E (what a single number could at most reach).
- Where MA is lost (`ma_by_truth_level`): MA, share and E ratio per material of the truth, with the
  truth's own strain there (`peak_green_strain`: a material that never strains is not in the video);
  and whether the fit's per-Gaussian confidence (its claimed probability of being within 20%) holds
  (`confidence_calibration`).
"""

from __future__ import annotations

import numpy as np

MA_TOLERANCE = 0.2


def psnr(pred: np.ndarray, true: np.ndarray, mask: np.ndarray | None = None, data_range: float = 1.0) -> float:
    """PSNR in dB over all pixels (and channels), or over the pixels where `mask` is true."""
    pred = np.asarray(pred, dtype=np.float64)
    true = np.asarray(true, dtype=np.float64)
    err = (pred - true) ** 2
    if mask is not None:
        mask = np.asarray(mask, bool)
        if not mask.any():
            return float("nan")
        err = err[mask]
    mse = float(np.mean(err))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range ** 2 / mse))


def psnr_masked(pred, true, sil_pred, sil_true, data_range: float = 1.0) -> float:
    """PSNR inside the union of the true and rendered silhouettes."""
    return psnr(pred, true, np.asarray(sil_pred, bool) | np.asarray(sil_true, bool), data_range)


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0, sigma: float = 1.5) -> float:
    """Mean SSIM of two (H, W) or (H, W, C) images: scikit-image's, with the design's settings (see
    the module doc). The fit's differentiable SSIM is `render.losses.ssim` (tested against this)."""
    from skimage.metrics import structural_similarity

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError("ssim: images differ in shape")
    return float(structural_similarity(a, b, gaussian_weights=True, sigma=sigma, use_sample_covariance=False,
                                       data_range=data_range, channel_axis=-1 if a.ndim == 3 else None))


def iou(sil_pred, sil_true) -> float:
    a = np.asarray(sil_pred, bool)
    b = np.asarray(sil_true, bool)
    union = np.logical_or(a, b).sum()
    if union == 0:
        return 1.0
    return float(np.logical_and(a, b).sum() / union)


def material_accuracy(e_pred, e_true, tol: float = MA_TOLERANCE) -> float:
    """Share of entries with |E_pred - E_true| / E_true <= tol."""
    e_pred = np.asarray(e_pred, dtype=np.float64)
    e_true = np.asarray(e_true, dtype=np.float64)
    return float(np.mean(np.abs(e_pred - e_true) <= tol * e_true + 1e-12 * e_true))


def best_uniform_ma(e_true, tol: float = MA_TOLERANCE) -> tuple[float, float]:
    """The best MA any single E reaches, and that E: E passes for entry i iff
    E_true_i (1 - tol) <= E <= E_true_i (1 + tol); the best E maximises the overlap count."""
    e = np.asarray(e_true, dtype=np.float64)
    lo, hi = e * (1 - tol), e * (1 + tol)
    events = np.concatenate([np.stack([lo, np.ones_like(lo)], 1), np.stack([hi, -np.ones_like(hi)], 1)])
    order = np.lexsort((-events[:, 1], events[:, 0]))  # starts before ends at equal values
    counts = np.cumsum(events[order, 1])
    k = int(np.argmax(counts))
    return float(counts[k] / len(e)), float(events[order][k, 0])


def track_error_px(pred_uv, true_uv) -> float:
    """Mean 2D distance in pixels between predicted and true tracks (any shape ending in 2)."""
    d = np.linalg.norm(np.asarray(pred_uv, float) - np.asarray(true_uv, float), axis=-1)
    return float(np.nanmean(d))


def position_error_m(pred_xyz, true_xyz) -> float:
    """Mean 3D distance in metres between corresponding points (any shape ending in 3)."""
    d = np.linalg.norm(np.asarray(pred_xyz, float) - np.asarray(true_xyz, float), axis=-1)
    return float(np.mean(d))


def frame_metrics(pred_rgb, true_rgb, pred_sil, true_sil, exclude=None) -> dict:
    """All image metrics of one frame. `exclude` (H, W) bool marks pixels no model of the object
    can explain (the hand in front of it): they are left out of PSNR and IoU, and for SSIM the
    prediction takes the video's values there (zero error)."""
    pred_sil = np.asarray(pred_sil, bool)
    true_sil = np.asarray(true_sil, bool)
    if exclude is not None and np.asarray(exclude).any():
        keep = ~np.asarray(exclude, bool)
        pred_rgb = np.where(keep[..., None], pred_rgb, true_rgb)
        return {"psnr": psnr(pred_rgb, true_rgb, keep),
                "psnr_masked": psnr(pred_rgb, true_rgb, (pred_sil | true_sil) & keep),
                "ssim": ssim(pred_rgb, true_rgb), "iou": iou(pred_sil & keep, true_sil & keep)}
    return {"psnr": psnr(pred_rgb, true_rgb), "psnr_masked": psnr_masked(pred_rgb, true_rgb, pred_sil, true_sil),
            "ssim": ssim(pred_rgb, true_rgb), "iou": iou(pred_sil, true_sil)}


def summarize(per_frame: list[dict]) -> dict:
    """Means over frames (infinite PSNRs, from identical frames, are capped at 100 dB)."""
    out = {}
    for key in ("psnr", "psnr_masked", "ssim", "iou"):
        vals = np.array([min(f[key], 100.0) for f in per_frame if key in f and not np.isnan(f[key])])
        out[key] = float(np.nanmean(vals)) if len(vals) else float("nan")
    return out


def truth_levels(e_true, max_levels: int = 4, bins: int = 3) -> np.ndarray:
    """A material index per entry: the truth's distinct E values (equal to 3 significant digits) when
    there are at most `max_levels`, else `bins` quantile bins of log E (a graded truth). 0 = softest."""
    e = np.asarray(e_true, dtype=np.float64)
    key = np.round(np.log10(np.maximum(e, 1e-30)), 3)
    vals = np.unique(key)
    if len(vals) <= max_levels:
        return np.searchsorted(vals, key)
    edges = np.quantile(key, np.linspace(0, 1, bins + 1)[1:-1])
    return np.searchsorted(edges, key, side="right")


def peak_green_strain(rest, positions, k: int = 12) -> np.ndarray:
    """Per point, the largest Frobenius norm over frames of the Green strain 0.5 (F^T F - I), F the
    least-squares affine map of its k nearest rest neighbours' offsets (rigid motion reads 0).
    rest (N, 3); positions (T, N, 3)."""
    from scipy.spatial import cKDTree

    x0 = np.asarray(rest, dtype=np.float64)
    xs = np.asarray(positions, dtype=np.float64)
    n = len(x0)
    k = int(min(k, n - 1))
    if k < 3:
        return np.zeros(n)
    _, nb = cKDTree(x0).query(x0, k + 1)
    d0 = x0[nb[:, 1:]] - x0[:, None, :]                       # (N, k, 3)
    # F^T = (D0^T D0)^-1 D0^T D: solve once per point for the rest offsets' pseudo-inverse
    g = np.einsum("nki,nkj->nij", d0, d0) + 1e-12 * np.eye(3)
    pinv = np.linalg.solve(g, np.transpose(d0, (0, 2, 1)))    # (N, 3, k)
    out = np.zeros(n)
    eye = np.eye(3)
    for x in xs:
        d = x[nb[:, 1:]] - x[:, None, :]
        ft = pinv @ d                                         # (N, 3, 3) = F^T
        green = 0.5 * (ft @ np.transpose(ft, (0, 2, 1)) - eye)
        out = np.maximum(out, np.sqrt((green ** 2).sum((1, 2))))
    return out


def ma_by_truth_level(e_pred, e_true, confidence=None, exposure=None, tol: float = MA_TOLERANCE) -> list[dict]:
    """Per material of the truth (`truth_levels`), softest first: its share of the entries, its MA,
    the median and quartiles of E_pred / E_true, the mean claimed confidence and the median strain
    exposure (when given). The shares times the MAs sum to the overall MA."""
    e_pred = np.asarray(e_pred, dtype=np.float64)
    e_true = np.asarray(e_true, dtype=np.float64)
    lev = truth_levels(e_true)
    ok = np.abs(e_pred - e_true) <= tol * e_true + 1e-12 * e_true
    out = []
    for v in np.unique(lev):
        m = lev == v
        r = e_pred[m] / e_true[m]
        row = {"e_truth": float(np.median(e_true[m])), "share": float(m.mean()), "ma": float(ok[m].mean()),
               "ratio_median": float(np.median(r)), "ratio_q25": float(np.quantile(r, 0.25)),
               "ratio_q75": float(np.quantile(r, 0.75))}
        if confidence is not None:
            row["confidence"] = float(np.mean(np.asarray(confidence, dtype=np.float64)[m]))
        if exposure is not None:
            row["exposure"] = float(np.median(np.asarray(exposure, dtype=np.float64)[m]))
        out.append(row)
    return out


def confidence_calibration(e_pred, e_true, confidence, edges=(0.0, 0.2, 0.5, 0.8, 1.0),
                           tol: float = MA_TOLERANCE) -> dict:
    """Does the claimed confidence (the probability of being within `tol`) hold? Per confidence bin:
    the share of entries, the mean claim and the MA found; overall: the mean claim (the MA the fit
    expects) against the MA, and the share that is confident (>= 0.8) and wrong."""
    e_pred = np.asarray(e_pred, dtype=np.float64)
    e_true = np.asarray(e_true, dtype=np.float64)
    c = np.asarray(confidence, dtype=np.float64)
    ok = np.abs(e_pred - e_true) <= tol * e_true + 1e-12 * e_true
    bins = []
    for i, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        m = (c >= a) & ((c < b) if i < len(edges) - 2 else (c <= b))
        if m.any():
            bins.append({"lo": float(a), "hi": float(b), "share": float(m.mean()), "claimed": float(c[m].mean()),
                         "ma": float(ok[m].mean())})
    return {"claimed": float(c.mean()), "ma": float(ok.mean()), "confident_wrong": float(((c >= 0.8) & ~ok).mean()),
            "bins": bins}


def truth_resolution(truth_cell: float | None, fit_cell: float) -> dict | None:
    """Whether a synthetic truth was simulated finer than the fit it scores (docs/synth.md: its cell 0.7x the
    suggested fit's). A truth on a cell as coarse as the fit's or coarser is another discretisation, not the
    continuum the fit approximates: its own discretisation error reads as material error (the 22nd session's
    suite: bow_tie's truth on 12.2 mm cells scored a fit on 9.4 mm at MA 0.22; the same scene's truth made for the
    fit's grid, 0.79; docs/benchmarks/fit.md). None when the truth's cell is not known (an older gt.json)."""
    if truth_cell is None or not truth_cell > 0 or not fit_cell > 0:
        return None
    ratio = float(truth_cell) / float(fit_cell)
    finer = ratio < 0.95
    note = None if finer else (
        f"the ground truth was simulated on a {truth_cell * 1000:.3g} mm cell, {'as coarse as' if ratio < 1.05 else 'coarser than'} "
        f"this fit's {fit_cell * 1000:.3g} mm: MA also measures the truth's discretisation (score a fit on a cell at "
        f"least {truth_cell / 0.7 * 1000:.3g} mm, or, for a named scene, make the capture for this grid: "
        f"synth NAME --fit-grid N)")
    return {"truth_cell_m": float(truth_cell), "fit_cell_m": float(fit_cell), "ratio": ratio, "finer": finer,
            "note": note}
