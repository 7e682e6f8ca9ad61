"""The material field's parameterisation for the fit.

log E per particle = lo + (hi - lo) * sigmoid(B theta): a smooth map into the allowed range
[E_min, E_max] (the CFL substep was chosen at E_max, so E never exceeds it), with B a
partition-of-unity basis of K normalised Gaussian bumps on k-means centres of the rest particles.
Coarse-to-fine: K = 1 (uniform), then more centres; each refinement starts from the projection of
the current field. nu is one value per basis function too, nu = nu_max * sigmoid(w), fitted at
the coarsest levels only (it is weakly observable).

Nested field (`set_base`): log E = lo + (hi - lo) * sigmoid(u_base + B theta), with u_base a fixed
per-particle value (the logit of a simpler model's E: uniform or parts) and theta the bumps'
offsets, zero at the start, so the field starts exactly at the simpler model, keeps its sharp part
boundaries, and its bumps only add a smooth correction. The offsets live in the same logit space
as the field (E stays inside [E_min, E_max], as the CFL substep needs); near the middle of the
range an offset w moves log E by about (hi - lo) / 4 * w. The smoothness term then measures the
offsets only (the base's part boundaries are not the field's to smooth away).

Appearance prior (optional): objects are made of parts, and a material change usually shows as a
change of colour. With per-particle appearance features (the local mean colour of the nearby
Gaussians), centres and bumps live in a joint space, position plus `appearance` x extent x colour,
so a bump does not spread across a colour edge and the field can jump there; the smoothness term
weighs neighbour pairs by their colour difference (edge-aware). Where colour does not change,
nothing changes.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree


def particle_appearance(points: np.ndarray, gaussian_means: np.ndarray, gaussian_colors: np.ndarray,
                        k: int = 16) -> np.ndarray:
    """(P, 3) local mean colour of the `k` Gaussians nearest each particle (interior particles take
    the colour of the surface nearest them; averaging over k washes out fine texture)."""
    g = np.asarray(gaussian_means, np.float64)
    c = np.clip(np.asarray(gaussian_colors, np.float64)[:, :3], 0.0, 1.0)
    k = int(min(k, len(g)))
    _, idx = cKDTree(g).query(np.asarray(points, np.float64), k=k)
    idx = idx.reshape(len(points), k)
    return c[idx].mean(1)


def joint_space(points: np.ndarray, features: np.ndarray | None, appearance: float) -> np.ndarray:
    """Positions, with the appearance features appended in metres: a full colour change counts as
    `appearance` times the object's extent."""
    points = np.asarray(points, np.float64)
    if features is None or appearance <= 0:
        return points
    ext = float(np.max(np.ptp(points, axis=0))) if len(points) > 1 else 1.0
    return np.concatenate([points, appearance * ext * np.asarray(features, np.float64)], axis=1)


def rbf_basis(points: np.ndarray, k: int, seed: int = 0, width: float = 0.6,
              centre_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P, K) partition-of-unity basis and its (K, D) centres; each bump's sigma is `width` times the
    median distance between neighbouring centres (small: nearly piecewise constant, sharp edges).
    `points` may carry appearance columns (see `joint_space`). Centres are placed among the points
    where `centre_mask` is true (all by default): held particles, whose E the video cannot see,
    get no bump of their own and take the value of the free material next to them."""
    P = len(points)
    if k <= 1:
        return np.ones((P, 1)), points.mean(0, keepdims=True)
    cand = points if centre_mask is None or not np.any(centre_mask) else points[np.asarray(centre_mask, bool)]
    k = min(k, len(cand))
    rng = np.random.default_rng(seed)
    init = cand[rng.choice(len(cand), k, replace=False)]
    centres, _ = kmeans2(cand, init, minit="matrix", seed=seed)
    d_cc = cKDTree(centres).query(centres, k=2)[0][:, 1]
    sigma = width * float(np.median(d_cc)) + 1e-9
    d2 = ((points[:, None, :] - centres[None]) ** 2).sum(-1)
    B = np.exp(-(d2 - d2.min(1, keepdims=True)) / (2 * sigma ** 2))
    B /= B.sum(1, keepdims=True)
    return B, centres


def _logit(p):
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p) - np.log1p(-p)


def appearance_transfer_weights(weight: np.ndarray, index: np.ndarray, gaussian_features: np.ndarray,
                                particle_features: np.ndarray, tolerance: float = 0.1) -> np.ndarray:
    """A Gaussian's weights over its bound particles (N, k), tilted toward the particles of its own
    colour, so that a Gaussian at a material edge reports its own part's value rather than an
    average across the edge. Falls back to the plain weights where no bound particle matches."""
    d2 = ((np.asarray(gaussian_features)[:, None, :] - np.asarray(particle_features)[index]) ** 2).sum(-1)
    w = np.asarray(weight) * np.exp(-d2 / (2 * tolerance ** 2))
    s = w.sum(1, keepdims=True)
    return np.where(s > 1e-6, w / np.maximum(s, 1e-300), weight)


class MaterialField:
    def __init__(self, points: np.ndarray, e_range: tuple, nu_max: float, *, dtype=torch.float64,
                 device="cpu", seed: int = 0, width: float = 0.6, features: np.ndarray | None = None,
                 appearance: float = 0.0, centre_mask: np.ndarray | None = None):
        self.width = float(width)
        self.centre_mask = centre_mask
        self.points = joint_space(points, features, appearance)
        self.lo, self.hi = float(np.log(e_range[0])), float(np.log(e_range[1]))
        self.nu_max = float(nu_max)
        self.dtype, self.device, self.seed = dtype, device, seed
        self.set_basis(1)
        self.base = None        # (P,) fixed per-particle logit of a simpler model's E (nested field)
        self.theta = torch.zeros(1, dtype=dtype, device=device, requires_grad=True)
        self.w_nu = torch.zeros(1, dtype=dtype, device=device, requires_grad=True)
        self.nu_basis = self.B

    # ------------------------------------------------------------------ basis
    def set_basis(self, k: int) -> None:
        B, self.centres = rbf_basis(self.points, k, self.seed, self.width, self.centre_mask)
        self.B = torch.as_tensor(B, dtype=self.dtype, device=self.device)
        self.K = self.B.shape[1]

    def _logit_of(self, E) -> np.ndarray:
        """Per-particle E (Pa) -> the field's logit value u (log E = lo + (hi - lo) sigmoid(u))."""
        E = np.clip(np.asarray(E, np.float64), np.exp(self.lo) * 1.0001, np.exp(self.hi) * 0.9999)
        return _logit((np.log(E) - self.lo) / (self.hi - self.lo))

    def set_base(self, E: np.ndarray | None) -> None:
        """Nest the field on a fixed per-particle E (a simpler model's: uniform or parts): log E =
        lo + (hi - lo) sigmoid(u_base + B theta), the offsets theta reset to zero, so the field's
        first value is `E` itself (within the range's clip). None: a plain field again (the
        current values are kept, projected onto the basis)."""
        if E is None:
            if self.base is not None:
                with torch.no_grad():
                    u = self.u().cpu().numpy()
                self.base = None
                theta, *_ = np.linalg.lstsq(self.B.cpu().numpy(), u, rcond=None)
                self.theta = torch.as_tensor(theta, dtype=self.dtype, device=self.device).requires_grad_(True)
            return
        self.base = torch.as_tensor(self._logit_of(E), dtype=self.dtype, device=self.device)
        self.theta = torch.zeros(self.K, dtype=self.dtype, device=self.device, requires_grad=True)

    def u(self) -> torch.Tensor:
        """The per-particle logit value: the basis' part, plus the base when the field is nested."""
        u = self.B @ self.theta
        return u if self.base is None else u + self.base

    def refine(self, k: int, refine_nu: bool = False) -> None:
        """Switch to a basis of k functions, starting from the projection of the current field
        (of its offsets, when nested: the base stays as it is)."""
        with torch.no_grad():
            u = (self.B @ self.theta).cpu().numpy()
            nu_u = (self.nu_basis @ self.w_nu).cpu().numpy()
        self.set_basis(k)
        Bn = self.B.cpu().numpy()
        theta, *_ = np.linalg.lstsq(Bn, u, rcond=None)
        self.theta = torch.as_tensor(theta, dtype=self.dtype, device=self.device).requires_grad_(True)
        if refine_nu:
            w, *_ = np.linalg.lstsq(Bn, nu_u, rcond=None)
            self.nu_basis = self.B
            self.w_nu = torch.as_tensor(w, dtype=self.dtype, device=self.device).requires_grad_(True)

    def set_regions(self, labels: np.ndarray) -> None:
        """A piecewise-constant basis: one indicator per region of `labels` (0..m-1), each region
        starting from the mean of the current field over it (`fit.regions`; a nested field's base
        is folded in and dropped)."""
        from .regions import one_hot

        labels = np.asarray(labels, np.int64)
        with torch.no_grad():
            u = self.u().cpu().numpy()
        self.base = None
        B = one_hot(labels)
        theta = np.array([u[labels == r].mean() if np.any(labels == r) else 0.0 for r in range(B.shape[1])])
        self.B = torch.as_tensor(B, dtype=self.dtype, device=self.device)
        self.K = B.shape[1]
        self.theta = torch.as_tensor(theta, dtype=self.dtype, device=self.device).requires_grad_(True)

    def set_region_log_e(self, log_e: np.ndarray) -> None:
        """Set each region's (basis function's) log E (one-hot bases, no base: exact)."""
        s = (np.asarray(log_e, np.float64) - self.lo) / (self.hi - self.lo)
        self.base = None
        with torch.no_grad():
            self.theta = torch.as_tensor(_logit(s), dtype=self.dtype, device=self.device).requires_grad_(True)

    def region_log_e(self) -> np.ndarray:
        """Each basis function's log E (one-hot bases: the regions' values)."""
        with torch.no_grad():
            return (self.lo + (self.hi - self.lo) * torch.sigmoid(self.theta)).cpu().numpy()

    # ------------------------------------------------------------------ values
    def log_e(self) -> torch.Tensor:
        return self.lo + (self.hi - self.lo) * torch.sigmoid(self.u())

    def youngs(self) -> torch.Tensor:
        return torch.exp(self.log_e())

    def poisson(self) -> torch.Tensor:
        return self.nu_max * torch.sigmoid(self.nu_basis @ self.w_nu)

    def set_uniform(self, E: float, nu: float | None = None) -> None:
        s = (np.log(E) - self.lo) / (self.hi - self.lo)
        self.base = None
        with torch.no_grad():
            self.theta.copy_(torch.full_like(self.theta, float(_logit(s))))
            if nu is not None:
                self.w_nu.copy_(torch.full_like(self.w_nu, float(_logit(nu / self.nu_max))))

    def set_values(self, E: np.ndarray, nu: np.ndarray | None = None) -> None:
        """Least-squares fit of the current basis to per-particle values (resume, warm starts; a
        nested field's offsets to what `E` adds to its base: zero where `E` is the base)."""
        u = self._logit_of(E)
        if self.base is not None:
            u = u - self.base.cpu().numpy()
        theta, *_ = np.linalg.lstsq(self.B.cpu().numpy(), u, rcond=None)
        with torch.no_grad():
            self.theta = torch.as_tensor(theta, dtype=self.dtype, device=self.device).requires_grad_(True)
            if nu is not None:
                w, *_ = np.linalg.lstsq(self.nu_basis.cpu().numpy(), _logit(np.asarray(nu) / self.nu_max), rcond=None)
                self.w_nu = torch.as_tensor(w, dtype=self.dtype, device=self.device).requires_grad_(True)

    def smoothness(self, neighbours: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
        """Mean squared log-E difference over neighbour pairs (P_pairs, 2): the |grad Theta| term
        (weighted per pair when `weights` is given: edge-aware). A nested field's: of what the
        offsets add to the base's log E (the base's own part boundaries cost nothing)."""
        le = self.log_e()
        if self.base is not None:
            le = le - (self.lo + (self.hi - self.lo) * torch.sigmoid(self.base))
        d2 = (le[neighbours[:, 0]] - le[neighbours[:, 1]]) ** 2
        return d2.mean() if weights is None else (weights * d2).mean()

    def state(self) -> dict:
        return {"theta": self.theta.detach().cpu().numpy(), "w_nu": self.w_nu.detach().cpu().numpy(),
                "K": self.K, "nu_K": self.nu_basis.shape[1], "nested": self.base is not None}


def neighbour_pairs(points: np.ndarray, radius: float) -> np.ndarray:
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    return pairs.astype(np.int64) if len(pairs) else np.zeros((0, 2), np.int64)


def pair_weights(pairs: np.ndarray, features: np.ndarray | None, appearance: float,
                 tolerance: float = 0.05) -> np.ndarray:
    """Edge-aware smoothness weights: exp(-d^2 / (2 tolerance^2)) with d the pair's colour distance
    (RGB in [0, 1]): ~1 within a part (texture noise after averaging is a few hundredths), ~0
    across a colour edge. All ones without features or with the prior off."""
    if features is None or appearance <= 0 or len(pairs) == 0:
        return np.ones(len(pairs))
    f = np.asarray(features, np.float64)
    d2 = ((f[pairs[:, 0]] - f[pairs[:, 1]]) ** 2).sum(1)
    return np.exp(-d2 / (2 * tolerance ** 2))
