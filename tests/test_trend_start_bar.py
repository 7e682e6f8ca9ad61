"""The trend start through the simulator and renderer (fit/trend_start.py), a case with a known answer: the tiny
cantilever of tests/fit_scene.py rendered with E graded log-linearly along its length, 4x from the clamp (stiff) to the
hand (soft), 10 frames (3 held back). The fit from the true contacts takes a trend along the bar, stiffer at the clamp,
nested as the field's base, the free end's E within 25% of the truth's (the clamp's end, held, is seen less: 0.6x);
a uniform bar's fit takes none. (A simplex cut as the parts start's is on the CPU stopped on this bar at a 2% gain, a
0.69x-scaled trend that rendered no better than one E on the held-back frames: the trend start's is uncut.)"""

from __future__ import annotations

import math

import numpy as np
import pytest

import fit_scene as fs
from physinteract_usd import api

pytestmark = pytest.mark.usefixtures("one_torch_thread")

E_CLAMP, E_HAND = 1.6e4, 4.0e3


def _graded(x):
    t = np.clip((x[:, 0] - fs.LO[0]) / fs.LENGTH, 0.0, 1.0)
    return np.exp((1 - t) * math.log(E_CLAMP) + t * math.log(E_HAND))


def _fit(root, E):
    b = fs.build(root, E=E, n_frames=10)
    logs = []
    over = {**fs.SMOKE_SETTINGS, "trend_start": 20, "parts_start": 0}
    out = api.fit(b["stage"], iterations=10, contact_from=b["gt"], settings_overrides=over, progress=False,
                  log=logs.append)
    return b, out.result, logs


def test_a_graded_bar_starts_from_its_trend_along_the_bar(tmp_path):
    b, r, logs = _fit(tmp_path / "graded", _graded)
    ps = r.model.get("parts_start") or {}
    assert ps.get("kind") == "trend" and ps.get("used"), logs
    assert abs(ps["axis"][0]) > 0.95, ps["axis"]                       # along the bar
    ends = [math.exp(v) for v in ps["log_e"]]
    clamp_end, hand_end = (ends[0], ends[1]) if ps["axis"][0] > 0 else (ends[1], ends[0])
    assert clamp_end > 1.5 * hand_end, ends                               # stiffer at the clamp (truth 4x)
    assert abs(hand_end / E_HAND - 1) < 0.25 and 0.4 < clamp_end / E_CLAMP < 1.25, ends
    assert r.model.get("nested")


def test_a_uniform_bar_takes_no_trend(tmp_path):
    _, r, logs = _fit(tmp_path / "uniform", fs.E_TRUE)
    ps = r.model.get("parts_start") or {}
    assert ps.get("kind") == "trend" and not ps.get("used"), (ps, logs)


def test_both_starts_screened_take_the_trend_on_the_graded_bar(tmp_path):
    """Both starts on (a GPU's default, forced here on the CPU), ordered by their screens (`starts_order` "screened"):
    the graded bar's trend screens lower than its colour parts and is taken; the parts simplex never runs."""
    b = fs.build(tmp_path / "both", E=_graded, n_frames=10)
    logs = []
    over = {**fs.SMOKE_SETTINGS, "trend_start": 20, "parts_start": 20, "starts_order": "screened"}
    r = api.fit(b["stage"], iterations=10, contact_from=b["gt"], settings_overrides=over, progress=False,
                log=logs.append).result
    ps = r.model.get("parts_start") or {}
    assert ps.get("kind") == "trend" and ps.get("used") and ps["order"][0] == "trend", (ps, logs)
    assert ps["screens"]["trend"] < ps["screens"]["parts"] and "parts_start" not in ps
    assert not any(m.startswith("parts start:") for m in logs)
    assert abs(ps["axis"][0]) > 0.95 and r.model.get("nested")
