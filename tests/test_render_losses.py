"""Losses: SSIM against scikit-image, weighted losses ignore weight-0 (hand) pixels."""

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from physinteract_usd.render import l1_loss, reconstruction_loss, silhouette_loss, ssim, ssim_loss


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _sk(a, b):
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1, channel_axis=-1)


def _pairs():
    g = np.random.default_rng(0)
    a = g.random((32, 40, 3))
    yield "noise", a, np.clip(a + 0.1 * g.standard_normal(a.shape), 0, 1)
    yield "independent", g.random((24, 24, 3)), g.random((24, 24, 3))
    jj, ii = np.mgrid[0:64, 0:48] / 20.0
    smooth = np.stack([np.sin(ii), np.cos(jj), np.sin(ii + jj)], -1) * 0.5 + 0.5
    yield "smooth", smooth, np.clip(smooth * 0.8 + 0.05, 0, 1)
    yield "identical", smooth, smooth.copy()
    yield "small", g.random((12, 13, 3)), g.random((12, 13, 3))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name,a,b", list(_pairs()))
def test_ssim_matches_skimage(dtype, name, a, b):
    ours = float(ssim(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype)))
    assert abs(ours - _sk(a, b)) < 1e-4, (name, ours, _sk(a, b))


def test_ssim_grey_images_and_batches():
    g = np.random.default_rng(1)
    a, b = g.random((30, 30)), g.random((30, 30))
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)
    assert abs(float(ssim(torch.tensor(a), torch.tensor(b))) - ref) < 1e-10
    A, B = g.random((2, 20, 22, 3)), g.random((2, 20, 22, 3))
    batch = float(ssim(torch.tensor(A), torch.tensor(B)))
    assert abs(batch - 0.5 * (_sk(A[0], B[0]) + _sk(A[1], B[1]))) < 1e-10


def test_ssim_gradient_finite_differences():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(14, 15, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(14, 15, 3, generator=g, dtype=torch.float64)
    w = torch.rand(14, 15, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: ssim(x, b, w), (a,), eps=1e-6, atol=1e-7, rtol=1e-4)
    assert torch.autograd.gradcheck(lambda x: l1_loss(x, b, w), (a,), eps=1e-6, atol=1e-7, rtol=1e-4)


def _hand_weight(h, w):
    wt = torch.ones(h, w, dtype=torch.float64)
    wt[5:15, 8:20] = 0.0  # the hand
    wt[20:, :6] = 0.5
    return wt


@pytest.mark.parametrize("loss", ["l1", "ssim", "silhouette", "total"])
def test_weight_zero_pixels_are_left_out(loss):
    g = torch.Generator().manual_seed(3)
    H, W = 28, 30
    wt = _hand_weight(H, W)
    pred = torch.rand(H, W, 3, generator=g, dtype=torch.float64)
    target = torch.rand(H, W, 3, generator=g, dtype=torch.float64)
    pa = torch.rand(H, W, generator=g, dtype=torch.float64)
    ma = (torch.rand(H, W, generator=g, dtype=torch.float64) > 0.5).double()

    def f(p, t, a, m):
        if loss == "l1":
            return l1_loss(p, t, wt)
        if loss == "ssim":
            return ssim_loss(p, t, wt)
        if loss == "silhouette":
            return silhouette_loss(a, m, wt)
        return reconstruction_loss(p, t, wt, a, m)["total"]

    base = float(f(pred, target, pa, ma))
    hand = wt == 0
    p2, t2, a2, m2 = pred.clone(), target.clone(), pa.clone(), ma.clone()
    p2[hand] = torch.rand(int(hand.sum()), 3, generator=g, dtype=torch.float64)
    t2[hand] = 1.0 - t2[hand]
    a2[hand] = 1.0 - a2[hand]
    m2[hand] = 1.0 - m2[hand]
    assert abs(float(f(p2, t2, a2, m2)) - base) < 1e-12
    # and the weight-1 pixels do matter
    p3 = pred.clone()
    p3[0:3, 25:] = 1.0 - p3[0:3, 25:]
    a3 = pa.clone()
    a3[0:3, 25:] = 1.0 - a3[0:3, 25:]
    assert abs(float(f(p3, target, a3, ma)) - base) > 1e-6
    # gradient is zero on hand pixels
    p4 = pred.clone().requires_grad_(True)
    a4 = pa.clone().requires_grad_(True)
    f(p4, target, a4, ma).backward()
    grads = [t.grad for t in (p4, a4) if t.grad is not None]
    assert grads and all(float(gr[hand].abs().max()) == 0.0 for gr in grads)


def test_unit_weights_equal_unweighted_and_values():
    g = torch.Generator().manual_seed(4)
    a = torch.rand(20, 21, 3, generator=g, dtype=torch.float64)
    b = torch.rand(20, 21, 3, generator=g, dtype=torch.float64)
    ones = torch.ones(20, 21, dtype=torch.float64)
    assert abs(float(ssim(a, b, ones)) - float(ssim(a, b))) < 1e-12
    assert abs(float(l1_loss(a, b)) - float((a - b).abs().mean())) < 1e-12
    half = torch.zeros(20, 21, dtype=torch.float64)
    half[:, :10] = 1.0
    assert abs(float(l1_loss(a, b, half)) - float((a - b)[:, :10].abs().mean())) < 1e-12
    m = (b[..., 0] > 0.5).double()
    assert abs(float(silhouette_loss(a[..., 0], m)) - float(((a[..., 0] - m) ** 2).mean())) < 1e-12
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
