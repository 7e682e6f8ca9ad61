"""Static-camera background from the video: per-pixel median over the frames in which the pixel
is not covered by the object (or the hand), masks dilated by a few pixels first.

Pixels never seen free fall back to `fallback` (a colour), or, without one, to the median colour
of all free pixels. numpy in, numpy out ((H, W, 3) float in [0, 1]); pass the result to
`render(..., background=torch.as_tensor(bg))`.
"""

from __future__ import annotations

import numpy as np


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0:
        return mask
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def estimate_background(frames, masks=None, *, dilate: int = 3, fallback=None,
                        min_frames: int = 1, return_seen: bool = False):
    """frames (T, H, W, 3) (uint8 or float in [0, 1]); masks (T, H, W) bool, True where the
    object or the hand is (None: every pixel is background in every frame).

    Returns the background (H, W, 3) float32, and with `return_seen` also the count of free
    frames per pixel (H, W).
    """
    f = np.asarray(frames)
    if f.ndim != 4 or f.shape[-1] < 3:
        raise ValueError("frames must be (T, H, W, 3)")
    f = f[..., :3]
    f = f.astype(np.float32) / 255.0 if f.dtype == np.uint8 else f.astype(np.float32)
    T, H, W, _ = f.shape
    if masks is None:
        free = np.ones((T, H, W), dtype=bool)
    else:
        m = np.asarray(masks).astype(bool).reshape(T, H, W)
        free = ~np.stack([_dilate(mi, dilate) for mi in m])
    seen = free.sum(0)
    data = np.where(free[..., None], f, np.nan)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            bg = np.nanmedian(data, axis=0)
    never = seen < max(int(min_frames), 1)
    if never.any():
        if fallback is not None:
            col = np.broadcast_to(np.asarray(fallback, dtype=np.float32), (3,))
        elif (~never).any():
            col = np.median(bg[~never], axis=0)
        else:
            col = np.median(f.reshape(-1, 3), axis=0)
        bg[never] = col
    bg = bg.astype(np.float32)
    return (bg, seen) if return_seen else bg
