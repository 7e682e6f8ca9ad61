"""Gaussians that follow the simulated particles (torch; autograd differentiates it).

Each Gaussian i is bound to k particles j (k = 1: the particle it follows, `fill.SimParticles.binding`;
k > 1: inverse-distance weights over its k nearest rest particles) with weights w_ij (sum 1) and
rest offsets o_ij = mu0_i - X0_j. With particle positions x_j and deformation gradients F_j:

    mean_i  = sum_j w_ij (x_j + F_j o_ij)          (x_j + o_ij without F)
    F_i     = sum_j w_ij F_j
    Sigma_i = F_i Sigma0_i F_i^T

A Gaussian at its particle (o = 0, k = 1) moves exactly with it. Helpers convert between
covariances and (scales, quaternions) for the USD writer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..gaussians import scales_quats_from_covariance  # noqa: F401  (re-exported)


@dataclass
class GaussianBinding:
    index: torch.Tensor   # (N, k) long, particle indices
    weight: torch.Tensor  # (N, k) float, rows sum to 1
    offset: torch.Tensor  # (N, k, 3) float, rest offsets mu0_i - X0_j

    @staticmethod
    def from_index(binding, means0, particles0, *, keep_offsets: bool = True,
                   dtype=torch.float32, device="cpu") -> "GaussianBinding":
        """k = 1 binding: Gaussian i follows particle binding[i]."""
        idx = torch.as_tensor(np.asarray(binding), dtype=torch.long, device=device).reshape(-1, 1)
        m0 = torch.as_tensor(np.asarray(means0), dtype=dtype, device=device)
        x0 = torch.as_tensor(np.asarray(particles0), dtype=dtype, device=device)
        off = (m0 - x0[idx[:, 0]])[:, None, :]
        if not keep_offsets:
            off = torch.zeros_like(off)
        return GaussianBinding(idx, torch.ones(idx.shape, dtype=dtype, device=device), off)

    @staticmethod
    def knn(means0, particles0, k: int = 4, *, power: float = 1.0, dtype=torch.float32,
            device="cpu") -> "GaussianBinding":
        """Inverse-distance weights (1 / d^power) over the k nearest rest particles."""
        from scipy.spatial import cKDTree

        m0 = np.asarray(means0, dtype=np.float64)
        x0 = np.asarray(particles0, dtype=np.float64)
        k = int(min(k, len(x0)))
        d, idx = cKDTree(x0).query(m0, k=k)
        d, idx = d.reshape(len(m0), k), idx.reshape(len(m0), k)
        w = 1.0 / np.maximum(d, 1e-9) ** power
        exact = d[:, 0] < 1e-9
        w[exact] = 0.0
        w[exact, 0] = 1.0
        w /= w.sum(1, keepdims=True)
        off = m0[:, None, :] - x0[idx]
        t = lambda a, dt=dtype: torch.as_tensor(a, dtype=dt, device=device)  # noqa: E731
        return GaussianBinding(t(idx, torch.long), t(w), t(off))

    def to(self, dtype=None, device=None) -> "GaussianBinding":
        return GaussianBinding(self.index.to(device=device), self.weight.to(dtype=dtype, device=device),
                               self.offset.to(dtype=dtype, device=device))

    def deformation(self, F: torch.Tensor) -> torch.Tensor:
        """Per-Gaussian deformation gradient (N, 3, 3) from per-particle F (P, 3, 3); (M, N, 3, 3)
        from a batch of M states (M, P, 3, 3)."""
        if F.dim() == 4:
            return (self.weight[:, :, None, None] * F[:, self.index]).sum(2)
        return (self.weight[:, :, None, None] * F[self.index]).sum(1)

    def apply(self, x: torch.Tensor, F: torch.Tensor | None = None, cov0: torch.Tensor | None = None):
        """Particle positions x (P, 3) and deformation gradients F (P, 3, 3) or None ->
        (means (N, 3), covs (N, 3, 3) = F_i cov0 F_i^T, or None without cov0). A batch of M states
        x (M, P, 3), F (M, P, 3, 3) gives (M, N, 3) and (M, N, 3, 3)."""
        if x.dim() == 3:
            return self._apply_batch(x, F, cov0)
        xj = x[self.index]  # (N, k, 3)
        if F is None:
            means = (self.weight[:, :, None] * (xj + self.offset)).sum(1)
            return means, cov0
        Fj = F[self.index]  # (N, k, 3, 3)
        moved = xj + torch.einsum("nkab,nkb->nka", Fj, self.offset)
        means = (self.weight[:, :, None] * moved).sum(1)
        if cov0 is None:
            return means, None
        return means, deform_covariances(cov0, self.deformation(F))

    def _apply_batch(self, x, F, cov0):
        xj = x[:, self.index]  # (M, N, k, 3)
        if F is None:
            return (self.weight[:, :, None] * (xj + self.offset)).sum(2), cov0
        Fj = F[:, self.index]  # (M, N, k, 3, 3)
        moved = xj + torch.einsum("mnkab,nkb->mnka", Fj, self.offset)
        means = (self.weight[:, :, None] * moved).sum(2)
        if cov0 is None:
            return means, None
        return means, deform_covariances(cov0, self.deformation(F))


def deform_covariances(cov0: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """Sigma' = F Sigma0 F^T, (N, 3, 3)."""
    return F @ cov0 @ F.transpose(-1, -2)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) quaternions w x y z (normalised here) -> (N, 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def covariance_from_scales_quats(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """R diag(s)^2 R^T (the `gaussians.Gaussians` convention), (N, 3, 3)."""
    M = quat_to_rotmat(quats) * scales[:, None, :]
    return M @ M.transpose(-1, -2)


def polar_rotation(F: torch.Tensor) -> torch.Tensor:
    """Rotation part R of F = R S (via SVD), (N, 3, 3); e.g. for rotating SH view directions."""
    U, _, Vh = torch.linalg.svd(F)
    d = torch.sign(torch.det(U @ Vh))
    D = torch.ones(F.shape[:-1], dtype=F.dtype, device=F.device)
    D[..., -1] = d
    return (U * D[..., None, :]) @ Vh
