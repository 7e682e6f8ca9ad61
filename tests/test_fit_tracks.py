"""The point-track term of the fit (physinteract_usd/fit/tracks_loss.py): the video's 2D tracks
against the model's projected Gaussians.

- the torch projection is the camera's (cv2 convention);
- the term is 0 when the model's Gaussians follow the tracks, grows with a wrong track, drops a
  track where it is invalid (occluded / lost);
- its gradient with respect to the Gaussians' positions and, through a tiny simulation, to log E
  matches float64 finite differences;
- known answer: tracks measured by the package's tracker (OpenCV DIS flow) on a capture rendered at
  a known uniform E: the term is smaller at the true E than at 0.5x and 2x, and its minimum over a
  sweep lies within 20% of the truth;
- wiring: `fit --track-weight` (settings, the app's measured tracks, refusals).

Tiny scenes (tests/fit_scene.py's bar: ~200 particles, a 10-cell grid, 5 frames)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd.fit import FitProblem, FitSettings, Observations
from physinteract_usd.fit import fit as run_fit
from physinteract_usd.fit.tracks_loss import (TrackLoss, charbonnier, outline_length, project_points,
                                              tracker_noise_px)
from physinteract_usd.render import render
from physinteract_usd.usd.stage import read_stage

QUIET = dict(progress=False, log=lambda *a: None)


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    return fs.build(tmp_path_factory.mktemp("tracks") / "base")


def _textured(sd, scale=2.0, seed=1):
    """The stage's scene with a camera `scale` times finer and a random colour per Gaussian (texture
    the flow can follow in every direction; the bar's stripes run one way only)."""
    sd.camera = sd.camera.scaled(scale)
    g = sd.gaussians
    col = np.random.default_rng(seed).uniform(0.1, 0.9, (len(g), 3))
    sh = np.zeros_like(g.sh)
    sh[:, 0] = (col - 0.5) / 0.28209479
    sd.gaussians = dataclasses.replace(g, sh=sh)
    return sd


def _render_truth(sd, specs, E, dtype="float32"):
    """Frames, silhouettes and the Gaussians' means (T, N, 3) at uniform E, through sd's camera."""
    T, H, W = sd.n_frames, sd.camera.height, sd.camera.width
    prob = FitProblem(sd, Observations(frames=np.zeros((T, H, W, 3), np.float32)), specs, dtype=dtype)
    P = len(sd.particles_positions)
    bg = torch.as_tensor(fs.BACKGROUND, dtype=prob.tdtype)
    frames, masks, means = [], [], []
    with torch.no_grad():
        x, F = prob.simulate(torch.full((P,), float(E), dtype=prob.tdtype),
                             torch.full((P,), fs.NU_TRUE, dtype=prob.tdtype))
        for k in range(T):
            m, c = prob.gaussians_at(x[k], F[k])
            out = render(m, c, prob.colors, prob.opacities, prob.cameras[k], background=bg)
            frames.append(out["rgb"].numpy())
            masks.append(out["alpha"].numpy() > 0.5)
            means.append(m.numpy())
    return np.stack(frames).astype(np.float32), np.stack(masks), np.stack(means)


@dataclasses.dataclass
class _Tracks:
    ids: np.ndarray
    uv: np.ndarray
    valid: np.ndarray
    fb_error: np.ndarray | None = None


def _exact_tracks(sd, means, n=40, seed=0):
    """Tracks that follow n front Gaussians exactly (their projections frame by frame)."""
    cam = sd.camera
    uv0, z0 = cam.project(means[0])
    front = np.argsort(z0)[: max(4 * n, n)]
    ids = np.sort(np.random.default_rng(seed).choice(front, n, replace=False))
    uv = np.stack([cam.at(k).project(means[k][ids])[0] for k in range(len(means))])
    return _Tracks(ids, uv, np.ones(uv.shape[:2], bool))


# ---------------------------------------------------------------------------------- the pieces
def test_projection_is_the_cameras():
    from physinteract_usd.camera import Camera

    cam = Camera.look_at([0.3, 0.2, 0.5], [0.0, 0.1, 0.0], width=40, height=30, fov_y_deg=50)
    pts = np.random.default_rng(0).normal(0, 0.05, (20, 3)) + [0.0, 0.1, 0.0]
    uv, z = project_points(torch.as_tensor(pts), cam)
    uv_np, z_np = cam.project(pts)
    assert np.allclose(uv.numpy(), uv_np, atol=1e-9) and np.allclose(z.numpy(), z_np, atol=1e-12)


def test_noise_scale_outline_and_penalty():
    # the tracker's noise: the fb disagreement's median / 2, the background drift, at least 0.25 px
    fb = np.full((3, 10), 1.2)
    assert tracker_noise_px(fb, np.ones((3, 10), bool)) == pytest.approx(0.6)
    assert tracker_noise_px(fb * 0.1, np.ones((3, 10), bool)) == pytest.approx(0.25)
    buv = np.zeros((3, 5, 2))
    buv[1:, :, 0] = 0.9
    assert tracker_noise_px(None, None, buv, np.ones((3, 5), bool)) == pytest.approx(0.9)
    m = np.zeros((10, 10), bool)
    m[2:6, 3:8] = True                      # 4 x 5: 14 boundary pixels
    assert outline_length(m) == 14
    r = torch.tensor([0.0, 0.01, 100.0], dtype=torch.float64)
    c = charbonnier(r, 0.5)
    assert float(c[0]) == 0.0
    assert float(c[1]) == pytest.approx(0.01 ** 2 / (2 * 0.5), rel=1e-3)   # quadratic within the noise
    assert float(c[2]) == pytest.approx(100.0 - 0.5, rel=1e-3)             # linear (robust) beyond


def test_term_vanishes_on_exact_tracks_grows_with_an_error_and_drops_invalid(bar):
    sd = read_stage(bar["stage"])
    specs = fs.contacts(sd)
    _, masks, means = _render_truth(sd, specs, fs.E_TRUE)
    tr = _exact_tracks(sd, means)
    cams = [sd.camera.at(k) for k in range(sd.n_frames)]
    tl = TrackLoss(tr.ids, tr.uv, tr.valid, cams, means[0], outline=masks[0], sigma_px=0.5, knn=1,
                    dtype=torch.float64)
    assert tl.n_tracks == len(tr.ids)
    m = [torch.as_tensor(means[k], dtype=torch.float64) for k in range(sd.n_frames)]
    for k in range(1, sd.n_frames):
        assert float(tl.frame_term(k, m[k])) < 1e-10
    # one track 10 px off in frame 2: the term is that track's Charbonnier share, scaled
    bad = tr.uv.copy()
    bad[2, 5] += [6.0, 8.0]
    tl2 = TrackLoss(tr.ids, bad, tr.valid, cams, means[0], outline=masks[0], sigma_px=0.5, knn=1,
                    dtype=torch.float64)
    want = tl2.scale * 0.5 * (np.sqrt(1 + (10.0 / 0.5) ** 2) - 1) / len(tr.ids)
    assert float(tl2.frame_term(2, m[2])) == pytest.approx(want, rel=1e-6)
    assert tl2.scale == pytest.approx(outline_length(masks[0]) / (sd.camera.width * sd.camera.height))
    # the same track lost (occluded) in that frame: dropped
    valid = tr.valid.copy()
    valid[2, 5] = False
    tl3 = TrackLoss(tr.ids, bad, valid, cams, means[0], outline=masks[0], sigma_px=0.5, knn=1,
                    dtype=torch.float64)
    assert float(tl3.frame_term(2, m[2])) < 1e-10
    # a frame with fewer than 3 valid tracks does not count
    valid[3, 2:] = False
    tl4 = TrackLoss(tr.ids, bad, valid, cams, means[0], outline=masks[0], sigma_px=0.5, knn=1,
                    dtype=torch.float64)
    assert 3 not in tl4.frames_used() and float(tl4.frame_term(3, m[3] + 0.01)) == 0.0


# --------------------------------------------------------------------------------- gradients
def test_gradient_wrt_positions_matches_finite_differences_float64(bar):
    sd = read_stage(bar["stage"])
    specs = fs.contacts(sd)
    _, masks, means = _render_truth(sd, specs, fs.E_TRUE)
    tr = _exact_tracks(sd, means)
    tr.uv[1:] += np.random.default_rng(2).normal(0, 0.8, tr.uv[1:].shape)   # residuals around the noise scale
    cams = [sd.camera.at(k) for k in range(sd.n_frames)]
    tl = TrackLoss(tr.ids, tr.uv, tr.valid, cams, means[0], outline=masks[0], sigma_px=0.5, knn=1,
                    dtype=torch.float64)
    k = 3
    x = torch.as_tensor(means[k], dtype=torch.float64).clone().requires_grad_(True)
    (g,) = torch.autograd.grad(tl.frame_term(k, x), [x])
    bound = np.unique(tl.gauss)
    rng = np.random.default_rng(0)
    h = 1e-6
    for i in rng.choice(bound, 6, replace=False):
        for a in range(3):
            with torch.no_grad():
                xp, xm = x.detach().clone(), x.detach().clone()
                xp[i, a] += h
                xm[i, a] -= h
                fd = (float(tl.frame_term(k, xp)) - float(tl.frame_term(k, xm))) / (2 * h)
            assert abs(float(g[i, a]) - fd) <= 1e-5 * abs(fd) + 1e-9, (i, a, float(g[i, a]), fd)
    assert float(g[bound].abs().max()) > 1e-3
    unbound = np.setdiff1d(np.arange(len(x)), bound)
    assert float(g[unbound].abs().max()) == 0.0


def test_gradient_through_the_simulation_to_log_e_matches_finite_differences_float64(bar):
    sd = read_stage(bar["stage"])
    specs = fs.contacts(sd)
    _, masks, means = _render_truth(sd, specs, fs.E_TRUE)
    tr = _exact_tracks(sd, means, n=60)
    obs = Observations(frames=bar["frames"].astype(np.float32), masks=bar["masks"], tracks=tr)
    prob = FitProblem(sd, obs, specs, dtype="float64")
    prob.weights.track = 1.0
    P = len(sd.particles_positions)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float64)
    logE = torch.tensor(np.log(2.0 * fs.E_TRUE), dtype=torch.float64, requires_grad=True)

    def loss(le):
        x, F = prob.simulate(torch.exp(le) * torch.ones(P, dtype=torch.float64), nu)
        return sum(prob.tracks.frame_term(k, prob.gaussians_at(x[k], F[k])[0]) for k in range(1, prob.T))

    (g,) = torch.autograd.grad(loss(logE), [logE])
    h = 1e-4
    with torch.no_grad():
        fd = (float(loss(logE + h)) - float(loss(logE - h))) / (2 * h)
    assert abs(fd) > 1e-6, "the track term does not depend on E"
    assert fd > 0          # too stiff: the bar sags less than its tracks
    assert abs(float(g) - fd) <= 2e-3 * abs(fd) + 1e-10, (float(g), fd)


# ------------------------------------------------------------------------------ known answer
def test_measured_tracks_pin_the_true_e(bar):
    """Tracks measured by the package's tracker on frames rendered at E_TRUE: the term is lowest near
    E_TRUE (the tracker's own bias, ~0.3 px by the last frame here, is what keeps it off exactly)."""
    from physinteract_usd.app.adapters import measured_tracks

    sd = _textured(read_stage(bar["stage"]))
    specs = fs.contacts(sd)
    frames, masks, _ = _render_truth(sd, specs, fs.E_TRUE)
    obs = Observations(frames=frames, masks=masks)
    tr = measured_tracks(sd, obs, cache=False)
    assert tr.valid[0].sum() >= 50
    obs.tracks = tr
    prob = FitProblem(sd, obs, specs)
    prob.weights.track = 1.0
    P = len(sd.particles_positions)
    nu = torch.full((P,), fs.NU_TRUE)

    def term(f):
        with torch.no_grad():
            x, F = prob.simulate(torch.full((P,), fs.E_TRUE * f), nu)
            return float(np.mean([prob.tracks.frame_term(k, prob.gaussians_at(x[k], F[k])[0])
                                  for k in range(1, prob.T)]))

    factors = 2.0 ** np.arange(-1.0, 1.01, 0.25)
    vals = np.array([term(f) for f in factors])
    i1 = int(np.argmin(np.abs(factors - 1)))
    assert vals[i1] < vals[0] and vals[i1] < vals[-1]        # the truth beats 0.5x and 2x
    j = int(np.clip(np.argmin(vals), 1, len(vals) - 2))
    # the minimum: a parabola in log E through the sweep's best point and its neighbours
    a, b, _ = np.polyfit(np.log(factors[j - 1:j + 2]), vals[j - 1:j + 2], 2)
    best = float(np.exp(-b / (2 * a))) if a > 0 else float(factors[np.argmin(vals)])
    assert abs(best - 1.0) <= 0.2, (best, dict(zip(np.round(factors, 3), vals)))


# ------------------------------------------------------------------------------------ wiring
def test_track_weight_without_tracks_is_refused(bar):
    sd = read_stage(bar["stage"])
    prob = FitProblem(sd, Observations(frames=bar["frames"], masks=bar["masks"]), fs.contacts(sd))
    with pytest.raises(ValueError, match="point tracks"):
        run_fit(prob, FitSettings(track_weight=1.0, iterations=1), **QUIET)


def test_cli_refuses_a_negative_track_weight(bar, capsys):
    from physinteract_usd.cli import main

    assert main(["fit", str(bar["stage"]), "--track-weight", "-1"]) == 2
    assert "--track-weight" in capsys.readouterr().err


def test_fit_with_tracks_measures_caches_and_counts_them(bar, tmp_path):
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.usd.layout import LayerPaths

    stage = fs.copy_scene(bar["root"], tmp_path / "s")
    logs = []
    over = dict(fs.SMOKE_SETTINGS, confidence_probes=0, track_weight=2.0)
    job = prepare_fit(stage, iterations=2, contact_from=stage.parent / "gt", settings_overrides=over,
                      log=logs.append, progress=False)
    assert job.observations.tracks is not None and any(m.startswith("tracks:") for m in logs), logs
    assert (LayerPaths.of(stage).sibling(".report") / "tracks.npz").exists()
    prob = make_problem(job)
    run_fit(prob, dataclasses.replace(job.settings, iterations=1, search_evals=1), **QUIET)
    assert prob.weights.track == 2.0
    P = len(read_stage(stage).particles_positions)
    with torch.no_grad():
        E = torch.full((P,), 2 * fs.E_TRUE)
        nu = torch.full((P,), fs.NU_TRUE)
        x, F = prob.simulate(E, nu)
        k = prob.T - 1
        parts = prob.frame_loss(k, prob.render_frame(k, x[k], F[k]))
    assert float(parts["track"]) > 0
    img = parts["l1"] + prob.weights.ssim * (1 - parts["ssim"]) + prob.weights.mask * parts["mask"]
    assert float(parts["total"]) == pytest.approx(float(img + 2.0 * parts["track"]), rel=1e-5)
