"""The diagnosis's residual: a least-squares view of the fit's image terms.

The fit minimises L1 + SSIM + silhouette terms; a score test needs a residual vector r whose
sum of squares is the loss. Per frame k >= 1 (frame 0 is the rest pose, not a prediction), on a
subsampled pixel grid (at most `max_pixels` per frame), r holds the rendered colour minus the
video's (3 channels) and the rendered alpha minus the video's silhouette (1 channel, when the
stage has silhouettes), with the hand's pixels weighted 0. Its layout (frames, rows, cols, 4)
gives the blocks the significance test sums over (`blocks`).
"""

from __future__ import annotations

import math

import numpy as np
import torch


class ImageResidual:
    """r(x, F) for a `fit.FitProblem`'s renderer and observations (torch, differentiable)."""

    def __init__(self, prob, *, max_pixels: int = 6000, frames=None, silhouette_weight: float = 1.0):
        self.prob = prob
        T = prob.T
        H, W = prob.frames.shape[1:3]
        self.stride = max(1, int(math.ceil(math.sqrt(H * W / max(int(max_pixels), 1)))))
        s = self.stride
        self.frames = list(range(1, T)) if frames is None else [int(k) for k in frames]
        self.rows, self.cols = slice(s // 2, H, s), slice(s // 2, W, s)
        self.target = prob.frames[:, self.rows, self.cols]
        w = prob.weight[:, self.rows, self.cols] if prob.weight is not None else torch.ones_like(self.target[..., 0])
        self.w = w
        self.has_sil = prob.masks is not None
        self.masks = prob.masks[:, self.rows, self.cols] if self.has_sil else None
        self.sw = float(silhouette_weight) if self.has_sil else 0.0
        self.shape = (len(self.frames),) + tuple(self.target.shape[1:3]) + (4,)

    def frame(self, k: int, x_k, F_k) -> torch.Tensor:
        out = self.prob.render_frame(k, x_k, F_k)
        w = self.w[k][..., None]
        rgb = (out["rgb"][self.rows, self.cols] - self.target[k]) * w
        if self.has_sil:
            sil = (out["alpha"][self.rows, self.cols] - self.masks[k]) * self.w[k] * self.sw
        else:
            sil = torch.zeros_like(rgb[..., 0])
        return torch.cat([rgb, sil[..., None]], -1)

    def torch(self, x, F, frames=None) -> torch.Tensor:
        """(n_frames, h, w, 4) residual for the simulated x (T, P, 3), F (T, P, 3, 3)."""
        ks = self.frames if frames is None else frames
        return torch.stack([self.frame(k, x[k], F[k]) for k in ks])

    def __call__(self, x, F) -> np.ndarray:
        """The residual as a flat float64 numpy vector."""
        with torch.no_grad():
            return self.torch(x, F).detach().cpu().numpy().astype(np.float64).ravel()

    @property
    def n(self) -> int:
        return int(np.prod(self.shape))

    def frame_of(self) -> np.ndarray:
        """(n,) the frame index of every element."""
        f = np.asarray(self.frames)[:, None, None, None]
        return np.broadcast_to(f, self.shape).ravel()

    def blocks(self, frames_per_block: int = 2, tiles: int = 6) -> tuple[np.ndarray, int]:
        """(labels (n,), count): blocks of `frames_per_block` consecutive frames x an image tile
        (about `tiles` tiles across the shorter side)."""
        nf, h, w, _ = self.shape
        t = max(2, int(round(min(h, w) / max(int(tiles), 1))))
        fb = np.arange(nf) // max(int(frames_per_block), 1)
        rb, cb = np.arange(h) // t, np.arange(w) // t
        nr, nc = rb.max() + 1, cb.max() + 1
        lab = (fb[:, None, None] * nr + rb[None, :, None]) * nc + cb[None, None, :]
        lab = np.broadcast_to(lab[..., None], self.shape).ravel()
        return lab.astype(np.int64), int(lab.max()) + 1


def loss(r: np.ndarray) -> float:
    """The diagnosis's loss: mean square residual."""
    return float(np.mean(np.square(r))) if len(r) else 0.0
