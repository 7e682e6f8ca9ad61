"""The Warp rasterizer against the dense pure-torch reference (tests/render_reference.py):
forward images within 1e-4 max abs, gradients within 1e-3 relative (float64)."""

import numpy as np
import pytest
import torch

from physinteract_usd.camera import Camera
from physinteract_usd.render import RasterSettings, render
from render_helpers import DEVICES
from render_reference import make_scene, reference_render_camera


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def cameras():
    a = Camera.look_at([0.3, 0.4, 2.0], [0.0, 0.0, 0.0], width=37, height=29, fov_y_deg=40)
    a.cx += 1.3  # principal point off centre
    a.fx *= 1.07  # non-square pixels
    b = Camera.look_at([-1.2, 0.5, -1.1], [0.05, -0.02, 0.0], width=64, height=48, fov_y_deg=55)
    return {"oblique37x29": a, "back64x48": b}


CAMS = cameras()


def _grad_close(g, g_ref, rtol=1e-3, atol_frac=1e-6):
    """Elementwise |g - g_ref| <= rtol |g_ref| + atol_frac max|g_ref|."""
    g, g_ref = g.detach().double().cpu(), g_ref.detach().double().cpu()
    tol = rtol * g_ref.abs() + atol_frac * g_ref.abs().max().clamp_min(1e-30)
    bad = (g - g_ref).abs() > tol
    return not bool(bad.any()), float(((g - g_ref).abs() / (g_ref.abs() + 1e-30)).max())


def _weights(shape_list, seed=1):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(s, generator=g, dtype=torch.float64) for s in shape_list]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("cam_name", list(CAMS))
@pytest.mark.parametrize("seed,thin", [(0, 0.0), (1, 0.5)])
def test_forward_matches_reference(device, dtype, cam_name, seed, thin):
    cam = CAMS[cam_name]
    means, covs, cols, op = make_scene(seed, 48, torch.float64, thin=thin)
    bg = torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64)
    ref = reference_render_camera(means, covs, cols, op, cam, background=bg)
    to = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
    out = render(to(means), to(covs), to(cols), to(op), cam, background=to(bg))
    assert out["rgb"].shape == (cam.height, cam.width, 3)
    assert out["alpha"].shape == out["depth"].shape == (cam.height, cam.width)
    assert float(ref[1].max()) > 0.5  # the scene is in view
    for name, r in zip(["rgb", "alpha", "depth_acc"], ref):
        err = float((out[name].double().cpu() - r).abs().max())
        assert err < 1e-4, (name, err)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cam_name", list(CAMS))
@pytest.mark.parametrize("seed,thin", [(2, 0.0), (3, 0.5)])
def test_gradients_match_reference(device, cam_name, seed, thin):
    cam = CAMS[cam_name]
    scene = make_scene(seed, 40, torch.float64, thin=thin)
    H, W = cam.height, cam.width
    wr, wa, wd = _weights([(H, W, 3), (H, W), (H, W)], seed)
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)

    ours = [t.clone().to(device).requires_grad_(True) for t in scene]
    out = render(*ours, cam, background=bg.to(device))
    loss = ((out["rgb"] * wr.to(device)).sum() + (out["alpha"] * wa.to(device)).sum()
            + (out["depth_acc"] * wd.to(device)).sum())
    loss.backward()

    refs = [t.clone().requires_grad_(True) for t in scene]
    rr = reference_render_camera(*refs, cam, background=bg)
    loss_ref = (rr[0] * wr).sum() + (rr[1] * wa).sum() + (rr[2] * wd).sum()
    loss_ref.backward()
    assert abs(loss.item() - loss_ref.item()) < 1e-9 * max(1.0, abs(loss_ref.item()))
    for name, a, b in zip(["means", "covs", "colors", "opacities"], ours, refs):
        assert float(b.grad.abs().max()) > 0, name
        ok, rel = _grad_close(a.grad, b.grad)
        assert ok, (name, rel)


@pytest.mark.parametrize("device", DEVICES)
def test_float32_gradients_close_to_float64_reference(device):
    cam = CAMS["oblique37x29"]
    scene = make_scene(4, 40, torch.float64)
    H, W = cam.height, cam.width
    wr, wa, wd = _weights([(H, W, 3), (H, W), (H, W)], 4)
    ours = [t.clone().float().to(device).requires_grad_(True) for t in scene]
    out = render(*ours, cam)
    ((out["rgb"] * wr.float().to(device)).sum() + (out["alpha"] * wa.float().to(device)).sum()
     + (out["depth_acc"] * wd.float().to(device)).sum()).backward()
    refs = [t.clone().requires_grad_(True) for t in scene]
    rr = reference_render_camera(*refs, cam)
    ((rr[0] * wr).sum() + (rr[1] * wa).sum() + (rr[2] * wd).sum()).backward()
    for name, a, b in zip(["means", "covs", "colors", "opacities"], ours, refs):
        err = float((a.grad.double().cpu() - b.grad).abs().max() / b.grad.abs().max())
        assert err < 1e-3, (name, err)


@pytest.mark.parametrize("device", DEVICES)
def test_background_image_and_normalised_depth(device):
    cam = CAMS["back64x48"]
    means, covs, cols, op = make_scene(5, 30, torch.float64)
    g = torch.Generator().manual_seed(0)
    bg = torch.rand(cam.height, cam.width, 3, generator=g, dtype=torch.float64)
    rgb, alpha, dacc = reference_render_camera(means, covs, cols, op, cam, background=bg)
    dv = lambda t: t.to(device)  # noqa: E731
    out = render(dv(means), dv(covs), dv(cols), dv(op), cam, background=dv(bg))
    assert float((out["rgb"].cpu() - rgb).abs().max()) < 1e-10
    hit = alpha > 1e-3
    assert hit.any() and (~hit).any()
    depth = out["depth"].cpu()
    assert float((depth[hit] - dacc[hit] / alpha[hit]).abs().max()) < 1e-10
    assert float(depth[alpha == 0].abs().max()) == 0.0
    # expected depth lies between the nearest and the farthest Gaussian
    z = torch.as_tensor(cam.world_to_camera(means.numpy())[:, 2])
    assert float(depth[hit].min()) >= float(z.min()) - 1e-9 and float(depth[hit].max()) <= float(z.max()) + 1e-9


@pytest.mark.parametrize("tile_size,lockstep", [(4, False), (8, True), (16, True), (16, False), (32, False)])
def test_tiling_and_lockstep_do_not_change_image_or_gradients(tile_size, lockstep):
    cam = CAMS["back64x48"]
    scene = make_scene(6, 50, torch.float64)
    H, W = cam.height, cam.width
    wr, wa, wd = _weights([(H, W, 3), (H, W), (H, W)], 6)
    results = []
    for settings in (RasterSettings(tile_size=8, lockstep=False),
                     RasterSettings(tile_size=tile_size, lockstep=lockstep)):
        ins = [t.clone().requires_grad_(True) for t in scene]
        out = render(*ins, cam, settings=settings)
        ((out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + (out["depth_acc"] * wd).sum()).backward()
        results.append((out, [t.grad for t in ins]))
    (a, ga), (b, gb) = results
    for k in ("rgb", "alpha", "depth_acc"):
        assert float((a[k] - b[k]).detach().abs().max()) < 1e-12
    for x, y in zip(ga, gb):
        assert float((x - y).abs().max()) <= 1e-10 * float(x.abs().max())


def test_many_overlapping_gaussians_hit_the_transmittance_cutoff():
    """Dense opaque stack: most pixels stop early at T < 1e-4; still equal to the reference."""
    cam = CAMS["oblique37x29"]
    means, covs, cols, op = make_scene(7, 120, torch.float64, radius=0.15, scale=(0.05, 0.12), opacity=(0.5, 1.0))
    ref = reference_render_camera(means, covs, cols, op, cam)
    out = render(means, covs, cols, op, cam)
    assert float(ref[1].max()) > 0.999
    for name, r in zip(["rgb", "alpha", "depth_acc"], ref):
        assert float((out[name] - r).abs().max()) < 1e-10, name
    ours = [t.clone().requires_grad_(True) for t in (means, covs, cols, op)]
    o = render(*ours, cam)
    (o["rgb"].sum() + 0.3 * o["depth_acc"].sum()).backward()
    refs = [t.clone().requires_grad_(True) for t in (means, covs, cols, op)]
    rr = reference_render_camera(*refs, cam)
    (rr[0].sum() + 0.3 * rr[2].sum()).backward()
    for name, a, b in zip(["means", "covs", "colors", "opacities"], ours, refs):
        ok, rel = _grad_close(a.grad, b.grad)
        assert ok, (name, rel)


def test_no_nan_with_degenerate_covariances():
    """Zero covariance (a point), rank-1 covariance (a needle) and an exactly flat disc: the 0.3 px^2
    low-pass keeps every 2D covariance invertible."""
    cam = CAMS["back64x48"]
    means = torch.zeros(3, 3, dtype=torch.float64)
    means[1, 0] = 0.1
    means[2, 1] = -0.1
    covs = torch.zeros(3, 3, 3, dtype=torch.float64)
    covs[1, 0, 0] = 0.05 ** 2
    covs[2, 0, 0] = covs[2, 1, 1] = 0.04 ** 2
    cols = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], dtype=torch.float64)
    op = torch.full((3,), 0.9, dtype=torch.float64)
    ins = [t.clone().requires_grad_(True) for t in (means, covs, cols, op)]
    out = render(*ins, cam)
    ref = reference_render_camera(means, covs, cols, op, cam)
    assert float((out["rgb"].detach() - ref[0]).abs().max()) < 1e-10
    assert float(out["alpha"].detach().max()) > 0.5
    (out["rgb"].sum() + out["alpha"].sum()).backward()
    for t in ins:
        assert torch.isfinite(t.grad).all()
    assert np.isfinite(out["depth"].detach().numpy()).all()


def test_tiled_backward_matches_pixel_backward():
    """The block-reduction backward (CUDA's alternative) gives the same gradients; on the CPU it
    runs with Warp's experimental CPU blocks (fibers)."""
    import warp as wp

    cam = CAMS["oblique37x29"]
    scene = make_scene(8, 40, torch.float64, thin=0.3)
    H, W = cam.height, cam.width
    wr, wa, wd = _weights([(H, W, 3), (H, W), (H, W)], 8)
    old = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        grads = []
        for settings in (RasterSettings(tile_size=4), RasterSettings(tile_size=4, backward="tiled")):
            ins = [t.clone().requires_grad_(True) for t in scene]
            out = render(*ins, cam, settings=settings)
            ((out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + (out["depth_acc"] * wd).sum()).backward()
            grads.append([t.grad for t in ins])
    finally:
        wp.config.enable_cpu_blocks = old
    for x, y in zip(*grads):
        assert float(x.abs().max()) > 0
        assert float((x - y).abs().max()) <= 1e-10 * float(x.abs().max())


def test_alpha_clamp_and_fov_clamp_paths():
    """Opaque Gaussians whose alpha hits the 0.99 clamp, and wide Gaussians outside the 1.3x
    field of view whose footprint still reaches the image (J at the clamped x/z): forward and
    gradients equal the reference's, and both paths are really taken."""
    from render_reference import ALPHA_MAX, FOV_CLAMP, reference_project

    cam = Camera.look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], width=32, height=32, fov_y_deg=40)
    tan = 0.5 * cam.width / cam.fx
    lim = (cam.width - cam.cx) / cam.fx + FOV_CLAMP * tan
    means = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.05, 0.1],        # opaque, on axis
                          [1.4 * lim * 2.0, 0.1, 0.0],               # right of the clamp limit
                          [-0.1, -1.35 * lim * 2.0, 0.2]],           # below it
                         dtype=torch.float64)
    covs = torch.stack([torch.eye(3) * 0.6 ** 2, torch.eye(3) * 0.05 ** 2,
                        torch.diag(torch.tensor([0.3, 0.2, 0.25])) ** 2,
                        torch.diag(torch.tensor([0.25, 0.3, 0.2])) ** 2]).double()
    cols = torch.tensor([[1.0, 0.2, 0.1], [0.1, 1.0, 0.3], [0.2, 0.3, 1.0], [0.9, 0.9, 0.1]], dtype=torch.float64)
    op = torch.tensor([1.0, 0.995, 0.9, 0.9], dtype=torch.float64)
    u, v, conic, z, _, _ = reference_project(means, covs, cam.w2c_cv(), cam.fx, cam.fy, cam.cx, cam.cy,
                                             cam.width, cam.height)
    w2c = torch.as_tensor(cam.w2c_cv())
    pc = means @ w2c[:3, :3].T + w2c[:3, 3]
    assert abs(float(pc[2, 0] / pc[2, 2])) > lim and abs(float(pc[3, 1] / pc[3, 2])) > lim  # outside the clamp
    H, W = cam.height, cam.width
    wr, wa, wd = _weights([(H, W, 3), (H, W), (H, W)], 9)
    ours = [t.clone().requires_grad_(True) for t in (means, covs, cols, op)]
    out = render(*ours, cam)
    refs = [t.clone().requires_grad_(True) for t in (means, covs, cols, op)]
    rr = reference_render_camera(*refs, cam)
    for name, r in zip(["rgb", "alpha", "depth_acc"], rr):
        assert float((out[name].detach() - r.detach()).abs().max()) < 1e-10, name
    # the off-frustum Gaussians draw something, the opaque one saturates the clamp
    only_side = reference_render_camera(means[2:], covs[2:], cols[2:], op[2:], cam)[1]
    assert float(only_side.max()) > 0.05
    solo = reference_render_camera(means[:1], covs[:1], cols[:1], op[:1], cam)[1]
    assert abs(float(solo.max()) - ALPHA_MAX) < 1e-12 and int((solo == ALPHA_MAX).sum()) >= 4
    ((out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + (out["depth_acc"] * wd).sum()).backward()
    ((rr[0] * wr).sum() + (rr[1] * wa).sum() + (rr[2] * wd).sum()).backward()
    for name, a, b in zip(["means", "covs", "colors", "opacities"], ours, refs):
        ok, rel = _grad_close(a.grad, b.grad)
        assert ok, (name, rel)
