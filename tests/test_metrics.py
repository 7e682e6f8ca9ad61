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


# ------------------------------------------------------------------ where MA is lost (#24)
def test_peak_green_strain_reads_a_known_stretch_and_nothing_for_a_rigid_motion():
    rng = np.random.default_rng(0)
    x0 = rng.uniform(-1, 1, (300, 3))
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    rigid = x0 @ R.T + np.array([0.3, -2.0, 1.0])
    s = 1.1                                              # 10% stretch along x: Green strain 0.5 (s^2 - 1)
    stretched = x0 * np.array([s, 1.0, 1.0])
    e = M.peak_green_strain(x0, np.stack([x0, rigid]))
    assert np.max(e) < 1e-9
    e = M.peak_green_strain(x0, np.stack([x0, rigid, stretched]))
    assert np.allclose(e, 0.5 * (s * s - 1), rtol=1e-9)


def test_ma_by_truth_level_splits_the_ma_by_the_truths_materials():
    e_true = np.array([1e4] * 6 + [1e5] * 4)
    e_pred = np.array([1.1e4] * 6 + [0.5e5, 0.5e5, 1e5, 1.1e5])
    conf = np.array([0.9] * 6 + [0.1] * 4)
    rows = M.ma_by_truth_level(e_pred, e_true, conf, exposure=np.arange(10.0))
    assert [r["e_truth"] for r in rows] == [1e4, 1e5]
    assert [r["share"] for r in rows] == [0.6, 0.4]
    assert [r["ma"] for r in rows] == [1.0, 0.5]
    assert rows[1]["ratio_median"] == pytest.approx(0.75)
    assert rows[0]["confidence"] == pytest.approx(0.9) and rows[1]["exposure"] == pytest.approx(7.5)
    assert sum(r["share"] * r["ma"] for r in rows) == pytest.approx(M.material_accuracy(e_pred, e_true))
    # a graded truth (more distinct values than levels) is cut into quantile bins of log E
    graded = np.exp(np.linspace(np.log(1e4), np.log(5e4), 90))
    assert len(M.ma_by_truth_level(graded, graded)) == 3


def test_confidence_calibration_counts_confident_misses():
    e_true = np.full(10, 1e5)
    e_pred = np.array([1e5] * 5 + [2e5] * 5)
    conf = np.array([0.95] * 8 + [0.1] * 2)               # three of the confident ones are wrong
    c = M.confidence_calibration(e_pred, e_true, conf)
    assert c["ma"] == 0.5 and c["confident_wrong"] == pytest.approx(0.3)
    assert c["claimed"] == pytest.approx(0.78)
    top = [b for b in c["bins"] if b["lo"] == 0.8][0]
    assert top["share"] == pytest.approx(0.8) and top["ma"] == pytest.approx(5 / 8)
