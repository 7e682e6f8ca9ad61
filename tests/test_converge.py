"""The fit's convergence stop (fit/converge.py): the plateau rule and the learning-rate schedule
with its tail, on loss sequences whose answer is known."""

from __future__ import annotations

import math

import pytest

from physinteract_usd.fit.converge import LR_FLOOR, lr_scale, plateaued


def test_a_falling_loss_has_not_plateaued():
    losses = [1.0 * 0.9 ** k for k in range(20)]
    assert not any(plateaued(losses[:n], 3, 0.005) for n in range(1, 21))


def test_a_flat_loss_plateaus_after_patience_more_losses():
    losses = [1.0, 0.999, 1.001, 0.998]          # the last 3: none 0.5% below 1.0
    assert not plateaued(losses[:3], 3, 0.005)   # not more than `patience` losses yet
    assert plateaued(losses, 3, 0.005)
    assert not plateaued(losses, 3, 0.001)       # 0.998 is 0.2% below: a new best at this tolerance
    assert not plateaued(losses, 0, 0.005)       # patience 0: the stop is off


def test_a_rise_after_the_best_is_a_plateau_and_a_late_drop_is_not():
    # the demo's bumps level: down to a best, then up (a too large step)
    losses = [0.0143, 0.0132, 0.0122, 0.0103, 0.0084, 0.0066, 0.0056, 0.00534, 0.00541, 0.00554]
    assert not plateaued(losses[:9], 3, 0.005)
    assert plateaued(losses + [0.00566], 3, 0.005)
    assert not plateaued(losses + [0.0053], 3, 0.005)   # 0.75% below the best before the last three


def test_non_finite_losses_are_never_a_new_best():
    assert plateaued([1.0, math.nan, math.inf, math.nan], 3, 0.005)
    assert not plateaued([math.nan, math.nan, 1.0, 0.9], 2, 0.005)   # nothing finite before the window


def test_lr_scale_is_the_cosine_and_the_tail_anneals_to_the_floor():
    n = 40
    assert lr_scale(0, n) == pytest.approx(1.0)
    assert lr_scale(n // 2, n) == pytest.approx(LR_FLOOR + (1 - LR_FLOOR) * 0.5)
    assert lr_scale(n, n) == pytest.approx(LR_FLOOR)
    vals = [lr_scale(j, n) for j in range(n)]
    assert all(a > b for a, b in zip(vals, vals[1:]))
    j0, s0, m = 12, lr_scale(11, n), 4
    tail = [lr_scale(j, n, (j0, s0, m)) for j in range(j0, j0 + m)]
    assert all(a > b for a, b in zip(tail, tail[1:]))
    assert tail[0] < s0 and tail[-1] == pytest.approx(LR_FLOOR)


def test_a_fit_that_converges_ends_early_with_its_best_iterate(tmp_path):
    """On the tiny bar (tests/fit_scene.py) a 40-iteration fit with the stop on runs fewer
    iterations than one with it off, says where each level plateaued, and reports its best
    iterate's loss, rendered from that iterate's own simulation."""
    import fit_scene as fs

    from physinteract_usd import api

    sc = fs.build(tmp_path / "base")
    runs = {}
    for patience in (0, 3):
        logs = []
        stage = fs.copy_scene(sc["root"], tmp_path / f"p{patience}")
        out = api.fit(stage, iterations=40, contact_from=sc["gt"], progress=False, log=logs.append,
                      checkpoint_every=0, settings_overrides=dict(fs.SMOKE_SETTINGS, confidence_probes=1,
                                                                  plateau_patience=patience))
        runs[patience] = (out.result, logs)
    off, on = runs[0][0], runs[3][0]
    assert len(off.loss_history) == 40 and len(on.loss_history) < 40
    assert any("plateaued" in m for m in runs[3][1]) and not any("plateaued" in m for m in runs[0][1])
    for r in (off, on):
        assert r.final_loss == pytest.approx(min(r.loss_history), rel=1e-6) and not r.interrupted
    assert on.final_loss < 1.25 * off.final_loss


def test_improved_says_whether_a_level_got_below_its_first_loss():
    from physinteract_usd.fit.converge import improved

    assert not improved([0.0143, 0.0148, 0.0143, 0.01429], 0.005)   # the demo's uniform level
    assert improved([0.0143, 0.0132, 0.0122], 0.005)
    assert not improved([math.nan, 0.5], 0.005) and improved([1.0, math.inf, 0.9], 0.005)


def test_a_uniform_level_at_the_searched_minimum_has_patience_one():
    """The uniform level that starts at the start search's minimum ends at its first step that is
    no new best (the demo's: 0.0149, 0.0156 -> two iterations, not four); every other level keeps
    the patience it was given, and a stop that is off stays off."""
    from physinteract_usd.fit.converge import level_patience

    assert level_patience(3, True, 1) == 1
    assert level_patience(3, False, 1) == 3
    assert level_patience(0, True, 1) == 0            # the stop is off
    assert level_patience(2, True, 5) == 2            # never longer than the others'
    demo = [0.0149, 0.0156]
    assert plateaued(demo, level_patience(3, True, 1), 0.005)
    assert not plateaued(demo, level_patience(3, False, 1), 0.005)


def test_the_uniform_level_after_the_start_search_is_skipped_when_the_next_fits_nu(tmp_path):
    """levels (1, 4) with nu fitted on both: with skip_searched_uniform on, the uniform level after the
    start search is skipped (every iteration on 4 bumps, the uniform level's share unused); by default it runs
    where no start runs (the CPU's default) and is skipped where one does; when on, it runs where the next level
    does not fit nu."""
    import fit_scene as fs

    from physinteract_usd import api
    from physinteract_usd.fit import FitProblem, FitSettings
    from physinteract_usd.fit import fit as run_fit
    from physinteract_usd.usd.stage import read_stage

    sc = fs.build(tmp_path / "base")
    sd = read_stage(sc["stage"])
    prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, sc["gt"]))
    ks = {}
    resolved = {}
    for name, kw in (("skip", {"skip_searched_uniform": True}), ("off", {}), ("nu1", {"skip_searched_uniform": True, "fit_poisson_levels": 1}),
                     ("starts", {"trend_start": 2, "parts_start": 0})):
        seen, logs = [], []
        s = FitSettings(iterations=4, levels=(1, 4), level_share=(0.5, 0.5), search_evals=2, joint=False,
                        confidence_probes=0, seed=0, plateau_patience=0, **{"fit_poisson_levels": 2, **kw})
        run_fit(prob, s, progress=False, log=logs.append, on_iteration=lambda it, lv, mat, tr: seen.append(mat.K))
        ks[name] = (seen, any("level 1 (K=1) skipped" in m for m in logs))
        resolved[name] = s.skip_searched_uniform
    assert ks["skip"] == ([4, 4], True)
    # the default (None) resolves by whether the starts run: off on the CPU's default (no starts), on where they run
    assert ks["off"] == ([1, 1, 4, 4], False) and resolved["off"] is False
    assert ks["nu1"] == ([1, 1, 4, 4], False)
    assert ks["starts"][1] and resolved["starts"] is True and all(k == 4 for k in ks["starts"][0])
