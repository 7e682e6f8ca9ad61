"""Point tracks as a loss term: the video's 2D point tracks (measured once, e.g. by
`extract.track.measure_tracks` from the Gaussians the video shows at frame 0) against the model's
projected Gaussians, so that the motion of the object's interior texture counts beside the pixel
colours and the outline.

Binding (fixed at frame 0): each usable track (valid at frame 0, finite) is bound to the `knn`
tracked Gaussians whose frame-0 projections lie nearest its start (the tracked Gaussians are the
front surface the video shows: opaque, within the rendered depth, inside the silhouette, one per
pixel), with weights exp(-d^2 / 2 r^2), d in pixels, and the constant offset that makes the
weighted projection equal the track's start at frame 0. Each Gaussian follows the particles
(`render.GaussianBinding`), so the term's gradient reaches the particle positions and, through the
simulator, the material.

Per frame k > 0: the mean over the tracks still valid at k (lost, occluded by the hand or failing
the tracker's forward-backward / appearance checks: dropped) of a Charbonnier penalty in pixels,
rho(r) = s (sqrt(1 + (r / s)^2) - 1), s the tracker's noise (`tracker_noise_px`): quadratic
within the noise, linear (robust) beyond. It is scaled by `outline_px / (H W)` (the frame-0
silhouette's boundary length over the image's area), so a 1-px error on every track costs about
what a 1-px shift of the whole outline costs the silhouette term (a mean over pixels of a binary
mask's squared difference): a track weight of 1 makes the two comparable.

No USD, no file paths: arrays in.
"""

from __future__ import annotations

import numpy as np
import torch

MIN_NOISE_PX = 0.25     # sub-pixel flow on a deforming surface is not better than this (as compare/noise.py)


def project_points(means: torch.Tensor, camera) -> tuple[torch.Tensor, torch.Tensor]:
    """(uv (n, 2) continuous pixel coordinates, z (n,) camera-frame depth) of world points (n, 3)
    through a static camera: ``camera.Camera.project`` in torch (differentiable), the renderer's
    projection (OpenCV frame, pixel centres at +0.5)."""
    w2c = torch.as_tensor(camera.w2c_cv(), dtype=means.dtype, device=means.device)
    pc = means @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    u = camera.fx * pc[:, 0] / z + camera.cx
    v = camera.fy * pc[:, 1] / z + camera.cy
    return torch.stack([u, v], 1), z


def tracker_noise_px(fb_error=None, valid=None, background_uv=None, background_valid=None,
                     min_px: float = MIN_NOISE_PX) -> float:
    """The tracker's random error in pixels: the larger of the object tracks' median
    forward-backward disagreement / 2 and the static background tracks' median drift (their true
    motion is zero), at least `min_px` (frames after the first)."""
    parts = [min_px]
    if fb_error is not None and valid is not None:
        fb = np.asarray(fb_error, float)[1:]
        ok = np.asarray(valid, bool)[1:] & np.isfinite(fb)
        if ok.sum() >= 3:
            parts.append(float(np.median(fb[ok])) / 2.0)
    if background_uv is not None and background_valid is not None and np.asarray(background_valid).shape[1]:
        buv = np.asarray(background_uv, float)
        bv = np.asarray(background_valid, bool)
        d = np.linalg.norm(buv[1:] - buv[:1], axis=-1)
        ok = bv[1:] & bv[:1] & np.isfinite(d)
        if ok.sum() >= 3:
            parts.append(float(np.median(d[ok])))
    return float(max(parts))


def outline_length(mask: np.ndarray) -> int:
    """Pixels on a binary mask's boundary (in the mask, with a 4-neighbour outside it or at the
    image's edge)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return 0
    p = np.pad(m, 1, constant_values=False)
    inner = p[1:-1, 1:-1] & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return int((m & ~inner).sum())


def charbonnier(r: torch.Tensor, s: float) -> torch.Tensor:
    """s (sqrt(1 + (r / s)^2) - 1): r^2 / 2s for r << s, |r| - s for r >> s (pixels)."""
    return s * (torch.sqrt(1.0 + (r / s) ** 2) - 1.0)


class TrackLoss:
    """The track term of a fit (module doc). `ids` (n,): the tracked Gaussians (indices into the
    model's Gaussians); `uv` (T, n, 2) measured positions (nan where lost); `valid` (T, n);
    `cameras`: T static cameras (frame k seen by cameras[k]); `means0` (N, 3): the Gaussians at rest
    (frame 0); `outline` (H, W) bool: the frame-0 silhouette (the normalisation); `sigma_px`: the
    Charbonnier scale (default: `tracker_noise_px` of `fb_error` and the background tracks)."""

    def __init__(self, ids, uv, valid, cameras, means0, *, outline=None, fb_error=None, background_uv=None,
                 background_valid=None, sigma_px: float | None = None, knn: int = 4, radius_px: float = 1.0,
                 min_tracks: int = 3, dtype=torch.float32, device="cpu"):
        ids = np.asarray(ids, np.int64)
        uv = np.asarray(uv, np.float64)
        valid = np.asarray(valid, bool)
        T = min(len(cameras), len(uv))
        if uv.ndim != 3 or uv.shape[1] != len(ids) or valid.shape != uv.shape[:2]:
            raise ValueError(f"tracks: uv must be (T, {len(ids)}, 2) and valid (T, {len(ids)})")
        uv, valid = uv[:T], valid[:T]
        valid = valid & np.isfinite(uv).all(-1)
        use = valid[0]
        self.T, self.min_tracks = T, int(min_tracks)
        self.sigma = float(sigma_px) if sigma_px is not None else tracker_noise_px(fb_error, valid, background_uv,
                                                                                 background_valid)
        if not self.sigma > 0:
            raise ValueError(f"tracks: the noise scale must be > 0, got {self.sigma}")
        H, W = int(cameras[0].height), int(cameras[0].width)
        n_outline = outline_length(outline) if outline is not None else 0
        # a 1-px error on every track costs about what a 1-px shift of the outline costs the
        # silhouette term; without an outline, the image's perimeter stands in
        self.scale = max(n_outline, 1) / float(H * W) if outline is not None else 2.0 * (H + W) / float(H * W)
        # binding: the knn tracked Gaussians nearest each track's start in the frame-0 image
        uv0_model, _ = cameras[0].project(np.asarray(means0, np.float64)[ids])
        start = uv[0][use]
        cand = np.isfinite(uv0_model).all(1)
        cand_ids, cand_uv = ids[cand], uv0_model[cand]
        n_used = int(use.sum())
        self.n_tracks = n_used
        k = int(min(max(knn, 1), len(cand_ids)))
        if n_used == 0 or k == 0:
            self.gauss = np.zeros((0, 1), np.int64)
            w = np.zeros((0, 1))
            off = np.zeros((0, 2))
        else:
            from scipy.spatial import cKDTree

            d, j = cKDTree(cand_uv).query(start, k=k)
            d, j = d.reshape(n_used, k), j.reshape(n_used, k)
            w = np.exp(-0.5 * (d / radius_px) ** 2)
            w[:, 0] = np.maximum(w[:, 0], 1e-12)          # the nearest always counts
            w /= w.sum(1, keepdims=True)
            self.gauss = cand_ids[j]
            off = start - (w[..., None] * cand_uv[j]).sum(1)
        t = lambda a, dt=dtype: torch.as_tensor(np.asarray(a), dtype=dt, device=device)  # noqa: E731
        self.weights = t(w)
        self.offset = t(off)
        self.index = torch.as_tensor(self.gauss, dtype=torch.long, device=device)
        self.target = t(np.nan_to_num(uv[:, use]))
        self.valid = torch.as_tensor(valid[:, use], device=device)
        self.cameras = list(cameras[:T])

    def frames_used(self) -> list[int]:
        """The frames (> 0) with at least `min_tracks` valid tracks: where the term counts."""
        n = self.valid.sum(1).cpu().numpy()
        return [k for k in range(1, self.T) if n[k] >= self.min_tracks]

    def model_uv(self, k: int, means: torch.Tensor) -> torch.Tensor:
        """(n, 2) the model's positions of the tracks in frame k from the Gaussians' means (N, 3)."""
        uv, _ = project_points(means[self.index.reshape(-1)], self.cameras[k])
        uv = uv.reshape(*self.index.shape, 2)
        return (self.weights.to(uv.dtype)[..., None] * uv).sum(1) + self.offset.to(uv.dtype)

    def errors_px(self, k: int, means: torch.Tensor) -> np.ndarray:
        """The valid tracks' distances (pixels) between model and video in frame k."""
        with torch.no_grad():
            r = (self.model_uv(k, means) - self.target[k].to(means.dtype)).norm(dim=1)
        return r[self.valid[k]].cpu().numpy()

    def frame_term(self, k: int, means: torch.Tensor) -> torch.Tensor:
        """The normalised track loss of frame k (0 for frame 0, beyond the tracks, or with fewer
        than `min_tracks` valid tracks)."""
        if k <= 0 or k >= self.T or self.n_tracks == 0:
            return means.sum() * 0.0
        v = self.valid[k]
        if int(v.sum()) < self.min_tracks:
            return means.sum() * 0.0
        d = self.model_uv(k, means)[v] - self.target[k][v].to(means.dtype)
        r2 = (d ** 2).sum(1)
        return self.scale * (self.sigma * (torch.sqrt(1.0 + r2 / self.sigma ** 2) - 1.0)).mean()


def track_loss_from(tracks, cameras, means0, **kw) -> TrackLoss:
    """A `TrackLoss` from any object with `ids`, `uv`, `valid` and optionally `fb_error`,
    `background_uv`, `background_valid` (e.g. `compare.GaussianTracks`)."""
    return TrackLoss(tracks.ids, tracks.uv, tracks.valid, cameras, means0,
                     fb_error=getattr(tracks, "fb_error", None), background_uv=getattr(tracks, "background_uv", None),
                     background_valid=getattr(tracks, "background_valid", None), **kw)
