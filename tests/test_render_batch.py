"""Several images in one rasterizer pass (`render_batch`) and the per-image loss of several images at
once (`reconstruction_loss_batch`) against one render / one loss per image; the batched gradients
against central finite differences in float64."""

import pytest
import torch

from physinteract_usd.camera import Camera
from physinteract_usd.render import RasterSettings, reconstruction_loss, reconstruction_loss_batch, render, render_batch
from render_reference import make_scene
from test_render_gradcheck import _central_fd

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _cameras():
    a = Camera.look_at([0.5, 0.3, 1.8], [0.0, 0.0, 0.0], width=32, height=24, fov_y_deg=45)
    a.cy -= 0.7
    b = Camera.look_at([-0.6, 0.2, 1.6], [0.05, 0.0, 0.0], width=32, height=24, fov_y_deg=50)
    return [a, b, a]


def _sets(dtype, n=24, M=3):
    """M copies of one scene, each moved and coloured a little differently."""
    means, covs, cols, op = make_scene(7, n, dtype, radius=0.3, thin=0.3, opacity=(0.2, 0.95))
    g = torch.Generator().manual_seed(3)
    d = (0.03 * torch.randn(M, n, 3, generator=g, dtype=torch.float64)).to(dtype)
    ms = means[None] + d
    ms[0] = means                      # one copy exactly the scene
    cs = covs[None].expand(M, n, 3, 3).clone()
    cs[1] = cs[1] * 1.3
    return ms, cs, cols, op


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("backward", ["pixel"])
def test_batch_equals_one_render_per_image_bitwise(dtype, backward):
    cams = _cameras()
    ms, cs, cols, op = _sets(dtype)
    bg = torch.tensor([0.4, 0.2, 0.9], dtype=dtype)
    st = RasterSettings(backward=backward)
    # forward and backward through the batch ...
    mb = ms.clone().requires_grad_(True)
    cb = cs.clone().requires_grad_(True)
    ob = op.clone().requires_grad_(True)
    out = render_batch(mb, cb, cols, ob, cams, background=bg, settings=st)
    g = torch.Generator().manual_seed(5)
    wr = torch.randn(out["rgb"].shape, generator=g, dtype=torch.float64).to(dtype)
    wa = torch.randn(out["alpha"].shape, generator=g, dtype=torch.float64).to(dtype)
    ((out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + out["depth"].sum()).backward()
    # ... against one render per image
    for m, cam in enumerate(cams):
        mm = ms[m].clone().requires_grad_(True)
        cm = cs[m].clone().requires_grad_(True)
        om = op.clone().requires_grad_(True)
        one = render(mm, cm, cols, om, cam, background=bg, settings=st)
        for key in ("rgb", "alpha", "depth", "depth_acc"):
            assert torch.equal(out[key][m], one[key]), (m, key)
        assert float(one["alpha"].detach().max()) > 0.3       # the image shows something
        ((one["rgb"] * wr[m]).sum() + (one["alpha"] * wa[m]).sum() + one["depth"].sum()).backward()
        assert torch.equal(mb.grad[m], mm.grad), m
        assert torch.equal(cb.grad[m], cm.grad), m
    # the two copies under the same camera differ: the images are not one image repeated
    assert not torch.equal(out["rgb"][0], out["rgb"][2])


def test_batch_gradients_central_differences_float64():
    cams = _cameras()[:2]
    ms, cs, cols, op = _sets(torch.float64, n=8, M=2)
    g = torch.Generator().manual_seed(9)
    wr = torch.randn(2, 24, 32, 3, generator=g, dtype=torch.float64)
    wa = torch.randn(2, 24, 32, generator=g, dtype=torch.float64)
    bg = torch.tensor([0.4, 0.2, 0.9], dtype=torch.float64)
    cols2 = torch.stack([cols, cols.flip(1)])       # per-image colours

    def f(means, covs, colors, opac):
        out = render_batch(means, covs, colors, opac, cams, background=bg)
        return (out["rgb"] * wr).sum() + (out["alpha"] * wa).sum()

    from physinteract_usd.render.function import cov6_from_matrix

    cov6 = cov6_from_matrix(cs.reshape(-1, 3, 3)).reshape(2, 8, 6)
    params = [ms.clone(), cov6.clone(), cols2.clone(), op[None].expand(2, 8).clone()]
    ad = [p.clone().requires_grad_(True) for p in params]
    f(*ad).backward()
    fd, trust = _central_fd(f, [p.clone() for p in params])
    n_trusted = sum(int(t.sum()) for t in trust)
    assert n_trusted >= 0.97 * sum(t.numel() for t in trust)
    for name, a, b, ok in zip(["means", "cov6", "colors", "opacities"], ad, fd, trust):
        assert float(b.abs().max()) > 0, name
        err = (a.grad - b)[ok].abs().max()
        assert float(err) <= 1e-5 * float(b.abs().max()) + 1e-8, (name, float(err), float(b.abs().max()))


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-6), (torch.float64, 1e-12)])
def test_loss_batch_equals_per_image(dtype, tol):
    g = torch.Generator().manual_seed(2)
    M, H, W = 3, 20, 24
    pred = torch.rand(M, H, W, 3, generator=g, dtype=torch.float64).to(dtype).requires_grad_(True)
    alpha = torch.rand(M, H, W, generator=g, dtype=torch.float64).to(dtype).requires_grad_(True)
    tgt = torch.rand(M, H, W, 3, generator=g, dtype=torch.float64).to(dtype)
    mask = (torch.rand(M, H, W, generator=g) > 0.5).to(dtype)
    w = (torch.rand(M, H, W, generator=g) > 0.2).to(dtype)
    b = reconstruction_loss_batch(pred, tgt, w, alpha, mask, lambda_ssim=0.2, lambda_mask=1.0)
    b["total"].sum().backward()
    gp, ga = pred.grad.clone(), alpha.grad.clone()
    pred.grad = alpha.grad = None
    tot = 0.0
    for m in range(M):
        one = reconstruction_loss(pred[m], tgt[m], w[m], alpha[m], mask[m], lambda_ssim=0.2, lambda_mask=1.0)
        for key in ("total", "l1", "ssim", "mask"):
            bv, ov = float(b[key][m].detach()), float(one[key].detach())
            assert abs(bv - ov) <= tol * max(1.0, abs(ov)), (m, key)
        tot = tot + one["total"]
    tot.backward()
    assert float((gp - pred.grad).abs().max()) <= tol * float(pred.grad.abs().max()) * 10
    assert float((ga - alpha.grad).abs().max()) <= tol * float(alpha.grad.abs().max()) * 10
    # weights of zero leave pixels out: changing them changes nothing
    pred2 = pred.detach().clone()
    pred2[w == 0] = 0.123
    b2 = reconstruction_loss_batch(pred2, tgt, w, alpha.detach(), mask)
    assert torch.allclose(b2["l1"], b["l1"].detach()) and torch.allclose(b2["mask"], b["mask"].detach())
