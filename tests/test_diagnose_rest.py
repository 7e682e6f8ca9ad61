"""The camera causes judged on the frames before contact (`DiagnoseSettings.camera_rest`, `--floor-rule rest`)
and `heterogeneity` priced as the fit's own model selection (issue #22, docs/diagnose.md).

Numpy only, fast. A toy 1-D scene seen as a (T, H, W, 4) residual: a bar that settles under gravity from
frame 0 (the rest frames 1..G-1: no hand), then is pulled from frame G on. The depth-scale probe is the
gravity's column (the settling x (1 + eps)); the base can re-adjust the pull's amplitude (an E-like column).
Known answers:

- a rendering floor only (soft alpha against a binary silhouette in every frame, and a finer truth that
  trails the model once the hand moves it): on the rest frames the gravity probe is not significant;
- the same floor plus a real depth-scale error (the truth's gravity x 2): on the rest frames it is
  significant and taken by forward selection.
(The false alarm itself, the floor leaning along the probe on the moving frames, is shown on a simulated
scene, tests/diagnose_rest_scene.py, in docs/benchmarks/diagnose_named.md; this toy does not reproduce it.)
"""

import types

import numpy as np

from physinteract_usd.diagnose.core import DiagnoseSettings, Probe, _forward_select
from physinteract_usd.diagnose.core import test_on_rows as score_on_rows
from physinteract_usd.diagnose.core import test_candidate as score_candidate
from physinteract_usd.diagnose.refit import price_heterogeneity

T, H, W = 16, 12, 40
G = 4                                   # the hand grasps at frame G: frames 1..G-1 are the rest frames
U = np.arange(W) + 0.5


def _path(g=1.0, pull=4.0, lag=0.0):
    """The bar's centre per frame: settling under gravity g from frame 0 (a free fall that stops at 3 px),
    pulled from frame G by `pull` px; `lag`: a finer truth trails the model by this much once pulled."""
    k = np.arange(T, dtype=np.float64)
    settle = g * 3.0 * (1.0 - np.exp(-(k / 2.0) ** 2))
    p = np.clip((k - G) / 5.0, 0, 1) * pull
    trail = lag * np.clip((k - G) / 2.0, 0, 1)
    return 14.0 + settle + p - trail


def _render(path):
    d = U[None, :] - path[:, None]
    dens = 2.5 / (1.0 + np.exp(-(d + 6.0) / 2.0)) / (1.0 + np.exp((d - 6.0) / 0.5))
    a = 1.0 - np.exp(-dens)
    alpha = np.zeros((T, H, W))
    alpha[:, 3:9, :] = a[:, None, :]
    rgb = alpha[..., None] * np.array([0.8, 0.2, 0.2]) + (1 - alpha[..., None]) * 0.5
    return alpha, rgb


def _r(model, truth_alpha, truth_rgb, noise):
    a, rgb = _render(model)
    return np.concatenate([rgb - truth_rgb - noise, (a - (truth_alpha > 0.5))[..., None]], -1)[1:].ravel()


def _case(seed, g_true=1.0):
    """(r0, J, depth-scale probe column, blocks, n_blocks, rest rows)."""
    rng = np.random.default_rng(seed)
    ta, trgb = _render(_path(g=g_true, lag=0.6))
    noise = rng.normal(scale=0.01, size=trgb.shape)
    base = _path()
    r0 = _r(base, ta, trgb, noise)
    col = lambda p, h: (_r(p, ta, trgb, noise) - r0) / h                      # noqa: E731
    J = np.column_stack([col(_path(pull=4.2), 0.05)])                           # the E-like column
    probe = col(_path(g=1.05), 0.05)
    frames = np.broadcast_to(np.arange(1, T)[:, None, None, None], (T - 1, H, W, 4)).ravel()
    tiles = np.broadcast_to((np.arange(W) // 4)[None, None, :, None], (T - 1, H, W, 4)).ravel()
    blocks = ((frames - 1) // 2) * (W // 4) + tiles
    rows = frames < G
    return r0, J, probe, blocks.astype(np.int64), int(blocks.max()) + 1, rows


def _depth(seed, g_true, rest: bool):
    r0, J, probe, blocks, nb, rows = _case(seed, g_true)
    s = DiagnoseSettings(min_relative_drop=0.0)
    p = [Probe("g", probe, 0, {})]
    if rest:
        return score_on_rows("camera:depth_scale", p, r0, J, blocks, s, rows, len(r0))
    return score_candidate("camera:depth_scale", p, r0, J, blocks, nb, s, len(r0))


def test_rendering_floor_only_is_no_depth_scale_on_the_rest_frames():
    thr = 0.05 / 3
    rest = [_depth(seed, 1.0, rest=True) for seed in range(4)]
    assert all(c.p_value > 0.1 for c in rest)                             # on the rest frames: quiet
    assert all(c.rest_only for c in rest)
    assert not any(c.rest_only for c in [_depth(0, 1.0, rest=False)])
    # the same floor with a real depth-scale error (gravity x 2 in the video) is seen there
    assert all(_depth(seed, 2.0, rest=True).p_value < thr for seed in range(4))


def test_real_depth_scale_error_shows_on_the_rest_frames_and_is_selected():
    for seed in range(3):
        c = _depth(seed, 2.0, rest=True)
        assert c.p_value < 0.05 / 3 and c.drop > 0 and c.step > 0
        # its drop is per element of the whole residual: at most the rest rows' share of the loss
        r0, J, probe, blocks, nb, rows = _case(seed, 2.0)
        assert c.drop <= np.sum(r0[rows] ** 2) / len(r0)
        res = [c]
        _forward_select(res, r0, J, blocks, nb, DiagnoseSettings(min_relative_drop=0.0, camera_rest=True),
                        float(np.mean(r0 ** 2)), len(r0), rows)
        assert res[0].significant and res[0].effect == "camera:depth_scale"


def test_no_rest_frame_means_not_testable():
    r0, J, probe, blocks, nb, rows = _case(0, 1.5)
    c = score_on_rows("camera:depth_scale", [Probe("g", probe, 0, {})], r0, J, blocks, DiagnoseSettings(),
                     np.zeros_like(rows), len(r0))
    assert c.p_value == 1.0 and c.drop == 0.0 and "not testable" in c.note and c.rest_only


def _diag(frames_per_elem):
    res = types.SimpleNamespace(frame_of=lambda: frames_per_elem)
    return types.SimpleNamespace(_ctx={"res": res, "settings": DiagnoseSettings()})


def test_heterogeneity_priced_needs_most_frames_and_the_time_blocks():
    """A drop carried by one held-back frame is not kept (the select rule's sign test), however large;
    one spread over every held-back frame is."""
    rng = np.random.default_rng(0)
    nf, per = 8, 400
    fr = np.repeat(np.arange(nf), per)
    d = _diag(fr)
    ref = rng.normal(scale=0.05, size=nf * per)
    m = np.ones(nf * per, bool)
    one = ref.copy()
    one[fr == 3] *= 0.2                    # much better on one frame, the same elsewhere
    out = price_heterogeneity(d, [(m, one)], [ref])
    assert not out["keep"] and out["select"]["better_frames"] == 1
    every = ref * 0.9                      # 10% better everywhere
    out = price_heterogeneity(d, [(m, every)], [ref])
    assert out["keep"] and out["p_time"] < 0.05 and out["select"]["better_frames"] == nf
    worse = ref * 1.1
    assert not price_heterogeneity(d, [(m, worse)], [ref])["keep"]
