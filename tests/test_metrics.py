"""Metrics against hand-computed values and skimage."""

import numpy as np
import pytest

from physinteract_usd import metrics as M


def test_psnr_hand_computed():
    a = np.zeros((4, 4, 3))
    b = np.zeros((4, 4, 3))
    b[0, 0, 0] = 0.5  # MSE = 0.25 / 48
    assert M.psnr(b, a) == pytest.approx(10 * np.log10(48 / 0.25))
    assert M.psnr(a, a) == float("inf")


def test_psnr_masked_uses_the_union_of_silhouettes():
    a = np.zeros((4, 4, 3))
    b = a.copy()
    b[0, 0] = 0.1  # error inside the true silhouette only
    sil_true = np.zeros((4, 4), bool)
    sil_true[0, :2] = True
    sil_pred = np.zeros((4, 4), bool)
    sil_pred[1, 0] = True
    # union has 3 pixels (9 values); squared error 3 * 0.01
    assert M.psnr_masked(b, a, sil_pred, sil_true) == pytest.approx(10 * np.log10(9 / 0.03))
    assert M.psnr_masked(b, a, sil_pred, sil_true) < M.psnr(b, a)


@pytest.mark.parametrize("shape", [(40, 48), (37, 52, 3)])
def test_reported_ssim_is_the_fits_ssim(shape):
    """The SSIM reports show (scikit-image's, the design's settings) is the one the fit minimises
    (render.losses.ssim, torch), and it falls as noise grows."""
    import torch

    from physinteract_usd.render.losses import ssim as fit_ssim

    rng = np.random.default_rng(0)
    a = rng.random(shape)
    b = np.clip(a + rng.normal(scale=0.1, size=shape), 0, 1)
    c = np.clip(a + rng.normal(scale=0.3, size=shape), 0, 1)
    assert M.ssim(a, b) == pytest.approx(float(fit_ssim(torch.tensor(b), torch.tensor(a))), abs=1e-6)
    assert M.ssim(a, a) == pytest.approx(1.0)
    assert 0 < M.ssim(a, c) < M.ssim(a, b) < 1


def test_iou():
    a = np.zeros((3, 3), bool)
    b = np.zeros((3, 3), bool)
    a[0, :2] = True
    b[0, 1:] = True
    assert M.iou(a, b) == pytest.approx(1 / 3)


def test_material_accuracy_and_best_uniform():
    e_true = np.array([1.0, 1.0, 1.0, 10.0])
    assert M.material_accuracy([1.1, 0.85, 1.3, 10.0], e_true) == pytest.approx(0.75)
    ma, e_best = M.best_uniform_ma(e_true)
    assert ma == pytest.approx(0.75)
    assert 0.8 <= e_best <= 1.2
    # a 5x-varying field: no single E can reach 0.9
    e_true = np.concatenate([np.full(50, 1e4), np.full(50, 5e4)])
    assert M.best_uniform_ma(e_true)[0] == pytest.approx(0.5)


def test_track_and_position_errors():
    assert M.track_error_px([[0, 0], [3, 4]], [[0, 0], [0, 0]]) == pytest.approx(2.5)
    assert M.position_error_m(np.ones((2, 3)), np.zeros((2, 3))) == pytest.approx(np.sqrt(3))


def test_excluded_hand_pixels_do_not_count():
    rng = np.random.default_rng(0)
    true = rng.random((20, 24, 3))
    pred = true.copy()
    hand = np.zeros((20, 24), bool)
    hand[5:10, 5:12] = True
    pred[hand] = 0.0  # the model cannot render the hand
    sil = np.zeros((20, 24), bool)
    sil[3:15, 3:15] = True
    d = M.frame_metrics(pred, true, sil, sil, exclude=hand)
    assert d["psnr"] == float("inf") and d["psnr_masked"] == float("inf")
    assert d["ssim"] == pytest.approx(1.0) and d["iou"] == 1.0
    assert M.frame_metrics(pred, true, sil, sil)["psnr"] < 30
