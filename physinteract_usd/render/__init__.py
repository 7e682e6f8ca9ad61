"""Differentiable Gaussian-splat renderer in Warp (CPU and CUDA, float32 and float64), with SH
colours, Gaussians deformed by the simulator's particles, a static-camera background estimate and
weighted image losses. Knows nothing of USD.

    from physinteract_usd.render import render, RasterSettings
    out = render(means, covs, colors_or_sh, opacities, camera.at(frame), background=bg)
    out["rgb"] (H, W, 3), out["alpha"] (H, W), out["depth"] (H, W)

See docs/render.md.
"""

from .background import estimate_background
from .deform import (GaussianBinding, covariance_from_scales_quats, deform_covariances, polar_rotation,
                     quat_to_rotmat, scales_quats_from_covariance)
from .function import RasterizeGaussians, cov6_from_matrix, matrix_from_cov6, project, render, render_batch
from .losses import l1_loss, reconstruction_loss, reconstruction_loss_batch, silhouette_loss, ssim, ssim_loss, ssim_map
from .rasterizer import RasterSettings
from .sh import eval_sh, sh_basis, sh_to_color

__all__ = [
    "RasterSettings", "RasterizeGaussians", "render", "render_batch", "project", "cov6_from_matrix", "matrix_from_cov6",
    "eval_sh", "sh_basis", "sh_to_color",
    "GaussianBinding", "deform_covariances", "covariance_from_scales_quats", "scales_quats_from_covariance",
    "quat_to_rotmat", "polar_rotation",
    "estimate_background",
    "l1_loss", "ssim", "ssim_map", "ssim_loss", "silhouette_loss", "reconstruction_loss", "reconstruction_loss_batch",
]
