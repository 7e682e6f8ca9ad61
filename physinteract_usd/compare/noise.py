"""The noise floor, measured from the video itself: what error a perfect model would still show.

- Pixel noise: frame-to-frame differences of the static background (pixels that neither the object
  nor the hand covers in either frame, a few pixels away from them), robust (MAD) standard
  deviation / sqrt(2), at least 8-bit quantisation's.
- Photometric floor: the model's error where no dynamics are involved (the rest frames, where the
  model is the object file itself), at least the pixel noise: a perfect physical model cannot
  render the video better than its appearance model renders the object at rest.
- Track floor: the tracker's own random error, per frame: the drift of tracks on textured static
  background (their true motion is zero) and the forward-backward disagreement of the object's
  tracks, at least `MIN_TRACK_PX` (sub-pixel flow on a deforming surface is not better than that).
  Its bias (flow underestimates large motions of fine texture) is measured apart: the same tracker
  run on the model's own rendered frames, against the model's known projections (`render_px`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

QUANTISATION = 1.0 / 255 / np.sqrt(12)   # 8-bit rounding: the smallest pixel noise a video has
MIN_TRACK_PX = 0.25


def dilate(mask: np.ndarray, px: int) -> np.ndarray:
    import cv2

    if px <= 0:
        return np.asarray(mask, bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.dilate(np.asarray(mask, np.uint8), k) > 0


def static_background(cover: np.ndarray | None, shape, margin: int = 3) -> np.ndarray:
    """(H, W) bool: pixels no frame covers (object or hand), `margin` pixels away from them."""
    if cover is None:
        return np.ones(shape[:2], bool)
    return ~dilate(np.asarray(cover, bool).any(0), margin)


def pixel_noise(frames: np.ndarray, cover: np.ndarray | None, margin: int = 3) -> float:
    """Per-channel noise sigma of the video (in [0, 1] units) from consecutive frames' differences
    on the static background; 8-bit quantisation at least."""
    f = np.asarray(frames, np.float32)
    T, H, W = f.shape[:3]
    if T < 2:
        return float(QUANTISATION)
    diffs = []
    for k in range(T - 1):
        free = np.ones((H, W), bool)
        if cover is not None:
            free = ~(dilate(cover[k], margin) | dilate(cover[k + 1], margin))
        if free.sum() >= 16:
            diffs.append((f[k + 1] - f[k])[free].ravel())
    if not diffs:
        return float(QUANTISATION)
    d = np.concatenate(diffs)
    sigma = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)
    if sigma == 0:   # a clean (synthetic) video: most differences are exactly 0; use the RMS instead
        sigma = float(np.sqrt(np.mean(d.astype(np.float64) ** 2)) / np.sqrt(2))
    return float(max(sigma, QUANTISATION))


@dataclass
class NoiseFloor:
    pixel_sigma: float              # per-channel video noise, [0, 1] units
    photometric_mse: float          # the masked MSE a perfect model would still show
    track_px: np.ndarray            # (T,) the tracker's error per frame, pixels
    background_px: np.ndarray       # (T,) drift of static background tracks (nan without any)
    fb_px: np.ndarray               # (T,) median forward-backward disagreement of the object tracks / 2
    n_background_tracks: int
    render_px: np.ndarray | None = None   # (T,) the tracker's error on the model's own rendered frames:
                                          # its bias on this motion and texture (what the plain track error
                                          # of a perfect model would be)

    @property
    def psnr_floor(self) -> float:
        """The masked PSNR a perfect model would reach (dB)."""
        return float(10 * np.log10(1.0 / max(self.photometric_mse, 1e-12)))

    def to_dict(self) -> dict:
        return {"pixel_sigma": self.pixel_sigma, "psnr_floor_db": self.psnr_floor,
                "photometric_mse": self.photometric_mse, "track_px": _list(self.track_px),
                "track_px_mean": float(np.nanmean(self.track_px)) if len(self.track_px) else None,
                "background_drift_px": _list(self.background_px), "forward_backward_px": _list(self.fb_px),
                "background_tracks": self.n_background_tracks,
                "tracker_bias_px": _list(self.render_px) if self.render_px is not None else None}


def _list(a) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]


def noise_floor(frames, cover, rest_mse: list[float], background_uv=None, background_valid=None,
                object_fb=None, object_valid=None, *, render_px=None, min_track_px: float = MIN_TRACK_PX) -> NoiseFloor:
    """The floors (see the module doc). `rest_mse`: the model's masked MSE on the rest frames;
    `background_uv` / `background_valid` (T, M, 2) / (T, M): static background tracks (None for a
    moving camera); `object_fb` / `object_valid` (T, N): the object tracks' forward-backward error."""
    sigma = pixel_noise(frames, cover)
    photo = max([m for m in rest_mse if np.isfinite(m)] + [sigma ** 2])
    T = len(frames)
    bg = np.full(T, np.nan)
    nb = 0
    if background_uv is not None and background_valid is not None and background_valid.shape[1]:
        nb = int(background_valid.shape[1])
        start = background_uv[0]
        for k in range(T):
            v = background_valid[k]
            if v.sum() >= 3:
                bg[k] = float(np.mean(np.linalg.norm(background_uv[k][v] - start[v], axis=1)))
    fb = np.full(T, np.nan)
    if object_fb is not None:
        for k in range(T):
            v = object_valid[k] & np.isfinite(object_fb[k])
            if v.sum() >= 3:
                fb[k] = float(np.median(object_fb[k][v])) / 2.0
    rp = np.full(T, np.nan) if render_px is None else np.asarray(render_px, float)
    parts = np.stack([np.nan_to_num(bg, nan=0.0), np.nan_to_num(fb, nan=0.0)])
    track = np.maximum(parts.max(0), min_track_px)
    track[0] = min_track_px
    return NoiseFloor(sigma, float(photo), track, bg, fb, nb, rp)
