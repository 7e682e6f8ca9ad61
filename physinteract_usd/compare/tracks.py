"""Tracks: which Gaussians the video shows at frame 0 (where the measured point tracks start), the
model's tracks (its Gaussians projected frame by frame), the residual motion (video minus model)
in pixels and lifted to metres in the image plane, and its split along physical directions
(the motion's velocity, gravity, the contact normal)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class GaussianTracks:
    """Point tracks measured on the video for Gaussians of the object (`extract.track.measure_tracks`
    started at their frame-0 projections), and for textured static background (the tracker's noise)."""

    ids: np.ndarray                       # (n,) indices of the tracked Gaussians (input PLY order)
    uv: np.ndarray                        # (T, n, 2) measured positions, pixels (nan where lost)
    valid: np.ndarray                     # (T, n) bool
    fb_error: np.ndarray | None = None    # (T, n) forward-backward disagreement, pixels
    background_uv: np.ndarray | None = None     # (T, M, 2) static background tracks (None: moving camera)
    background_valid: np.ndarray | None = None  # (T, M) bool


def visible_gaussians(uv0: np.ndarray, z0: np.ndarray, alpha0: np.ndarray, depth0: np.ndarray, *,
                      depth_tolerance: float, silhouette=None, hand=None, max_points: int = 3000,
                      seed: int = 0) -> np.ndarray:
    """Indices of the Gaussians on the visible surface at frame 0: in the image, where the model
    renders opaque (alpha > 0.5) and within `depth_tolerance` of the rendered depth; inside the
    video's silhouette when given, off the hand; one per pixel (the front one), at most
    `max_points` (an even random subset)."""
    H, W = alpha0.shape
    u, v = uv0[:, 0], uv0[:, 1]
    ok = np.isfinite(u) & np.isfinite(v) & (z0 > 0) & (u >= 1) & (u < W - 1) & (v >= 1) & (v < H - 1)
    iu = np.clip(np.floor(np.nan_to_num(u)).astype(int), 0, W - 1)
    iv = np.clip(np.floor(np.nan_to_num(v)).astype(int), 0, H - 1)
    ok &= alpha0[iv, iu] > 0.5
    ok &= z0 <= depth0[iv, iu] + depth_tolerance
    if silhouette is not None:
        ok &= np.asarray(silhouette, bool)[iv, iu]
    if hand is not None:
        ok &= ~np.asarray(hand, bool)[iv, iu]
    idx = np.where(ok)[0]
    if not len(idx):
        return idx
    # one per pixel: the nearest to the camera
    order = idx[np.lexsort((z0[idx], iv[idx] * W + iu[idx]))]
    pix = iv[order] * W + iu[order]
    first = np.r_[True, pix[1:] != pix[:-1]]
    idx = np.sort(order[first])
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    return idx


def background_points(frame0: np.ndarray, static: np.ndarray, max_points: int = 300) -> np.ndarray:
    """(M, 2) textured points (corners) on the static background of frame 0, pixel coordinates
    (centres at +0.5): where the tracker's drift measures its own noise. Empty when the background
    has no texture to track."""
    import cv2

    g = np.clip(np.asarray(frame0, np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) * 255, 0, 255)
    if not static.any():
        return np.zeros((0, 2))
    pts = cv2.goodFeaturesToTrack(g.astype(np.uint8), maxCorners=max_points, qualityLevel=0.05, minDistance=3,
                                  mask=static.astype(np.uint8))
    if pts is None:
        return np.zeros((0, 2))
    return pts.reshape(-1, 2).astype(np.float64) + 0.5


def project_tracks(means: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """means (T, n, 3) -> uv (T, n, 2), camera-frame depth z (T, n), frame k seen by camera.at(k)."""
    uv = np.zeros(means.shape[:2] + (2,))
    z = np.zeros(means.shape[:2])
    for k in range(len(means)):
        uv[k], z[k] = camera.at(k).project(means[k])
    return uv, z


def model_visible(uv: np.ndarray, z: np.ndarray, alpha: np.ndarray, depth: np.ndarray, tolerance: float) -> np.ndarray:
    """(T, n) bool: the model's Gaussian is on its visible surface in frame k (in the image, opaque,
    not behind the rendered depth)."""
    T, H, W = alpha.shape
    u, v = uv[..., 0], uv[..., 1]
    ok = np.isfinite(u) & np.isfinite(v) & (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    iu = np.clip(np.floor(np.nan_to_num(u)).astype(int), 0, W - 1)
    iv = np.clip(np.floor(np.nan_to_num(v)).astype(int), 0, H - 1)
    kk = np.arange(T)[:, None]
    ok &= alpha[kk, iv, iu] > 0.5
    ok &= z <= depth[kk, iv, iu] + tolerance
    return ok


def lift_to_metres(res_px: np.ndarray, z: np.ndarray, camera) -> np.ndarray:
    """Residuals in pixels (T, n, 2) at camera depth z (T, n) -> world vectors (T, n, 3) in metres,
    in the image plane (the video says nothing about motion along the line of sight)."""
    out = np.zeros(res_px.shape[:2] + (3,))
    for k in range(len(res_px)):
        cam = camera.at(k)
        R = cam.w2c_cv()[:3, :3]        # rows: the camera's x (right) and y (down) axes in world coordinates
        dx = res_px[k, :, 0] * z[k] / cam.fx
        dy = res_px[k, :, 1] * z[k] / cam.fy
        out[k] = dx[:, None] * R[0] + dy[:, None] * R[1]
    return out


def unit(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > eps, v / np.maximum(n, eps), 0.0)


def velocities(means: np.ndarray, fps: float) -> np.ndarray:
    """(T, n, 3) central-difference velocities (one-sided at the ends), m/s."""
    v = np.gradient(means, axis=0) if len(means) > 1 else np.zeros_like(means)
    return v * fps


def contact_normal(contacts, x0: np.ndarray) -> np.ndarray | None:
    """A unit direction for the interactions' contact normal: a surface contact's own normal, else
    the outward direction at the contact point (from the object's centre through it); None
    without an interaction."""
    inter = [c for c in contacts if c.is_interaction]
    if not inter:
        return None
    n = np.zeros(3)
    centre = np.asarray(x0, float).mean(0)
    for c in inter:
        if c.type == "surfaceNonAdherent":
            n += -np.asarray(c.normal, float)   # the plane's normal points toward the object: flip to outward
        else:
            n += unit(c.point(x0) - centre)
    n = unit(n)
    return n if np.linalg.norm(n) > 0 else None


def split_residual(res_m: np.ndarray, valid: np.ndarray, vel: np.ndarray, gravity=(0.0, -9.81, 0.0),
                   normal: np.ndarray | None = None) -> dict:
    """The residual motion (T, n, 3) (video minus model, metres) split along the model's own
    velocity (positive: the video moves further along the motion than the model), gravity
    (positive: the video is lower than the model) and the contact normal (positive: the video is
    further out), each (T, n), nan where not valid (or the direction undefined)."""
    out = {}
    v_hat = unit(vel)
    out["velocity"] = np.where(valid & (np.linalg.norm(vel, axis=-1) > 1e-9), (res_m * v_hat).sum(-1), np.nan)
    g = unit(np.asarray(gravity, float))
    out["gravity"] = np.where(valid, res_m @ g, np.nan)
    out["contact_normal"] = np.where(valid, res_m @ normal, np.nan) if normal is not None else \
        np.full(valid.shape, np.nan)
    out["total"] = np.where(valid, np.linalg.norm(res_m, axis=-1), np.nan)
    return out
