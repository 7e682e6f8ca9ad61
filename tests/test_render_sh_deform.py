"""SH colours (3DGS basis), Gaussians following particles (Sigma' = F Sigma F^T), background."""

import numpy as np
import pytest
import torch

from physinteract_usd.camera import Camera
from physinteract_usd.gaussians import Gaussians, quat_to_rotmat as np_quat_to_rotmat
from physinteract_usd.render import (GaussianBinding, covariance_from_scales_quats, deform_covariances,
                                     estimate_background, eval_sh, polar_rotation, render,
                                     scales_quats_from_covariance, sh_basis, sh_to_color)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def test_sh_basis_is_orthonormal_up_to_degree_3():
    d = torch.tensor(_fibonacci_sphere(200_000))
    Y = sh_basis(d, 3)
    gram = 4 * np.pi * (Y.T @ Y).numpy() / len(d)
    assert np.abs(gram - np.eye(16)).max() < 1e-3


def test_sh_signs_follow_3dgs():
    # 3DGS: result = C0 sh0 - C1 y sh1 + C1 z sh2 - C1 x sh3 + C2[0] xy sh4 + ... + C3[6] x (xx - 3yy) sh15
    d = torch.tensor([[0.6, 0.0, 0.8], [0.0, 1.0, 0.0], [0.48, 0.6, 0.64]], dtype=torch.float64)
    Y = sh_basis(d, 3).numpy()
    x, y, z = d.numpy().T
    C1 = 0.4886025119029199
    assert np.allclose(Y[:, 1:4], np.stack([-C1 * y, C1 * z, -C1 * x], 1))
    assert np.allclose(Y[:, 4], 1.0925484305920792 * x * y)
    assert np.allclose(Y[:, 15], -0.5900435899266435 * x * (x * x - 3 * y * y))


def test_sh_colour_dc_and_clamp():
    g = Gaussians.from_colors(np.zeros((2, 3)), [[0.2, 0.5, 0.9], [1.0, 0.0, 0.3]], 0.01)
    sh = torch.tensor(g.sh)
    col = sh_to_color(sh, torch.tensor(g.means) + 1.0, torch.zeros(3, dtype=torch.float64))
    assert np.allclose(col.numpy(), g.colors)
    sh3 = torch.zeros(1, 16, 3, dtype=torch.float64)
    sh3[0, 0] = -5.0  # colour far below zero: clamped
    assert float(sh_to_color(sh3, torch.ones(1, 3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)).max()) == 0.0
    with pytest.raises(ValueError):
        eval_sh(torch.zeros(1, 5, 3), torch.ones(1, 3))


def test_render_with_sh_uses_view_direction():
    cam = Camera.look_at([0, 0, 2.0], [0, 0, 0], width=16, height=16)
    means = torch.zeros(1, 3, dtype=torch.float64)
    covs = torch.eye(3, dtype=torch.float64)[None] * 0.05 ** 2
    sh = torch.zeros(1, 4, 3, dtype=torch.float64, requires_grad=True)
    with torch.no_grad():
        sh[0, 2] = torch.tensor([0.5, 0.0, -0.5])  # z-dependent (Y_1,0 = C1 z)
    op = torch.tensor([0.9], dtype=torch.float64)
    out = render(means, covs, sh, op, cam)
    # view direction from the camera (0,0,2) to the origin is -z: colour = 0.5 + C1 * (-1) * coeff
    expect = 0.5 - 0.4886025119029199 * np.array([0.5, 0.0, -0.5])
    c = out["rgb"][8, 8].detach().numpy() / float(out["alpha"][8, 8].detach())
    assert np.allclose(c, expect, atol=1e-12)
    out["rgb"].sum().backward()
    assert float(sh.grad[0, 2].abs().sum()) > 0


def test_covariance_helpers_round_trip():
    g = np.random.default_rng(0)
    q = g.standard_normal((20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    s = g.uniform(0.01, 0.1, (20, 3))
    cov = covariance_from_scales_quats(torch.tensor(s), torch.tensor(q)).numpy()
    ref = Gaussians(np.zeros((20, 3)), s, q, np.full(20, 0.5), np.zeros((20, 1, 3))).covariances()
    assert np.abs(cov - ref).max() < 1e-14
    s2, q2 = scales_quats_from_covariance(cov)
    R2 = np_quat_to_rotmat(q2)
    assert np.abs((R2 * s2[:, None, :] ** 2) @ np.swapaxes(R2, 1, 2) - cov).max() < 1e-12
    assert (q2[:, 0] >= 0).all()


def test_binding_follows_particles_and_deforms_covariance():
    g = torch.Generator().manual_seed(0)
    X0 = torch.rand(30, 3, generator=g, dtype=torch.float64)
    mu0 = X0[:10] + 0.01 * torch.randn(10, 3, generator=g, dtype=torch.float64)
    cov0 = covariance_from_scales_quats(torch.full((10, 3), 0.02, dtype=torch.float64),
                                        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(10, 4))
    b = GaussianBinding.from_index(np.arange(10), mu0, X0, dtype=torch.float64)
    # rigid motion: rotation + translation of every particle moves Gaussians rigidly
    Rm = torch.tensor(np_quat_to_rotmat(np.array([0.9, 0.1, -0.3, 0.2])), dtype=torch.float64)
    t = torch.tensor([0.3, -0.1, 0.5], dtype=torch.float64)
    x = X0 @ Rm.T + t
    F = Rm.expand(30, 3, 3)
    means, covs = b.apply(x, F, cov0)
    assert torch.allclose(means, mu0 @ Rm.T + t, atol=1e-12)
    assert torch.allclose(covs, Rm @ cov0 @ Rm.T, atol=1e-14)
    # k-NN interpolation reproduces an affine deformation exactly
    A = torch.tensor([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.05, 0.0, 1.1]], dtype=torch.float64)
    bk = GaussianBinding.knn(mu0, X0, k=4, dtype=torch.float64)
    assert torch.allclose(bk.weight.sum(1), torch.ones(10, dtype=torch.float64))
    means, covs = bk.apply(X0 @ A.T + t, A.expand(30, 3, 3), cov0)
    assert torch.allclose(means, mu0 @ A.T + t, atol=1e-12)
    assert torch.allclose(covs, deform_covariances(cov0, A.expand(10, 3, 3)), atol=1e-14)
    # gradients reach particle positions and F
    xr = x.clone().requires_grad_(True)
    Fr = F.clone().requires_grad_(True)
    m, c = b.apply(xr, Fr, cov0)
    (m.sum() + c.sum()).backward()
    assert float(xr.grad[:10].abs().sum()) > 0 and float(Fr.grad[:10].abs().sum()) > 0
    assert float(xr.grad[10:].abs().sum()) == 0


def test_polar_rotation():
    Rm = torch.tensor(np_quat_to_rotmat(np.array([0.5, 0.5, -0.5, 0.5])), dtype=torch.float64)
    S = torch.tensor([[1.3, 0.1, 0.0], [0.1, 0.8, 0.0], [0.0, 0.0, 1.1]], dtype=torch.float64)
    assert torch.allclose(polar_rotation((Rm @ S)[None])[0], Rm, atol=1e-12)


def test_background_median_outside_masks():
    g = np.random.default_rng(0)
    H, W, T = 20, 24, 9
    bg = g.random((H, W, 3)).astype(np.float32)
    frames = np.repeat(bg[None], T, 0) + 0.01 * g.standard_normal((T, H, W, 3)).astype(np.float32)
    masks = np.zeros((T, H, W), bool)
    for t in range(T):  # an object moving left to right, covering 6 columns
        masks[t, 5:15, 2 * t:2 * t + 6] = True
        frames[t, masks[t]] = [1.0, 0.0, 0.0]
    masks[:, 0:2, 22:24] = True  # never seen
    est, seen = estimate_background(frames, masks, dilate=1, fallback=(0.0, 1.0, 0.0), return_seen=True)
    ok = seen > 0
    assert (seen[0:2, 22:24] == 0).all()
    assert np.abs(est[ok] - bg[ok]).max() < 0.05
    assert np.allclose(est[0:2, 22:24], [0.0, 1.0, 0.0])
    # uint8 frames, no masks: the plain median
    u8 = (np.repeat(bg[None], 3, 0) * 255).astype(np.uint8)
    assert np.abs(estimate_background(u8) - u8[0] / 255.0).max() < 1e-6
