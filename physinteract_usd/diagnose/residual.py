"""The diagnosis's residual: a least-squares view of the fit's image terms.

The fit minimises L1 + SSIM + silhouette terms; a score test needs a residual vector r whose
sum of squares is the loss. Per frame k >= 1 (frame 0 is the rest pose, not a prediction), on a
subsampled pixel grid (at most `max_pixels` per frame), r holds the rendered colour minus the
video's (3 channels) and the rendered alpha minus the video's silhouette (1 channel, when the
stage has silhouettes), with the hand's pixels weighted 0. Its layout (frames, rows, cols, 4)
gives the blocks the significance test sums over (`blocks`).

Photometric nuisance (`set_photometric`): a real video's exposure and lighting change from frame
to frame (flicker, auto-exposure, compression's DC drift), which no physical candidate explains
and which the appearance model (fixed colours, a static background) cannot follow. Per frame and
colour channel the residual's affine part in the base rendering, a gain g_k,c and an offset
o_k,c (video ~ (1 + g) rendered + o, the standard affine brightness model), is projected out:
rgb_k,c <- rgb_k,c - Q_k,c Q_k,c^T rgb_k,c, Q the orthonormal basis of [w, w * rendered_base]. The
projector is fixed (taken at the base) and linear, so every residual the diagnosis forms (the
base's, the probes', the refits') is the same linear map of the image residual: by
Frisch-Waugh-Lovell, scoring the projected residual against projected columns is the joint test
with the 6 nuisance parameters per frame added to the base columns, at no forward's cost. The
silhouette channel has its own per-frame nuisance: a segmentation that grows or shrinks the whole
mask by a fraction of a pixel from frame to frame (a threshold on a flickering video), whose column
is the base rendering's alpha edge |grad alpha| (the first-order change of a dilated silhouette).

Channel weights from the data (`set_noise_weights`): where the video has rest frames (before the
first grasp: the object and the model still), the residual's change between them is the data's own
noise. Its variance in the band around the silhouette's edge (where the physics shows), per
channel kind (colour, silhouette), gives the silhouette channel the weight
min(1, sigma_colour / sigma_silhouette): a segmentation much noisier than the colours counts less
(generalised least squares between the two kinds), never more than the colours (a clean mask's
systematic soft-alpha error is not noise). Without 3 rest frames the weight stays 1.
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
        self.photo = None          # (T, 3, m, q) the photometric nuisance's orthonormal basis per frame / channel
        self.edge = None           # (T, h, w) the silhouette's unit edge column per frame
        self.floor_cols = None     # (T, h, w, 4, q) the rendering floor's unit columns per frame (`set_floor`)

    def set_photometric(self, x, F) -> None:
        """Fix the per-frame nuisance bases (module doc) at the simulated base x, F (all T frames,
        frame 0 included: the floor uses it): colour gain and offset, and the silhouette's edge.
        A frame's basis drops columns the weights make degenerate (a frame all hand)."""
        Q, E = [], []
        with torch.no_grad():
            for k in range(self.prob.T):
                out = self.prob.render_frame(k, x[k], F[k])
                rend = out["rgb"][self.rows, self.cols]
                w = self.w[k][..., None].expand_as(rend)
                A = torch.stack([w, w * rend], -1).reshape(-1, 3, 2).permute(1, 0, 2)     # (3, m, 2)
                U, S, _ = torch.linalg.svd(A, full_matrices=False)
                keep = (S > 1e-6 * S[:, :1].clamp_min(1e-30)).to(U.dtype)               # (3, 2)
                Q.append(U * keep[:, None, :])
                if self.has_sil and "alpha" in out:
                    e = self.w[k] * _edge(out["alpha"])[self.rows, self.cols]
                    nrm = torch.linalg.norm(e)
                    E.append(e / nrm if nrm > 1e-12 else torch.zeros_like(e))
        self.photo = torch.stack(Q)
        self.edge = torch.stack(E) if E else None

    def set_noise_weights(self, x, F, rest_frames) -> dict:
        """The silhouette channel's weight from the data's own noise on `rest_frames` (module doc);
        returns {"rest_frames", "sigma_colour", "sigma_silhouette", "silhouette_weight", "band_pixels"}."""
        out = {"rest_frames": [int(k) for k in rest_frames], "sigma_colour": None, "sigma_silhouette": None,
               "silhouette_weight": self.sw, "band_pixels": 0}
        if not self.has_sil or len(rest_frames) < 3:
            return out
        sw0 = self.sw
        self.sw = 1.0
        with torch.no_grad():
            R = torch.stack([self.frame(k, x[k], F[k]) for k in rest_frames]).cpu().numpy().astype(np.float64)
            alpha = torch.stack([self.prob.render_frame(k, x[k], F[k])["alpha"][self.rows, self.cols]
                                 for k in rest_frames]).cpu().numpy()
        self.sw = sw0
        from scipy.ndimage import binary_dilation, binary_erosion

        m = self.masks[list(rest_frames)].cpu().numpy() > 0.5
        inside = (alpha > 0.5) | m
        band = np.stack([binary_dilation(a, iterations=2) & ~binary_erosion(a, iterations=2) for a in inside]).any(0)
        band &= (self.w[list(rest_frames)].cpu().numpy() > 0).all(0)
        if band.sum() < 4:
            return out
        D = (R - R.mean(0, keepdims=True))[:, band]            # (n_rest, band, 4)
        corr = len(rest_frames) / (len(rest_frames) - 1.0)
        s_rgb = math.sqrt(corr * float(np.mean(D[..., :3] ** 2)))
        s_sil = math.sqrt(corr * float(np.mean(D[..., 3] ** 2)))
        self.sw = float(min(1.0, s_rgb / s_sil)) * sw0 if s_sil > 0 else sw0
        out.update(sigma_colour=s_rgb, sigma_silhouette=s_sil, silhouette_weight=self.sw, band_pixels=int(band.sum()))
        return out

    def set_floor(self, x, F, rest_frames, bins: int | None = None, split: bool = False) -> dict:
        """The rendering's own error as a per-frame nuisance (module doc, "Floor"). On the rest frames
        (`rest_frames` and frame 0, the rest pose: the object and the model still, no physics acts) the
        residual's mean per channel in bins of the base's rendered alpha is the floor's model f(alpha):
        whatever the rendering leaves as a function of the alpha it draws (soft alpha against a binary
        silhouette, the video's clipped noise on one side of the edge, anti-aliasing). Per frame k its
        column f(alpha_k) (the base's alpha at that frame: the floor moves with the object) is projected
        out of every residual, one amplitude per frame (`split`: two, the colours and the silhouette
        apart). Fitted on the rest frames only, so no physics leaks into it; the projector is fixed and
        linear like the photometric one (a nuisance column per frame in the base, by Frisch-Waugh-Lovell).
        Returns {"rest_frames", "bins", "pixels" (per bin, bin 0 = the background), "template" (bins x 4),
        "rest_share" (the share of the rest frames' residual energy the columns take), "split"}."""
        rest = sorted({0, *[int(k) for k in rest_frames]})
        self.floor_cols = None
        with torch.no_grad():
            A = torch.stack([self.prob.render_frame(k, x[k], F[k])["alpha"][self.rows, self.cols]
                             for k in range(self.prob.T)]).cpu().numpy().astype(np.float64)     # (T, h, w)
            R = torch.stack([self.frame(k, x[k], F[k]) for k in rest]).cpu().numpy().astype(np.float64)
        cols, info = floor_columns(A, R, rest, self.w.cpu().numpy().astype(np.float64), bins=bins, split=split)
        self.floor_cols = torch.as_tensor(cols, dtype=self.target.dtype, device=self.target.device)
        return info

    def _photometric(self, k: int, rgb: torch.Tensor) -> torch.Tensor:
        if self.photo is None:
            return rgb
        Q = self.photo[k]                                   # (3, m, 2)
        flat = rgb.reshape(-1, 3)
        coef = torch.einsum("cmq,mc->cq", Q, flat)
        return (flat - torch.einsum("cmq,cq->mc", Q, coef)).reshape(rgb.shape)

    def frame(self, k: int, x_k, F_k) -> torch.Tensor:
        out = self.prob.render_frame(k, x_k, F_k)
        w = self.w[k][..., None]
        rgb = self._photometric(k, (out["rgb"][self.rows, self.cols] - self.target[k]) * w)
        if self.has_sil:
            sil = (out["alpha"][self.rows, self.cols] - self.masks[k]) * self.w[k]
            if self.photo is not None and self.edge is not None:
                e = self.edge[k]
                sil = sil - e * (e * sil).sum()
            sil = sil * self.sw
        else:
            sil = torch.zeros_like(rgb[..., 0])
        out = torch.cat([rgb, sil[..., None]], -1)
        if self.floor_cols is not None:
            Q = self.floor_cols[k]                                                  # (h, w, 4, q)
            out = out - torch.einsum("hwcq,q->hwc", Q, torch.einsum("hwcq,hwc->q", Q, out))
        return out

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


def floor_columns(alpha: np.ndarray, R_rest: np.ndarray, rest: list, w: np.ndarray | None = None, *,
                  bins: int | None = None, split: bool = False) -> tuple[np.ndarray, dict]:
    """The rendering floor's model (`ImageResidual.set_floor`), arrays in: `alpha` (T, h, w) the base's
    rendered alpha per frame, `R_rest` (len(rest), h, w, 4) the residual on the rest frames `rest`, `w`
    (T, h, w) the pixels' weights (0: the hand). f(alpha) per channel is the rest residual's mean in
    `bins` bins of alpha (plus a background bin, alpha <= FLOOR_BACKGROUND; a bin with fewer than
    FLOOR_MIN_PIXELS pixels gets 0); frame k's column is f(alpha_k) x w_k, unit norm, one per frame
    (`split`: colours and silhouette apart). Returns ((T, h, w, 4, q) columns, info)."""
    bins = int(FLOOR_BINS if bins is None else bins)
    alpha = np.asarray(alpha, np.float64)
    R = np.asarray(R_rest, np.float64)
    w = np.ones_like(alpha) if w is None else np.asarray(w, np.float64)
    lab = 1 + np.clip(np.digitize(alpha, np.linspace(0.0, 1.0, bins + 1)[1:-1]), 0, bins - 1)
    lab = np.where(alpha <= FLOOR_BACKGROUND, 0, lab)       # bin 0: the background away from the object
    nb = bins + 1
    tot, cnt = np.zeros((nb, 4)), np.zeros(nb)
    for i, k in enumerate(rest):
        ok = w[k] > 0
        for c in range(4):
            tot[:, c] += np.bincount(lab[k][ok], weights=R[i][..., c][ok], minlength=nb)
        cnt += np.bincount(lab[k][ok], minlength=nb)
    m = np.where(cnt[:, None] >= FLOOR_MIN_PIXELS, tot / np.maximum(cnt[:, None], 1.0), 0.0)
    tmpl = m[lab] * w[..., None]                                                      # (T, h, w, 4)
    groups = [slice(0, 4)] if not split else [slice(0, 3), slice(3, 4)]
    cols = np.zeros(tmpl.shape + (len(groups),))
    for q, g in enumerate(groups):
        part = np.zeros_like(tmpl)
        part[..., g] = tmpl[..., g]
        nrm = np.sqrt(np.sum(part ** 2, axis=(1, 2, 3)))[:, None, None, None]
        cols[..., q] = np.where(nrm > 1e-12, part / np.maximum(nrm, 1e-300), 0.0)
    e_all = float(np.sum(R ** 2))
    took = sum(float(np.sum(R[i] * cols[k, ..., q])) ** 2 for i, k in enumerate(rest) for q in range(len(groups)))
    return cols, {"rest_frames": [int(k) for k in rest], "bins": bins, "pixels": cnt.astype(int).tolist(),
                  "template": np.round(m, 6).tolist(), "rest_share": took / e_all if e_all > 0 else 0.0,
                  "split": bool(split)}


def project_floor(R: np.ndarray, cols: np.ndarray, frames=None) -> np.ndarray:
    """R (n_frames, h, w, 4) less its part along the floor's columns of its frames (`cols` (T, h, w, 4, q),
    `frames` the frame index of each row of R, default 0..n-1): what `ImageResidual.frame` does."""
    R = np.asarray(R, np.float64)
    ks = range(len(R)) if frames is None else frames
    out = R.copy()
    for i, k in enumerate(ks):
        Q = cols[k]
        out[i] -= np.einsum("hwcq,q->hwc", Q, np.einsum("hwcq,hwc->q", Q, R[i]))
    return out


FLOOR_BINS = 8            # bins of the base's rendered alpha in the floor's model f(alpha) (`set_floor`)
FLOOR_MIN_PIXELS = 5      # a bin with fewer rest-frame pixels gets 0 (its mean would be noise)
FLOOR_BACKGROUND = 1e-3   # alpha at or below this: the background bin


def _edge(alpha: torch.Tensor) -> torch.Tensor:
    """|grad alpha| (central differences, full resolution): where a dilation changes the silhouette."""
    a = alpha
    gy = torch.zeros_like(a)
    gx = torch.zeros_like(a)
    gy[1:-1] = 0.5 * (a[2:] - a[:-2])
    gx[:, 1:-1] = 0.5 * (a[:, 2:] - a[:, :-2])
    return torch.sqrt(gx * gx + gy * gy)


def correlation_frames(R: np.ndarray, max_lag: int = 20) -> float:
    """The residual's integrated correlation time in frames, 1 + 2 sum_l rho_l over the lags before
    the first rho_l <= 0 (Geyer's initial positive sequence); rho_l is the pooled correlation of
    the residual (frames, ...) with itself l frames later, its static part kept (a persistent
    appearance error correlates every frame with every other). The sign flips' blocks must be at
    least this long to be independent: with 2-frame blocks on a residual correlated over 8 frames
    the test cries wolf."""
    R = np.asarray(R, np.float64).reshape(len(R), -1)
    e = float(np.sum(R * R))
    if len(R) < 3 or e <= 0:
        return 1.0
    tau = 1.0
    for lag in range(1, min(int(max_lag), len(R) - 1) + 1):
        rho = float(np.sum(R[lag:] * R[:-lag])) / (e * (len(R) - lag) / len(R))
        if rho <= 0:
            break
        tau += 2.0 * rho
    return tau


def loss(r: np.ndarray) -> float:
    """The diagnosis's loss: mean square residual."""
    return float(np.mean(np.square(r))) if len(r) else 0.0
