"""The object at rest seen by the camera, and the design's back-projection onto it.

`RestView` renders the stage's Gaussians at rest through one (static) camera: silhouette (alpha),
expected depth (camera-frame z), colour. `back_project` lifts pixels to world points with that
depth (X_p = T_c^-1 pi^-1(x_p, d_p)); `particles_near` maps world points to the simulation
particles within a radius. No USD here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RestView:
    camera: object            # camera.Camera (static)
    alpha: np.ndarray         # (H, W)
    depth: np.ndarray         # (H, W) expected camera z, 0 where nothing is rendered
    rgb: np.ndarray           # (H, W, 3) over black
    particle_uv: np.ndarray   # (P, 2) particles projected
    particle_z: np.ndarray    # (P,) camera-frame depth of the particles
    particle_visible: np.ndarray  # (P,) bool: in the image and not hidden behind the surface

    @property
    def silhouette(self) -> np.ndarray:
        return self.alpha > 0.5


def render_rest(gaussians, camera, particles: np.ndarray | None = None, spacing: float = 0.0,
                device: str = "cpu") -> RestView:
    """Render the Gaussians at rest through `camera` (static) on `device` (cpu or cuda). With
    `particles`, also project them and mark the ones on the visible surface (within 1.5 particle
    spacings of the rendered depth)."""
    import torch

    from ..devices import torch_device
    from ..render import covariance_from_scales_quats, render

    dev = torch_device(device)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)  # noqa: E731
    cov = covariance_from_scales_quats(t(gaussians.scales), t(gaussians.quats))
    colours = t(gaussians.sh) if gaussians.sh.shape[1] > 1 else t(gaussians.colors)
    with torch.no_grad():
        out = render(t(gaussians.means), cov, colours, t(gaussians.opacities), camera)
    alpha = out["alpha"].cpu().numpy().astype(np.float64)
    depth = out["depth"].cpu().numpy().astype(np.float64)
    rgb = out["rgb"].cpu().numpy().astype(np.float64)
    if particles is None:
        particles = np.zeros((0, 3))
    uv, z = camera.project(np.asarray(particles, np.float64))
    vis = np.zeros(len(uv), bool)
    if len(uv):
        d = sample(depth, uv, order=0)
        a = sample(alpha, uv, order=0)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        vis = inside & (a > 0.5) & (z > 0) & (z <= d + 1.5 * max(spacing, 1e-9) + 1e-6)
    return RestView(camera, alpha, depth, rgb, uv, z, vis)


def sample(img: np.ndarray, uv: np.ndarray, order: int = 1) -> np.ndarray:
    """Sample an (H, W[, C]) image at continuous pixel coordinates (pixel centres at +0.5);
    clamped at the borders. order 0: nearest, 1: bilinear."""
    img = np.asarray(img)
    H, W = img.shape[:2]
    x = np.asarray(uv, np.float64)[:, 0] - 0.5
    y = np.asarray(uv, np.float64)[:, 1] - 0.5
    if order == 0:
        xi = np.clip(np.round(x).astype(int), 0, W - 1)
        yi = np.clip(np.round(y).astype(int), 0, H - 1)
        return img[yi, xi]
    x = np.clip(x, 0, W - 1)
    y = np.clip(y, 0, H - 1)
    x0 = np.minimum(np.floor(x).astype(int), W - 2 if W > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(int), H - 2 if H > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = x - x0, y - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    return (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x1] * fx * (1 - fy)
            + img[y1, x0] * (1 - fx) * fy + img[y1, x1] * fx * fy)


def pixel_centres(mask: np.ndarray) -> np.ndarray:
    """(N, 2) continuous (u, v) coordinates of the true pixels of a mask."""
    v, u = np.nonzero(mask)
    return np.stack([u + 0.5, v + 0.5], 1).astype(np.float64)


def back_project(view: RestView, uv: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """World points of pixels `uv` at the rendered depth (the design's X_p = T_c^-1 pi^-1(x_p, d_p)).

    Pixels off the rendered object (depth 0) take the nearest rendered depth."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if depth is None:
        depth = sample(view.depth, uv, order=0)
        miss = ~(depth > 0)
        if miss.any():
            filled = fill_depth(view.depth, view.alpha > 0.05)
            depth = np.where(miss, sample(filled, uv, order=0), depth)
    return view.camera.unproject(uv, depth)


def fill_depth(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Depth extended to every pixel by the nearest valid pixel's value."""
    from scipy.ndimage import distance_transform_edt

    if not valid.any():
        return depth
    _, (iy, ix) = distance_transform_edt(~valid, return_indices=True)
    return depth[iy, ix]


def particles_near(points: np.ndarray, particles: np.ndarray, radius: float, min_count: int = 3) -> np.ndarray:
    """Indices of the particles within `radius` of any of `points`; at least the `min_count`
    nearest to their centroid."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(pts):
        return np.zeros(0, np.int64)
    tree = cKDTree(particles)
    hits = tree.query_ball_point(pts, radius)
    idx = np.unique(np.concatenate([np.asarray(h, np.int64) for h in hits])) if len(hits) else np.zeros(0, np.int64)
    if len(idx) < min_count:
        _, nn = tree.query(pts.mean(0), k=min(min_count, len(particles)))
        idx = np.unique(np.concatenate([idx, np.atleast_1d(nn)]))
    return idx.astype(np.int64)
