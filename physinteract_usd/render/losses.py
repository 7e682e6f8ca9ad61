"""Image losses for analysis-by-synthesis, all differentiable and all taking a per-pixel weight
image in [0, 1] (0 = a pixel the hand covers, left out; None = all ones).

Images are (H, W, C) or (B, H, W, C) (a grey image or silhouette may be (H, W) / (B, H, W));
weights are (H, W) or (B, H, W). With weights, every term depends only on pixels of non-zero
weight: L1 and the silhouette loss are weighted means; SSIM uses weight-normalised local
statistics (mu = G*(w x) / G*w, ...), which with w = 1 is exactly
``skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)``: Gaussian 11x11 window (sigma 1.5,
truncated at 3.5 sigma as scipy does), K1 = 0.01, K2 = 0.03, SSIM map averaged over the pixels at
least 5 from the border (skimage crops them), and over channels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as Fnn

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _bchw(img: torch.Tensor, weight: torch.Tensor | None, channels_last: bool = True):
    """-> image (B, C, H, W), weight (B, 1, H, W)."""
    x = img
    if x.dim() == 2:
        x = x[None, :, :, None]
    elif x.dim() == 3:
        x = x[None] if channels_last else x[:, :, :, None]
    if x.dim() != 4:
        raise ValueError("images must be (H, W), (H, W, C) or (B, H, W, C)")
    x = x.permute(0, 3, 1, 2)
    B, _, H, W = x.shape
    if weight is None:
        w = torch.ones((B, 1, H, W), dtype=x.dtype, device=x.device)
    else:
        w = torch.as_tensor(weight, dtype=x.dtype, device=x.device)
        w = w.reshape(-1, 1, H, W).expand(B, 1, H, W)
    return x, w


def _grey_ok(pred, target):
    if pred.shape != target.shape:
        raise ValueError(f"shape mismatch {tuple(pred.shape)} vs {tuple(target.shape)}")


def l1_loss(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Weighted mean absolute error: sum w |pred - target| / (C sum w)."""
    _grey_ok(pred, target)
    chl = pred.dim() != 3 or pred.shape[-1] in (1, 3, 4)
    x, w = _bchw(pred, weight, chl)
    y, _ = _bchw(target.to(pred.dtype), None, chl)
    C = x.shape[1]
    return ((x - y).abs() * w).sum() / (C * w.sum()).clamp_min(1e-12)


def silhouette_loss(pred_alpha: torch.Tensor, target_mask: torch.Tensor,
                    weight: torch.Tensor | None = None) -> torch.Tensor:
    """Weighted mean squared error between the rendered alpha and the mask (in [0, 1]); the
    design's |M^ - M|_2 term (squared, per pixel, averaged)."""
    _grey_ok(pred_alpha, target_mask)
    x, w = _bchw(pred_alpha, weight, False) if pred_alpha.dim() == 3 else _bchw(pred_alpha, weight)
    y, _ = (_bchw(target_mask.to(pred_alpha.dtype), None, False) if target_mask.dim() == 3
            else _bchw(target_mask.to(pred_alpha.dtype), None))
    return (((x - y) ** 2) * w).sum() / w.sum().clamp_min(1e-12)


def gaussian_window(sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE, dtype=torch.float64,
                    device="cpu") -> torch.Tensor:
    """scipy.ndimage.gaussian_filter's 1D kernel: radius int(truncate sigma + 0.5) (5: 11 taps)."""
    r = int(truncate * sigma + 0.5)
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype=dtype, device=device)


def _blur_valid(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' Gaussian filter of (B, C, H, W)."""
    C = x.shape[1]
    k = g.numel()
    x = Fnn.conv2d(x, g.view(1, 1, 1, k).expand(C, 1, 1, k), groups=C)
    return Fnn.conv2d(x, g.view(1, 1, k, 1).expand(C, 1, k, 1), groups=C)


def ssim_map(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
             data_range: float = 1.0):
    """SSIM map on the pixels at least `radius` from the border: returns (S (B, C, H-2r, W-2r),
    cropped weight (B, 1, H-2r, W-2r))."""
    _grey_ok(pred, target)
    x, w = _bchw(pred, weight)
    y, _ = _bchw(target.to(pred.dtype), None)
    g = gaussian_window(dtype=x.dtype, device=x.device)
    r = (g.numel() - 1) // 2
    if x.shape[2] <= 2 * r or x.shape[3] <= 2 * r:
        raise ValueError(f"SSIM needs images larger than {2 * r + 1} px")
    C1 = (SSIM_K1 * data_range) ** 2
    C2 = (SSIM_K2 * data_range) ** 2
    wx, wy = w * x, w * y
    stack = torch.cat([wx, wy, wx * x, wy * y, wx * y], 1)
    f = _blur_valid(stack, g)
    mw = _blur_valid(w, g).clamp_min(1e-12)
    c = x.shape[1]
    ux, uy, uxx, uyy, uxy = (f[:, i * c:(i + 1) * c] / mw for i in range(5))
    vx = uxx - ux * ux
    vy = uyy - uy * uy
    vxy = uxy - ux * uy
    S = ((2 * ux * uy + C1) * (2 * vxy + C2)) / ((ux * ux + uy * uy + C1) * (vx + vy + C2))
    return S, w[:, :, r:-r, r:-r]


def ssim(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
         data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM (weighted by `weight` over the cropped map, averaged over channels)."""
    S, wc = ssim_map(pred, target, weight, data_range)
    return (S * wc).sum() / (S.shape[1] * wc.sum()).clamp_min(1e-12)


def ssim_loss(pred, target, weight=None) -> torch.Tensor:
    """1 - SSIM."""
    return 1.0 - ssim(pred, target, weight)


def reconstruction_loss(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, weight: torch.Tensor | None = None,
                        pred_alpha: torch.Tensor | None = None, target_mask: torch.Tensor | None = None,
                        lambda_ssim: float = 0.2, lambda_mask: float = 1.0) -> dict:
    """The design's per-frame L_rec = |I^ - I|_1 + lambda_ssim (1 - SSIM) + lambda_mask |M^ - M|_2,
    every term weighted by `weight` (hand pixels 0). Returns {"total", "l1", "ssim", "mask"}."""
    l1 = l1_loss(pred_rgb, target_rgb, weight)
    s = ssim(pred_rgb, target_rgb, weight)
    total = l1 + lambda_ssim * (1.0 - s)
    out = {"l1": l1, "ssim": s}
    if pred_alpha is not None and target_mask is not None:
        m = silhouette_loss(pred_alpha, target_mask, weight)
        total = total + lambda_mask * m
        out["mask"] = m
    out["total"] = total
    return out


def reconstruction_loss_batch(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, weight: torch.Tensor | None = None,
                              pred_alpha: torch.Tensor | None = None, target_mask: torch.Tensor | None = None,
                              lambda_ssim: float = 0.2, lambda_mask: float = 1.0) -> dict:
    """`reconstruction_loss` of M images at once, one value per image (a handful of batched torch
    ops for all M instead of M times each). pred_rgb, target_rgb (M, H, W, C); weight, pred_alpha,
    target_mask (M, H, W) or None. Returns {"total", "l1", "ssim"[, "mask"]}, each (M,): image m's
    terms equal `reconstruction_loss` of image m alone up to the summation order (float rounding;
    tests/test_render_batch.py)."""
    _grey_ok(pred_rgb, target_rgb)
    if pred_rgb.dim() != 4:
        raise ValueError("reconstruction_loss_batch takes (M, H, W, C) images")
    x, w = _bchw(pred_rgb, weight)
    y, _ = _bchw(target_rgb.to(pred_rgb.dtype), None)
    C = x.shape[1]
    ws = w.sum((1, 2, 3))
    l1 = ((x - y).abs() * w).sum((1, 2, 3)) / (C * ws).clamp_min(1e-12)
    S, wc = ssim_map(pred_rgb, target_rgb, weight)
    s = (S * wc).sum((1, 2, 3)) / (S.shape[1] * wc.sum((1, 2, 3))).clamp_min(1e-12)
    total = l1 + lambda_ssim * (1.0 - s)
    out = {"l1": l1, "ssim": s}
    if pred_alpha is not None and target_mask is not None:
        _grey_ok(pred_alpha, target_mask)
        a = pred_alpha[:, None]
        m = target_mask.to(pred_alpha.dtype)[:, None]
        out["mask"] = (((a - m) ** 2) * w).sum((1, 2, 3)) / ws.clamp_min(1e-12)
        total = total + lambda_mask * out["mask"]
    out["total"] = total
    return out


__all__ = ["l1_loss", "silhouette_loss", "ssim", "ssim_map", "ssim_loss", "psnr", "gaussian_window",
           "reconstruction_loss", "reconstruction_loss_batch"]
