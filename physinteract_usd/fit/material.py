"""The material field's parameterisation for the fit.

log E per particle = lo + (hi - lo) * sigmoid(B theta): a smooth map into the allowed range
[E_min, E_max] (the CFL substep was chosen at E_max, so E never exceeds it), with B a
partition-of-unity basis of K normalised Gaussian bumps on k-means centres of the rest particles.
Coarse-to-fine: K = 1 (uniform), then more centres; each refinement starts from the projection of
the current field. nu is one value per basis function too, nu = nu_max * sigmoid(w), fitted at
the coarsest levels only (it is weakly observable).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree


def rbf_basis(points: np.ndarray, k: int, seed: int = 0, width: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """(P, K) partition-of-unity basis and its (K, 3) centres; each bump's sigma is `width` times the
    median distance between neighbouring centres (small: nearly piecewise constant, sharp edges)."""
    P = len(points)
    if k <= 1:
        return np.ones((P, 1)), points.mean(0, keepdims=True)
    k = min(k, P)
    rng = np.random.default_rng(seed)
    init = points[rng.choice(P, k, replace=False)]
    centres, _ = kmeans2(points, init, minit="matrix", seed=seed)
    d_cc = cKDTree(centres).query(centres, k=2)[0][:, 1]
    sigma = width * float(np.median(d_cc)) + 1e-9
    d2 = ((points[:, None, :] - centres[None]) ** 2).sum(-1)
    B = np.exp(-(d2 - d2.min(1, keepdims=True)) / (2 * sigma ** 2))
    B /= B.sum(1, keepdims=True)
    return B, centres


def _logit(p):
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p) - np.log1p(-p)


class MaterialField:
    def __init__(self, points: np.ndarray, e_range: tuple, nu_max: float, *, dtype=torch.float64,
                 device="cpu", seed: int = 0, width: float = 0.6):
        self.width = float(width)
        self.points = np.asarray(points, dtype=np.float64)
        self.lo, self.hi = float(np.log(e_range[0])), float(np.log(e_range[1]))
        self.nu_max = float(nu_max)
        self.dtype, self.device, self.seed = dtype, device, seed
        self.set_basis(1)
        self.theta = torch.zeros(1, dtype=dtype, device=device, requires_grad=True)
        self.w_nu = torch.zeros(1, dtype=dtype, device=device, requires_grad=True)
        self.nu_basis = self.B

    # ------------------------------------------------------------------ basis
    def set_basis(self, k: int) -> None:
        B, self.centres = rbf_basis(self.points, k, self.seed, self.width)
        self.B = torch.as_tensor(B, dtype=self.dtype, device=self.device)
        self.K = self.B.shape[1]

    def refine(self, k: int, refine_nu: bool = False) -> None:
        """Switch to a basis of k functions, starting from the projection of the current field."""
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

    # ------------------------------------------------------------------ values
    def log_e(self) -> torch.Tensor:
        return self.lo + (self.hi - self.lo) * torch.sigmoid(self.B @ self.theta)

    def youngs(self) -> torch.Tensor:
        return torch.exp(self.log_e())

    def poisson(self) -> torch.Tensor:
        return self.nu_max * torch.sigmoid(self.nu_basis @ self.w_nu)

    def set_uniform(self, E: float, nu: float | None = None) -> None:
        s = (np.log(E) - self.lo) / (self.hi - self.lo)
        with torch.no_grad():
            self.theta.copy_(torch.full_like(self.theta, float(_logit(s))))
            if nu is not None:
                self.w_nu.copy_(torch.full_like(self.w_nu, float(_logit(nu / self.nu_max))))

    def set_values(self, E: np.ndarray, nu: np.ndarray | None = None) -> None:
        """Least-squares fit of the current basis to per-particle values (resume, warm starts)."""
        s = (np.log(np.clip(E, np.exp(self.lo) * 1.0001, np.exp(self.hi) * 0.9999)) - self.lo) / (self.hi - self.lo)
        theta, *_ = np.linalg.lstsq(self.B.cpu().numpy(), _logit(s), rcond=None)
        with torch.no_grad():
            self.theta = torch.as_tensor(theta, dtype=self.dtype, device=self.device).requires_grad_(True)
            if nu is not None:
                w, *_ = np.linalg.lstsq(self.nu_basis.cpu().numpy(), _logit(np.asarray(nu) / self.nu_max), rcond=None)
                self.w_nu = torch.as_tensor(w, dtype=self.dtype, device=self.device).requires_grad_(True)

    def smoothness(self, neighbours: torch.Tensor) -> torch.Tensor:
        """Mean squared log-E difference over neighbour pairs (P_pairs, 2): the |grad Theta| term."""
        le = self.log_e()
        return ((le[neighbours[:, 0]] - le[neighbours[:, 1]]) ** 2).mean()

    def state(self) -> dict:
        return {"theta": self.theta.detach().cpu().numpy(), "w_nu": self.w_nu.detach().cpu().numpy(),
                "K": self.K, "nu_K": self.nu_basis.shape[1]}


def neighbour_pairs(points: np.ndarray, radius: float) -> np.ndarray:
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    return pairs.astype(np.int64) if len(pairs) else np.zeros((0, 2), np.int64)
