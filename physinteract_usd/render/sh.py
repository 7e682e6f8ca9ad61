"""Real spherical harmonics up to degree 3, 3DGS's basis and sign conventions, in torch.

colour = max(0, 0.5 + sum_k sh_k Y_k(dir)), dir = normalise(mean - camera centre), in the frame
the SH coefficients were fitted in (world, or the Gaussian's rest frame: pass `rotations` to
rotate the view direction back into it when the Gaussian has turned with its particle).
sh is (N, K, 3), coefficient-major, K = (deg + 1)^2 (`gaussians.Gaussians.sh`).
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, 3) unit directions -> (N, (degree + 1)^2) basis values Y_k (3DGS ordering and signs)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree {degree} not in 0..3")
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [torch.full_like(x, SH_C0)]
    if degree > 0:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree > 2:
        out += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(out, 1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """sum_k sh_k Y_k(dir): (N, K, 3) coefficients, (N, 3) unit directions -> (N, 3)."""
    k = sh.shape[1]
    degree = int(round(k ** 0.5)) - 1
    if (degree + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients is not (degree+1)^2")
    basis = sh_basis(dirs, degree)
    return (sh * basis[:, :, None]).sum(1)


def sh_to_color(sh: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor,
                rotations: torch.Tensor | None = None) -> torch.Tensor:
    """View-dependent colour (N, 3) = max(0, 0.5 + SH(dir)); dir from the camera centre to the mean.

    rotations: optional (N, 3, 3) rotation of each Gaussian since its rest pose; the view
    direction is then rotated back (R^T dir) before evaluating the SH. Differentiable in sh and
    means (and rotations).
    """
    d = means - camera_center.to(means.dtype)
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    if rotations is not None:
        d = torch.einsum("nji,nj->ni", rotations, d)
    return (0.5 + eval_sh(sh, d)).clamp_min(0.0)
