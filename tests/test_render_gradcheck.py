"""Renderer gradients against central finite differences in float64 (small scenes)."""

import pytest
import torch

from physinteract_usd.camera import Camera
from physinteract_usd.render import RasterizeGaussians, RasterSettings, render
from physinteract_usd.render.function import cov6_from_matrix
from render_helpers import DEVICES
from render_reference import make_scene


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _camera():
    cam = Camera.look_at([0.5, 0.3, 1.8], [0.0, 0.0, 0.0], width=32, height=24, fov_y_deg=45)
    cam.cy -= 0.7
    return cam


def _loss_fn(cam, device, seed):
    g = torch.Generator().manual_seed(seed)
    H, W = cam.height, cam.width
    wr = torch.randn(H, W, 3, generator=g, dtype=torch.float64).to(device)
    wa = torch.randn(H, W, generator=g, dtype=torch.float64).to(device)
    wd = torch.randn(H, W, generator=g, dtype=torch.float64).to(device)
    bg = torch.tensor([0.4, 0.2, 0.9], dtype=torch.float64, device=device)

    def loss(means, cov6, colors, opacities):
        out = render(means, cov6, colors, opacities, cam, background=bg)
        return (out["rgb"] * wr).sum() + (out["alpha"] * wa).sum() + (out["depth"] * wd).sum()

    return loss


def _central_fd(f, params, rel_eps=1e-5):
    """Central differences, step rel_eps * max|p| per tensor. Also returns, per entry, whether
    the estimate is trustworthy: the steps h and h/4 agree (a step that moves a pixel across a
    cut-off boundary, where the image is discontinuous, gives two different answers)."""
    grads, trust = [], []
    with torch.no_grad():
        for p in params:
            h0 = rel_eps * float(p.abs().max())
            g = torch.zeros_like(p)
            ok = torch.ones_like(p, dtype=torch.bool)
            flat, gf, okf = p.view(-1), g.view(-1), ok.view(-1)
            for i in range(flat.numel()):
                old = flat[i].item()
                est = []
                for h in (h0, h0 / 4):
                    flat[i] = old + h
                    lp = f(*params).item()
                    flat[i] = old - h
                    lm = f(*params).item()
                    flat[i] = old
                    est.append((lp - lm) / (2 * h))
                gf[i] = est[1]
                okf[i] = abs(est[0] - est[1]) <= 1e-4 * abs(est[1]) + 1e-7 * (1 + abs(est[1]))
            grads.append(g)
            trust.append(ok)
    return grads, trust


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed,thin", [(10, 0.0), (11, 1.0)])
def test_central_differences_float64(device, seed, thin):
    cam = _camera()
    means, covs, cols, op = make_scene(seed, 10, torch.float64, radius=0.3, thin=thin, opacity=(0.2, 0.95))
    params = [t.to(device) for t in (means, cov6_from_matrix(covs), cols, op)]
    f = _loss_fn(cam, device, seed)
    ad = [p.clone().requires_grad_(True) for p in params]
    f(*ad).backward()
    fd, trust = _central_fd(f, [p.clone() for p in params])
    n_trusted = sum(int(t.sum()) for t in trust)
    n_all = sum(t.numel() for t in trust)
    assert n_trusted >= 0.97 * n_all, (n_trusted, n_all)
    for name, a, b, ok in zip(["means", "cov6", "colors", "opacities"], ad, fd, trust):
        a, b, ok = a.grad.cpu(), b.cpu(), ok.cpu()
        assert float(b.abs().max()) > 0, name
        tol = 1e-3 * b.abs() + 1e-6 * b.abs().max()
        bad = ((a - b).abs() > tol) & ok
        assert not bool(bad.any()), (name, float(((a - b).abs() / b.abs().clamp_min(1e-30))[ok].max()))


def test_torch_gradcheck_fast_mode():
    cam = _camera()
    means, covs, cols, op = make_scene(12, 8, torch.float64, radius=0.3, opacity=(0.2, 0.95))
    ins = [t.clone().requires_grad_(True) for t in (means, cov6_from_matrix(covs), cols, op)]

    def fn(m, c, col, o):
        return RasterizeGaussians.apply(m, c, col, o, cam, RasterSettings())

    assert torch.autograd.gradcheck(fn, ins, eps=1e-6, atol=1e-6, rtol=1e-3, fast_mode=True)
