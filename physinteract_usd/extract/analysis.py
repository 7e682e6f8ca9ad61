"""The per-frame analysis every extraction step reads: the object at rest through the camera
(silhouette, depth, particle visibility), the hand and object masks per frame (`models.segmenter`),
the optical flow (`models.tracker`), and the image scales derived from them; plus the small image
helpers the steps share."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from .geometry import render_rest
from .segmentation import dilate

if TYPE_CHECKING:  # the models registry imports the default steps; only its type is needed here
    from .models import Models


def disk_mask(shape, centre, radius) -> np.ndarray:
    """(H, W) bool: the pixels whose centres lie within `radius` of `centre` (u, v)."""
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W]
    return (xx + 0.5 - centre[0]) ** 2 + (yy + 0.5 - centre[1]) ** 2 <= radius ** 2


def median_flow(flow: np.ndarray, mask: np.ndarray, fallback: np.ndarray | None = None):
    """The median flow vector over `mask` (over `fallback` when `mask` has fewer than 3 pixels);
    None when neither has a pixel."""
    m = mask if mask.sum() >= 3 else fallback
    if m is None or not m.any():
        return None
    return np.median(flow[m], axis=0)


def unit(v):
    """`v` normalised (zeros for a zero vector)."""
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else np.zeros_like(v)


# the particle count whose spacing sets the finest image window (`window_radius`)
WINDOW_PARTICLES = 1500


def window_radius(spacing_px: float, n_particles: int, obj_size_px: float) -> float:
    """The radius [px] of the image windows about the contact: 2.5 particle spacings, but no finer than the spacing
    the object would have at WINDOW_PARTICLES particles (at 4 px and a quarter of the object at least and most)."""
    window_px = spacing_px * max(1.0, (n_particles / WINDOW_PARTICLES) ** (1.0 / 3.0))
    return float(np.clip(2.5 * window_px, 4.0, 0.25 * obj_size_px + 4.0))


class Analysis:
    """Per-frame quantities shared by the steps."""

    def __init__(self, scene, frames, masks, masks_amodal, models: "Models", device: str = "cpu"):
        self.scene = scene
        self.device = device
        self.frames = np.asarray(frames, np.float32)
        self.T, self.H, self.W = self.frames.shape[:3]
        cam = scene.camera
        self.static_camera = cam.is_static or np.allclose(cam.c2w, cam.c2w[0:1], atol=1e-9)
        self.cam0 = cam.at(0)
        self.x0 = np.asarray(scene.particles_positions, np.float64)
        self.spacing = float(scene.settings.particle_spacing)
        self.rest = render_rest(scene.gaussians, self.cam0, self.x0, self.spacing, device)
        if not self.rest.silhouette.any():
            raise InputError(scene.path, "the object is not in the camera's view at frame 0 (its rendered "
                             "silhouette is empty): check the camera")
        z = self.rest.depth[self.rest.silhouette]
        self.z_obj = float(np.median(z))
        self.px_per_m = float(self.cam0.fx / self.z_obj)
        self.spacing_px = self.spacing * self.px_per_m
        # visible silhouettes (not amodal, not none): where the toucher hides the object, the frame's
        # silhouette has a notch (`contact.hidden_front`)
        self.visible_masks = masks is not None and not masks_amodal
        self.seg = models.segmenter(self.frames, masks, masks_amodal=masks_amodal, rest_alpha=self.rest.alpha,
                                    object_colors=scene.gaussians.colors)
        self.hand = self.seg.hand
        self.obj = self.seg.object
        self.flows = models.tracker.flows(self.frames)
        self.tracker = models.tracker
        ys, xs = np.nonzero(self.rest.silhouette)
        self.obj_size_px = float(max(np.ptp(xs), np.ptp(ys)) + 1)
        # the image windows about the contact (flows, the toucher's and the object's motion) scale with the object's
        # particle spacing, but no finer than the spacing the object would have at WINDOW_PARTICLES particles: the
        # windows are the image's, and a finer particle cap (init --grid auto --max-particles) is not a sharper video
        # (dev_0505 at 7571 particles: windows of 2.5 spacings saw the hand alone in 14 of 22 contact frames, and the
        # grasp read 8 frames early)
        self.R = window_radius(self.spacing_px, len(self.x0), self.obj_size_px)
        self.eps = 0.35  # px per frame: below this, "not moving"
        self.clear = max(2, int(round(0.4 * self.R)))  # px kept clear of the hand when measuring the object

    # ---- contact region per frame
    def contact_region(self, k: int, centre=None) -> np.ndarray:
        hand = self.hand[k]
        region = hand & (self.rest.silhouette | dilate(self.obj[k], 2))
        if centre is not None:
            region &= disk_mask((self.H, self.W), centre, 1.5 * self.R)
        return region

    def touching(self, k: int) -> int:
        return int((self.hand[k] & dilate(self.obj[k], 2)).sum())

    def rest_at(self, k: int):
        """The object at rest seen by the camera at frame k (frame 0's view for a static camera)."""
        if self.static_camera:
            return self.rest
        return render_rest(self.scene.gaussians, self.scene.camera.at(k), self.x0, self.spacing, self.device)
