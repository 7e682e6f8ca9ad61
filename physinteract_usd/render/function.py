"""torch entry points of the renderer: a torch.autograd.Function over the Warp rasterizer and
the friendly `render(...)` wrapper.

Device follows the tensors (cpu or cuda); torch memory is shared with Warp (`wp.from_torch`) and
on CUDA Warp runs on torch's current stream. float32 in production, float64 for gradient tests.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from . import rasterizer as R
from .rasterizer import RasterSettings
from .sh import sh_to_color

_WP_INIT = False


def _init():
    global _WP_INIT
    if not _WP_INIT:
        wp.init()
        _WP_INIT = True


def cov6_from_matrix(cov: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) covariances -> (N, 6) upper triangle (xx, xy, xz, yy, yz, zz), symmetrised."""
    s = 0.5 * (cov + cov.transpose(-1, -2))
    return torch.stack([s[:, 0, 0], s[:, 0, 1], s[:, 0, 2], s[:, 1, 1], s[:, 1, 2], s[:, 2, 2]], 1)


def matrix_from_cov6(c: torch.Tensor) -> torch.Tensor:
    """(N, 6) upper triangle -> (N, 3, 3) symmetric matrices."""
    row0 = torch.stack([c[:, 0], c[:, 1], c[:, 2]], 1)
    row1 = torch.stack([c[:, 1], c[:, 3], c[:, 4]], 1)
    row2 = torch.stack([c[:, 2], c[:, 4], c[:, 5]], 1)
    return torch.stack([row0, row1, row2], 1)


class _Scope:
    """Device (and, on CUDA, torch's current stream) for Warp launches."""

    def __init__(self, device: torch.device):
        self.device = device
        self.ctx = []

    def __enter__(self):
        if self.device.type == "cuda":
            self.ctx = [wp.ScopedDevice(wp.device_from_torch(self.device)),
                        wp.ScopedStream(wp.stream_from_torch(self.device))]
        for c in self.ctx:
            c.__enter__()
        return self

    def __exit__(self, *exc):
        for c in reversed(self.ctx):
            c.__exit__(*exc)
        return False


def _wp(t: torch.Tensor, dtype):
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


class RasterizeGaussians(torch.autograd.Function):
    """(means (N,3), cov6 (N,6), colors (N,3), opacities (N,)) -> (rgb (H,W,3) over black,
    alpha (H,W), depth_acc (H,W) = sum of alpha-weighted camera-frame z).

    Differentiable w.r.t. all four inputs; `camera` (a static camera.Camera) and `settings`
    (RasterSettings) are constants. With `camera` a list of M static cameras of one image size,
    M images in one pass: the inputs are M sets of N/M Gaussians one after another (image m
    renders its own set with its own camera) and the outputs (M,H,W,3), (M,H,W), (M,H,W), each
    image bitwise what it would be alone (`rasterizer.forward`).
    """

    @staticmethod
    def forward(ctx, means, cov6, colors, opacities, camera, settings):
        _init()
        dtype, dev = means.dtype, means.device
        scalar = R.warp_scalar(dtype)
        k = R.kernels(scalar)
        means = means.detach().contiguous()
        cov6 = cov6.detach().to(dtype).contiguous()
        colors = colors.detach().to(dtype).contiguous()
        opacities = opacities.detach().to(dtype).contiguous()
        many = isinstance(camera, (list, tuple))
        c0 = camera[0] if many else camera
        H, W = int(c0.height), int(c0.width)
        lead = (len(camera),) if many else ()
        rgb = torch.empty(lead + (H, W, 3), dtype=dtype, device=dev)
        alpha = torch.empty(lead + (H, W), dtype=dtype, device=dev)
        depth = torch.empty(lead + (H, W), dtype=dtype, device=dev)
        with _Scope(dev):
            wm, wc, wcol, wo = _wp(means, k.vec3), _wp(cov6, k.vec6), _wp(colors, k.vec3), _wp(opacities, scalar)
            st = R.forward(wm, wc, wcol, wo, camera, settings,
                           _wp(rgb.view(-1, 3), k.vec3), _wp(alpha.view(-1), scalar), _wp(depth.view(-1), scalar))
        ctx.st = st
        ctx.wp_in = (wm, wc, wcol)
        ctx.save_for_backward(means, cov6, colors, opacities)
        return rgb, alpha, depth

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth):
        means, cov6, colors, opacities = ctx.saved_tensors
        dtype, dev = means.dtype, means.device
        st = ctx.st
        k = st.k
        scalar = k.scalar
        n = means.shape[0]
        g_means = torch.zeros((n, 3), dtype=dtype, device=dev)
        g_cov6 = torch.zeros((n, 6), dtype=dtype, device=dev)
        g_colors = torch.zeros((n, 3), dtype=dtype, device=dev)
        g_pack = torch.zeros((n, 8), dtype=dtype, device=dev)
        g_rgb = g_rgb.to(dtype).contiguous()
        g_alpha = g_alpha.to(dtype).contiguous()
        g_depth = g_depth.to(dtype).contiguous()
        if n > 0:
            with _Scope(dev):
                wm, wc, wcol = ctx.wp_in
                R.backward(st, wm, wc, wcol, _wp(g_rgb.view(-1, 3), k.vec3), _wp(g_alpha.view(-1), scalar),
                           _wp(g_depth.view(-1), scalar), _wp(g_means, k.vec3), _wp(g_cov6, k.vec6),
                           _wp(g_colors, k.vec3), _wp(g_pack, k.vec8))
        return g_means, g_cov6, g_colors, g_pack[:, 5].contiguous(), None, None


def render(means: torch.Tensor, covs: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
           camera, background=None, settings: RasterSettings | None = None) -> dict:
    """Render 3D Gaussians seen by one static camera.

    Args:
        means: (N, 3) world positions (metres).
        covs: (N, 3, 3) world covariances, or (N, 6) upper triangles (xx, xy, xz, yy, yz, zz).
        colors: (N, 3) RGB, or (N, K, 3) SH coefficients (K = (deg + 1)^2, colour = 0.5 + sum_k
            sh_k Y_k(dir), clamped at 0 from below; dir from the camera centre to the mean).
        opacities: (N,) in [0, 1].
        camera: a static `physinteract_usd.camera.Camera` (``camera.at(frame)``).
        background: None (black), an (3,) colour, or an (H, W, 3) image; a constant (its gradient
            is not needed by the fit, but autograd gives it where it requires grad).
        settings: cut-offs and tiling (RasterSettings(); the defaults are 3DGS's).

    Returns a dict of tensors, all differentiable w.r.t. means, covs, colours and opacities:
        ``rgb`` (H, W, 3) composited over the background, ``alpha`` (H, W) silhouette,
        ``depth`` (H, W) expected camera-frame z (alpha-weighted z divided by alpha; 0 where
        nothing is rendered), ``depth_acc`` (H, W) the alpha-weighted z before normalisation.
    """
    if not camera.is_static:
        raise ValueError("render needs a static camera: pass camera.at(frame)")
    settings = settings or RasterSettings()
    if means.dtype not in (torch.float32, torch.float64):
        raise TypeError("means must be float32 or float64")
    dtype, dev = means.dtype, means.device
    if covs.dim() == 3:
        cov6 = cov6_from_matrix(covs.to(dtype))
    elif covs.dim() == 2 and covs.shape[1] == 6:
        cov6 = covs.to(dtype)
    else:
        raise ValueError("covs must be (N, 3, 3) or (N, 6)")
    if colors.dim() == 3:
        center = torch.as_tensor(camera.position, dtype=dtype, device=dev)
        colors = sh_to_color(colors.to(dtype), means, center)
    rgb, alpha, depth_acc = RasterizeGaussians.apply(means, cov6, colors.to(dtype), opacities.to(dtype).reshape(-1),
                                                     camera, settings)
    return _composite(rgb, alpha, depth_acc, background)


def _composite(rgb, alpha, depth_acc, background) -> dict:
    """The rasterizer's accumulated colour over `background` (if any), and the depth normalised by
    the coverage (0 where nothing covers the pixel): `render`'s and `render_batch`'s outputs."""
    if background is not None:
        bg = torch.as_tensor(background, dtype=rgb.dtype, device=rgb.device)
        rgb = rgb + (1.0 - alpha)[..., None] * bg
    eps = 1e-6
    depth = torch.where(alpha > eps, depth_acc / alpha.clamp_min(eps), torch.zeros_like(depth_acc))
    return {"rgb": rgb, "alpha": alpha, "depth": depth, "depth_acc": depth_acc}


def render_batch(means: torch.Tensor, covs: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor,
                 cameras, background=None, settings: RasterSettings | None = None) -> dict:
    """M renders in one rasterizer pass (one launch per stage for all of them): image m renders
    Gaussian set m with `cameras[m]` (M static cameras of one image size; the same camera M times
    for M copies of a scene, or each frame's camera for M frames).

    Args (M sets of N Gaussians):
        means: (M, N, 3). covs: (M, N, 3, 3) or (M, N, 6). colors: (N, 3) or (M, N, 3) RGB, or
        (N, K, 3) / (M, N, K, 3) SH coefficients (each image's view directions from its camera).
        opacities: (N,) or (M, N). background: as `render`'s (one for all images), or (M, H, W, 3).

    Returns `render`'s dict with a leading image axis: ``rgb`` (M, H, W, 3), ``alpha``,
    ``depth``, ``depth_acc`` (M, H, W); each image equal, bit for bit, to `render` of its own set
    (the rasterizer's images are independent: tests/test_render_batch.py).
    """
    cameras = list(cameras)
    M = len(cameras)
    if M == 0:
        raise ValueError("render_batch needs at least one camera")
    if any(not c.is_static for c in cameras):
        raise ValueError("render_batch needs static cameras: pass camera.at(frame)")
    settings = settings or RasterSettings()
    if means.dtype not in (torch.float32, torch.float64):
        raise TypeError("means must be float32 or float64")
    if means.dim() != 3 or means.shape[0] != M or means.shape[2] != 3:
        raise ValueError(f"means must be (M, N, 3) with M = {M} cameras, got {tuple(means.shape)}")
    dtype, dev = means.dtype, means.device
    N = means.shape[1]
    if covs.dim() == 4:
        cov6 = cov6_from_matrix(covs.to(dtype).reshape(M * N, 3, 3))
    elif covs.dim() == 3 and covs.shape[2] == 6:
        cov6 = covs.to(dtype).reshape(M * N, 6)
    else:
        raise ValueError("covs must be (M, N, 3, 3) or (M, N, 6)")
    colors = colors.to(dtype)
    if colors.dim() == 2:                                   # (N, 3) RGB, every image
        colors = colors.expand(M, N, 3)
    elif not (colors.dim() == 3 and tuple(colors.shape) == (M, N, 3)):     # SH: (N, K, 3) or (M, N, K, 3)
        if colors.dim() == 3:
            colors = colors.expand(M, *colors.shape)
        centres = torch.as_tensor(np.stack([c.position for c in cameras]), dtype=dtype, device=dev)
        colors = torch.stack([sh_to_color(colors[m], means[m], centres[m]) for m in range(M)])
    op = opacities.to(dtype)
    op = op.expand(M, N) if op.dim() == 1 else op
    rgb, alpha, depth_acc = RasterizeGaussians.apply(means.reshape(M * N, 3), cov6, colors.reshape(M * N, 3),
                                                     op.reshape(M * N), cameras, settings)
    return _composite(rgb, alpha, depth_acc, background)


@torch.no_grad()
def project(means: torch.Tensor, covs: torch.Tensor, opacities: torch.Tensor, camera,
            settings: RasterSettings | None = None) -> dict:
    """The renderer's own per-Gaussian projection (no gradients), for checks and overlays.

    Returns ``uv`` (N, 2) continuous pixel coordinates, ``conic`` (N, 3) inverse 2D covariance
    (a, b, c) = [[a, b], [b, c]] (uv and conic are 0 where not visible), ``depth`` (N,) camera-frame z,
    ``visible`` (N,) bool (touches at
    least one tile), ``tiles`` (N, 4) tile rectangle (x0, y0, x1, y1).
    """
    _init()
    settings = settings or RasterSettings()
    dtype, dev = means.dtype, means.device
    scalar = R.warp_scalar(dtype)
    k = R.kernels(scalar)
    cov6 = cov6_from_matrix(covs.to(dtype)) if covs.dim() == 3 else covs.to(dtype)
    n = means.shape[0]
    pack = torch.zeros((n, 8), dtype=dtype, device=dev)
    rect = torch.zeros((n, 4), dtype=torch.int32, device=dev)
    count = torch.zeros((n,), dtype=torch.int32, device=dev)
    dkey = torch.zeros((n,), dtype=torch.float32, device=dev)
    if n:
        with _Scope(dev):
            _, cams = R.make_cams(k, [camera], settings, wp.device_from_torch(dev))
            wp.launch(k.project, n, inputs=[_wp(means.contiguous(), k.vec3), _wp(cov6.contiguous(), k.vec6),
                                            _wp(opacities.to(dtype).contiguous(), scalar), cams, n],
                      outputs=[_wp(pack, k.vec8), _wp(rect, wp.vec4i), _wp(count, wp.int32), _wp(dkey, wp.float32),
                               _wp(torch.zeros((n,), dtype=torch.int32, device=dev), wp.int32)],
                      device=wp.device_from_torch(dev))
    w2c = torch.as_tensor(camera.w2c_cv(), dtype=dtype, device=dev)
    z = means @ w2c[2, :3] + w2c[2, 3]
    return {"uv": pack[:, 0:2], "conic": pack[:, 2:5], "depth": z, "visible": count > 0, "tiles": rect}
