"""The floor rule's statistics on synthetic residuals (numpy only, fast; issue #22, docs/diagnose.md
"The rendering's own error"): a toy renderer (a bar with one soft and one sharp edge, sliding across a
small image, seen as soft alpha and colour against a *binary* video silhouette with pixel noise) and a
toy simulator (the bar's path) whose model is coarser than the truth (the truth's swing 3% larger: what
a finer grid or substep gives). The residual's floor is then the rendering's own error (soft alpha
against the binary mask, in every frame) plus the model's discretisation error (growing with the
motion): no physics is missing. Known answers:

- floor only: without the floor rule a gravity-like probe (`camera:depth_scale`: a drift growing with
  time) is significant (the H200's controls' false alarm, reproduced), with it nothing is;
- floor + a damping-like truth (the swing decays after release): the floor rule names damping.
"""

import numpy as np

from physinteract_usd.diagnose import score as S
from physinteract_usd.diagnose.core import DiagnoseSettings, Probe, _forward_select
from physinteract_usd.diagnose.core import test_candidate as score_candidate
from physinteract_usd.diagnose.residual import floor_columns, project_floor

T, H, W = 20, 12, 40
RELEASE = 7
U = np.arange(W) + 0.5


def _path(c=0.0, drift=0.0, omega=0.9, sag=0.0):
    """The bar's centre per frame: pulled over the first frames, released at RELEASE, swinging (decaying
    at rate c after the release); `drift` a gravity-like offset growing as t^2 (the depth-scale probe);
    `sag` the settling a finer model adds (a coarse grid or substep is stiffer: it sags less); frame 0 at
    rest."""
    k = np.arange(T, dtype=np.float64)
    pull = np.clip(k / RELEASE, 0, 1) * 4.0
    swing = np.where(k >= RELEASE, 4.0 * np.cos(omega * (k - RELEASE)) * np.exp(-c * np.clip(k - RELEASE, 0, None)), pull)
    return 16.0 + swing + drift * (k / T) ** 2 + sag * (1.0 - np.exp(-k / 3.0))


def _render(path):
    """(T, H, W) alpha and (T, H, W, 3) colour: a bar of half-width 6 px, its left edge soft (2 px), its
    right edge sharp (0.3 px), rows 3..8, red on a grey background."""
    d = U[None, :] - path[:, None]
    dens = 2.5 / (1.0 + np.exp(-(d + 6.0) / 2.0)) / (1.0 + np.exp((d - 6.0) / 0.5))
    a = 1.0 - np.exp(-dens)                    # splats' alpha: saturating, never 1 (an asymmetric edge profile)
    alpha = np.zeros((T, H, W))
    alpha[:, 3:9, :] = a[:, None, :]
    col = np.array([0.8, 0.2, 0.2])
    rgb = alpha[..., None] * col + (1 - alpha[..., None]) * 0.5
    return alpha, rgb


def _residual(model_path, alpha_true, rgb_true, noise):
    a, rgb = _render(model_path)
    R = np.concatenate([rgb - rgb_true - noise, (a - (alpha_true > 0.5))[..., None]], -1)   # (T, H, W, 4)
    return a, R


def _case(seed, c_true=0.0, noise_sigma=0.01):
    """(model alpha (T, H, W), residual (T, H, W, 4), {name: column (T, H, W, 4)}) for a truth 3% finer
    (larger swing) than the model, optionally damped."""
    rng = np.random.default_rng(seed)
    truth = _path(c=c_true, sag=0.3)
    alpha_t, rgb_t = _render(truth)
    noise = rng.normal(scale=noise_sigma, size=rgb_t.shape)
    model = _path()
    a, R = _residual(model, alpha_t, rgb_t, noise)

    def col(p, h):
        return (_residual(p, alpha_t, rgb_t, noise)[1] - R) / h

    cols = {"omega": col(_path(omega=0.9 + 1e-3), 1e-3),              # the base: the material's frequency
            "discretisation": col(_path(sag=0.1), 1.0),               # the model at a finer discretisation
            "damping": col(_path(c=1e-3), 1e-3),
            "camera:depth_scale": col(_path(drift=1e-2), 1e-2)}
    return a, R, cols


def _diagnose(a, R, cols, rule: bool, min_relative_drop: float):
    """The projected score test and forward selection over frames 1.. (frame 0 the rest pose), blocks of
    2 frames x 4 tiles; with the rule: the floor's columns (fitted on frame 0) projected out of the
    residual and every column, the discretisation column in the base, and the given size gate."""
    ks = list(range(1, T))
    if rule:
        Q, info = floor_columns(a, R[[0]], [0])
        assert info["rest_share"] > 0.5                       # the rest frame's residual is mostly the floor
        proj = lambda X: project_floor(X[ks], Q, ks).ravel()  # noqa: E731
    else:
        proj = lambda X: X[ks].ravel()                        # noqa: E731
    r = proj(R)
    base = ["omega"] + (["discretisation"] if rule else [])
    J = np.column_stack([proj(cols[b]) for b in base])
    n = r.size
    fr = np.repeat(np.arange(len(ks)), n // len(ks))
    tile = (np.arange(n) // 4 % W // (W // 4)).astype(np.int64)          # 4 tiles across
    blocks = (fr // 2) * 4 + tile
    nb = int(blocks.max()) + 1
    s = DiagnoseSettings(n_flips=2000, min_relative_drop=min_relative_drop, floor_model=rule,
                         floor_min_relative_drop=min_relative_drop)
    res = [score_candidate(e, [Probe(e, proj(cols[e]), sign)], r, J, blocks, nb, s)
           for e, sign in (("damping", +1), ("camera:depth_scale", 0))]
    _forward_select(res, r, J, blocks, nb, s, float(np.mean(r ** 2)))
    return {x.effect: x for x in res}


def test_floor_only_residual_names_nothing_with_the_floor_rule_and_depth_scale_without_it():
    """Floor only (the rendering's soft alpha against the binary mask, the model's coarser swing, pixel
    noise): without the rule and without a size gate the gravity-like probe is significant on every seed
    (the false alarm); with the floor rule (the floor's model from the rest frame projected out, the
    model's discretisation column in the base, no size gate) nothing is significant on any seed."""
    plain_hits, rule_hits = 0, 0
    for seed in range(6):
        a, R, cols = _case(seed)
        plain = _diagnose(a, R, cols, rule=False, min_relative_drop=0.0)
        rule = _diagnose(a, R, cols, rule=True, min_relative_drop=0.0)
        plain_hits += plain["camera:depth_scale"].significant
        rule_hits += sum(x.significant for x in rule.values())
    assert plain_hits == 6
    assert rule_hits == 0


def test_floor_plus_damping_names_damping_with_the_floor_rule():
    """The same floor with a damped truth (the swing decaying at 0.08 / frame after the release): the
    floor rule names damping first on every seed, and nothing else."""
    for seed in range(4):
        a, R, cols = _case(seed, c_true=0.08)
        rule = _diagnose(a, R, cols, rule=True, min_relative_drop=0.0)
        assert rule["damping"].significant, rule["damping"].p_value
        assert not rule["camera:depth_scale"].significant


def test_the_floor_projection_removes_a_function_of_alpha_and_keeps_motion():
    """The floor's columns take the soft-alpha-against-binary residual of a frame the template never saw
    (another pose) almost whole, and leave most of a motion's column (a shift of the bar)."""
    a, _ = _render(_path())
    R0 = np.concatenate([np.zeros(a.shape + (3,)), (a - (a > 0.5))[..., None]], -1)
    Q, _ = floor_columns(a, R0[[0]], [0])
    k = RELEASE + 2
    left = project_floor(R0[[k]], Q, [k])
    assert np.sum(left ** 2) < 0.05 * np.sum(R0[k] ** 2)
    p2 = _path()
    p2[k] += 0.3
    a2, _ = _render(p2)
    shift = np.zeros_like(R0[[k]])
    shift[..., 3] = a2[k] - a[k]
    kept = project_floor(shift, Q, [k])
    assert np.sum(kept ** 2) > 0.5 * np.sum(shift ** 2)
    assert S.project_out(None, kept.ravel()).shape == kept.ravel().shape
