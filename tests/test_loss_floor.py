"""The fit's render of a synth capture at rest against its frame 0 (#24: telephone_cable's loss floor).

Known answer: frame 0 is the object file's Gaussians at rest, so the fit's rest render (the
Gaussians bound to its particles, F = I) is the synth's noise-free frame 0 exactly, up to the
background the fit estimates from the video, and a stand-in for a real capture (telephone_cable:
sensor noise sigma 0.015) scores against its video what a perfect model scores: the noise's loss.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd import api
from physinteract_usd.synth.generate import background_image, generate, noise_free_frames, sensor_noise
from physinteract_usd.synth.gt import read_ground_truth


@pytest.fixture(scope="module")
def coil(tmp_path_factory):
    root = tmp_path_factory.mktemp("floor")
    cap = root / "tc"
    info = generate("telephone_cable", cap, size="small", frames=3, log=lambda *a: None)
    sug = info["suggested_init"]
    stage = root / "tc.usda"
    api.init(stage, cap, grid=12, padding=sug["padding"], youngs_range=tuple(sug["youngs_range"]),
             max_poisson=sug["max_poisson"], density=sug["density"], log=lambda *a: None)
    from physinteract_usd.app.fit import make_problem, prepare_fit

    job = prepare_fit(stage, iterations=1, contact_from=cap / "gt", warm=False, progress=False, log=lambda m: None)
    return cap, make_problem(job)


def rest_render(prob, background):
    x0 = torch.as_tensor(np.asarray(prob.x0), dtype=prob.tdtype)
    eye = torch.eye(3, dtype=prob.tdtype).expand(len(x0), 3, 3).contiguous()
    means, covs = prob.gaussians_at(x0, eye)
    from physinteract_usd.render import render

    with torch.no_grad():
        return render(means, covs, prob.colors, prob.opacities, prob.cameras[0],
                      background=torch.as_tensor(background, dtype=prob.tdtype))


def test_sensor_noise_is_the_generators():
    a = sensor_noise(3, 0.015, (2, 4, 5, 3))
    assert a.shape == (2, 4, 5, 3) and abs(a.std() - 0.015) < 0.006
    assert np.array_equal(a, sensor_noise(3, 0.015, (2, 4, 5, 3)))
    assert not np.array_equal(a, sensor_noise(4, 0.015, (2, 4, 5, 3)))
    assert noise_free_frames({"noise": {"sigma": 0.0}, "n_frames": 2}, np.zeros((2, 4, 5, 3))) is None


def test_rest_render_is_the_noise_free_frame_0(coil):
    """The Gaussians bound to the particles at rest over the synth's own background are its
    noise-free frame 0 to the PNG's 8-bit rounding, on every pixel the hand leaves alone."""
    cap, prob = coil
    info = read_ground_truth(cap / "gt")
    assert info["noise"]["sigma"] > 0                  # a stand-in for a real capture: noisy
    clean = noise_free_frames(info, prob.obs.frames)
    H, W = clean.shape[1:3]
    out = rest_render(prob, background_image(W, H, int(info["seed"])))
    import cv2

    hand = cv2.dilate(prob.obs.hand_masks[0].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    err = np.abs(out["rgb"].numpy() - clean[0]).max(-1)[~hand]
    assert np.quantile(err, 0.99) < 1.5 / 255 and err.max() < 0.03
    # the noise is really there: the video is not its noise-free frame
    assert np.abs(prob.obs.frames[0] - clean[0]).mean() > 0.5 * 0.015


def test_rest_loss_floor_is_the_noise(coil):
    """The fit's frame-0 loss (its own background) is what the noise-free truth scores against the
    video, within 10%: the floor is the sensor noise, not the render. Against the noise-free frame
    the render over the synth's background scores only the silhouette term's soft edges (< 1/4 of
    the floor), and over the fit's background (a median of 3 noisy frames here) less than the floor."""
    cap, prob = coil
    info = read_ground_truth(cap / "gt")
    clean = noise_free_frames(info, prob.obs.frames)
    H, W = clean.shape[1:3]
    out = rest_render(prob, prob.background.numpy())
    out_true_bg = rest_render(prob, background_image(W, H, int(info["seed"])))
    fit0 = float(prob.frame_loss(0, out)["total"])
    perfect = float(prob.frame_loss(0, {"rgb": torch.as_tensor(clean[0], dtype=prob.tdtype),
                                        "alpha": out["alpha"]})["total"])
    prob.frames[0] = torch.as_tensor(clean[0], dtype=prob.tdtype)
    own = float(prob.frame_loss(0, out)["total"])
    own_true_bg = float(prob.frame_loss(0, out_true_bg)["total"])
    assert perfect > 0.02                      # sigma 0.015 on every pixel: ~0.012 L1 + ~0.02 SSIM term
    assert abs(fit0 - perfect) < 0.1 * perfect
    assert own_true_bg < 0.25 * perfect
    assert own < perfect
