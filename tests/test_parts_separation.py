"""The colour parts' separation (fit/regions.py `separation`, fit/parts_start.py PARTS_MIN_SEPARATION; #24): regions
lie apart at the scale of the parts, a pattern's two colour classes are interleaved, and the parts start does not try
the latter (on the H200 suite, glove's checker was taken on held-back frames and lowered its MA)."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from physinteract_usd.fit import regions as R
from physinteract_usd.fit.parts_start import PARTS_MIN_SEPARATION


def _bar(n=(24, 8, 8), h=1.0):
    i, j, k = np.meshgrid(*(np.arange(m) for m in n), indexing="ij")
    return np.c_[i.ravel(), j.ravel(), k.ravel()].astype(float) * h, (i.ravel(), j.ravel(), k.ravel())


def test_a_bars_two_halves_are_regions_and_its_checker_is_not():
    x, (i, j, k) = _bar()
    halves = (i >= 12).astype(int)
    checker = ((i // 2 + j // 2 + k // 2) % 2).astype(int)        # 2-particle cubes, as a 3D checker pattern
    stripes = ((i // 3) % 2).astype(int)                          # rings along the bar, 3 particles wide
    assert R.separation(x, halves) > 2 * PARTS_MIN_SEPARATION
    assert R.separation(x, checker) < 0.5 * PARTS_MIN_SEPARATION
    assert R.separation(x, stripes) < PARTS_MIN_SEPARATION
    # the same at another spacing: the measure has no length scale of its own
    assert R.separation(x * 0.003, halves) == pytest.approx(R.separation(x, halves))
    assert R.separation(x, np.zeros(len(x), int)) == math.inf


def test_a_flat_layer_against_one_neighbour_scores_about_sqrt3():
    """Two slabs stacked along z, 20 particles thick each, 40 x 40 across: each part's mean distance to the other is
    half its thickness, its thinnest extent thickness / sqrt(12): sqrt(3) in the limit (a little more when discrete)."""
    x, (i, j, k) = _bar((40, 40, 40))
    lab = (k >= 20).astype(int)
    s = R.separation(x, lab)
    assert math.sqrt(3) <= s < 1.1 * math.sqrt(3)
    assert s > PARTS_MIN_SEPARATION


def test_the_parts_start_does_not_try_an_interleaved_pattern(monkeypatch):
    """The screened starts on the bowl problem of tests/test_trend_start.py with a checker's colours: the parts start
    is not built (no screen probe, a line saying why), the trend start runs alone; with the halves' colours it is
    screened as before."""
    import test_trend_start as T
    from physinteract_usd.fit import select
    from physinteract_usd.fit import trend_start as ts

    x = T._grid()
    g = np.round((x - x.min(0)) / np.array([0.05 / 3, 0.05, 0.05 / 3])).astype(int)
    t = (x[:, 1] - x[:, 1].min()) / np.ptp(x[:, 1])
    truth = math.log(3.75e4) * t + math.log(7.5e3) * (1 - t)
    for name, labels in (("checker", (g.sum(1) % 2).astype(np.int64)), ("halves", (t > 0.5).astype(np.int64))):
        prob, calls = T._problem(truth, x)
        monkeypatch.setattr(select, "part_candidates",
                            lambda *a, lab=labels: [{"kind": "appearance", "parts": 2, "labels": lab}])
        mat = T._Mat(np.full(len(x), float(np.mean(truth))))
        s = types.SimpleNamespace(select_sweep_batch="never", select_holdout_every=3, select_penalty=0.002,
                                  parts_nest=False)
        total = lambda: float(prob.loss(mat.youngs().detach(), None, None, None)["rec"])   # noqa: E731
        said = []
        rec = ts.starts_hook(20, 20, "screened")(prob, mat, s, None, None, total, log=said.append)
        if name == "checker":
            assert any("interleaved" in m and "not tried" in m for m in said), said
            assert rec["screens"]["parts"] == math.inf and rec["order"] == ["trend"]
            assert rec["used"] and rec["kind"] == "trend" and rec["forwards"] == len(calls)
        else:
            assert not any("interleaved" in m for m in said)
            assert math.isfinite(rec["screens"]["parts"])
