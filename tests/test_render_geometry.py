"""Known answers: where a Gaussian lands (cv2.projectPoints), its depth (camera-frame z), the
EWA footprint's values, culling, empty scenes."""

import cv2
import numpy as np
import pytest
import torch

from physinteract_usd.camera import Camera
from physinteract_usd.render import project, render
from render_helpers import DEVICES


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _odd_camera(width=64, height=48):
    """A camera with a rotated, translated pose, fx != fy and an off-centre principal point."""
    cam = Camera.look_at([0.7, -0.4, 1.9], [0.05, 0.1, 0.0], up=(0.1, 1.0, 0.05), width=width, height=height,
                         fov_y_deg=50)
    cam.fx *= 1.1
    cam.cx += 2.3
    cam.cy -= 1.7
    return cam


def _cv2_project(cam, pts):
    rvec, tvec = cam.rvec_tvec()
    uv, _ = cv2.projectPoints(np.asarray(pts, dtype=np.float64).reshape(-1, 1, 3), rvec, tvec, cam.K, None)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("device", DEVICES)
def test_projection_matches_cv2_and_depth_is_camera_z(device):
    cam = _odd_camera()
    g = np.random.default_rng(0)
    pts = g.uniform(-0.3, 0.3, (25, 3))
    means = torch.tensor(pts, device=device)
    covs = torch.eye(3, dtype=torch.float64, device=device).expand(25, 3, 3) * 0.01 ** 2
    p = project(means, covs, torch.full((25,), 0.8, dtype=torch.float64, device=device), cam)
    assert bool(p["visible"].all())
    uv_cv = _cv2_project(cam, pts)
    assert np.abs(p["uv"].cpu().numpy() - uv_cv).max() < 1e-6
    z = (pts @ cam.w2c_cv()[:3, :3].T + cam.w2c_cv()[:3, 3])[:, 2]
    assert np.abs(p["depth"].cpu().numpy() - z).max() < 1e-12


@pytest.mark.parametrize("device", DEVICES)
def test_isotropic_gaussian_lands_where_cv2_says(device):
    cam = _odd_camera()
    X = np.array([0.08, -0.05, 0.12])
    sigma = 0.012
    op, col = 0.7, torch.tensor([[0.9, 0.4, 0.1]], dtype=torch.float64)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    dv = lambda t: t.to(device)  # noqa: E731
    out = render(dv(torch.tensor(X[None])), dv(torch.eye(3, dtype=torch.float64)[None] * sigma ** 2), dv(col),
                 dv(torch.tensor([op], dtype=torch.float64)), cam, background=dv(bg))
    alpha = out["alpha"].cpu().numpy()
    u_cv, v_cv = _cv2_project(cam, X)[0]
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    cu = (alpha * (ii + 0.5)).sum() / alpha.sum()
    cv = (alpha * (jj + 0.5)).sum() / alpha.sum()
    assert abs(cu - u_cv) < 0.05 and abs(cv - v_cv) < 0.05, (cu, cv, u_cv, v_cv)
    # the brightest pixel is the one containing the projected point
    j, i = np.unravel_index(alpha.argmax(), alpha.shape)
    assert (i, j) == (int(np.floor(u_cv)), int(np.floor(v_cv)))
    # expected depth is the camera-frame z wherever the Gaussian is drawn
    z = cam.world_to_camera(X[None])[0, 2]
    hit = alpha > 0
    assert np.abs(out["depth"].cpu().numpy()[hit] - z).max() < 1e-12
    # pixel values: alpha = op exp(-d^T cov2d^-1 d / 2) - 1/255 (>= 0), cov2d = J W Sigma W^T J^T + 0.3 I (numpy here)
    w2c = cam.w2c_cv()
    x, y, zc = w2c[:3, :3] @ X + w2c[:3, 3]
    J = np.array([[cam.fx / zc, 0, -cam.fx * x / zc ** 2], [0, cam.fy / zc, -cam.fy * y / zc ** 2]])
    Wr = w2c[:3, :3]
    cov2 = J @ Wr @ (np.eye(3) * sigma ** 2) @ Wr.T @ J.T + 0.3 * np.eye(2)
    d = np.stack([ii + 0.5 - u_cv, jj + 0.5 - v_cv], -1)
    s2 = np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(cov2), d)
    expect = np.maximum(op * np.exp(-0.5 * s2) - 1 / 255, 0.0)  # the continuous floor (default)
    assert np.abs(alpha - expect).max() < 1e-12
    rgb = out["rgb"].cpu().numpy()
    assert np.abs(rgb - (expect[..., None] * col.numpy() + (1 - expect[..., None]) * bg.numpy())).max() < 1e-12


@pytest.mark.parametrize("device", DEVICES)
def test_anisotropic_footprint_follows_ewa(device):
    """A flat disc seen obliquely: the footprint is the EWA ellipse (numpy formula)."""
    cam = _odd_camera()
    X = np.array([-0.05, 0.02, 0.0])
    Rz = cv2.Rodrigues(np.array([0.4, -0.7, 0.2]))[0]
    S = Rz @ np.diag([0.08, 0.04, 0.0]) ** 2 @ Rz.T  # rank 2: a surfel
    out = render(torch.tensor(X[None], device=device), torch.tensor(S[None], device=device),
                 torch.ones(1, 3, dtype=torch.float64, device=device),
                 torch.tensor([0.95], dtype=torch.float64, device=device), cam)
    alpha = out["alpha"].cpu().numpy()
    w2c = cam.w2c_cv()
    x, y, zc = w2c[:3, :3] @ X + w2c[:3, 3]
    J = np.array([[cam.fx / zc, 0, -cam.fx * x / zc ** 2], [0, cam.fy / zc, -cam.fy * y / zc ** 2]])
    cov2 = J @ w2c[:3, :3] @ S @ w2c[:3, :3].T @ J.T + 0.3 * np.eye(2)
    u, v = _cv2_project(cam, X)[0]
    jj, ii = np.mgrid[0:cam.height, 0:cam.width]
    d = np.stack([ii + 0.5 - u, jj + 0.5 - v], -1)
    s2 = np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(cov2), d)
    expect = np.clip(0.95 * np.exp(-0.5 * s2) - 1 / 255, 0.0, 0.99)  # the continuous floor (default)
    assert np.abs(alpha - expect).max() < 1e-12
    assert (alpha > 0).sum() > 20


@pytest.mark.parametrize("device", DEVICES)
def test_culled_gaussians_draw_nothing(device):
    cam = Camera.look_at([0, 0, 2.0], [0, 0, 0], width=32, height=32, fov_y_deg=40)
    means = torch.tensor([[0.0, 0.0, 3.0],     # behind the camera
                          [0.0, 0.0, -200.0],  # beyond far
                          [5.0, 0.0, 0.0],     # far outside the image
                          [0.0, 0.0, 0.0]],    # visible but opacity below 1/255
                         dtype=torch.float64, device=device)
    covs = torch.eye(3, dtype=torch.float64, device=device).expand(4, 3, 3) * 0.05 ** 2
    op = torch.tensor([0.9, 0.9, 0.9, 0.003], dtype=torch.float64, device=device)
    ins = [t.clone().requires_grad_(True) for t in (means, covs, torch.rand(4, 3, dtype=torch.float64, device=device), op)]
    bg = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64, device=device)
    out = render(*ins, cam, background=bg)
    assert float(out["alpha"].detach().abs().max()) == 0.0
    assert float((out["rgb"].detach() - 0.5).abs().max()) == 0.0
    out["rgb"].sum().backward()
    for t in ins:
        assert float(t.grad.abs().max()) == 0.0
    p = project(means, covs, op, cam)
    assert not bool(p["visible"].any())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_scene_renders_background(dtype):
    cam = Camera.look_at([0, 0, 2.0], [0, 0, 0], width=20, height=12)
    bg = torch.rand(12, 20, 3, dtype=dtype)
    ins = [torch.zeros(0, 3, dtype=dtype, requires_grad=True), torch.zeros(0, 3, 3, dtype=dtype, requires_grad=True),
           torch.zeros(0, 3, dtype=dtype, requires_grad=True), torch.zeros(0, dtype=dtype, requires_grad=True)]
    out = render(*ins, cam, background=bg)
    assert torch.equal(out["rgb"].detach(), bg) and float(out["alpha"].detach().abs().max()) == 0
    out["rgb"].sum().backward()
    assert ins[0].grad.shape == (0, 3)


def test_per_frame_camera_must_be_made_static():
    cam = Camera.look_at([0, 0, 2.0], [0, 0, 0], width=20, height=12)
    moving = Camera(cam.fx, cam.fy, cam.cx, cam.cy, 20, 12, np.stack([cam.c2w, cam.c2w]))
    g = [torch.zeros(1, 3), torch.eye(3)[None] * 1e-3, torch.ones(1, 3), torch.ones(1)]
    with pytest.raises(ValueError):
        render(*g, moving)
    assert render(*g, moving.at(1))["rgb"].shape == (12, 20, 3)
