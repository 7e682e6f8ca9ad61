"""The fit decides whether the scan carries its weight where the stage does not say (#23; fit/preload_choice.py).

Known answers: the same clamped bar, its video rendered once from the scan prestressed (scanned settled, as a real
object is) and once from the scan stress-free (it sags in the video); each stage initialised without --preload or
--no-preload. The fit must take the hypothesis the video was made with, write it on the stage, and find E."""
from __future__ import annotations

import numpy as np
import pytest

import fit_scene as fs
from physinteract_usd import api

E_OVER_RHO = 200.0          # a soft, heavy bar: it sags ~cm under its own weight (the two hypotheses differ)
E = 1e5
SETTINGS = dict(schedule="ladder", max_regions=1, sweep_points=7, search_evals=5, confidence_probes=0,
                uniform_share=0.6, final_share=0.4, lr_material=0.1)


def fit_undecided(tmp_path, truth_preloaded: bool):
    b = fs.build(tmp_path / "bar", E=E, density=E / E_OVER_RHO, n_frames=12, release=4, e_range=(1e3, 1e7),
                 lift=np.array([0.0, 0.03, 0.0]), preload=truth_preloaded, stage_preload=None)
    assert api.read_scene(b["stage"]).settings.preload is None       # the stage says nothing
    lines = []
    out = api.fit(b["stage"], iterations=4, contact_from=b["gt"], joint=False, progress=False,
                  log=lambda *a: lines.append(" ".join(map(str, a))), settings_overrides=SETTINGS)
    return b, out, lines


@pytest.mark.parametrize("truth_preloaded", [True, False])
def test_the_fit_takes_the_hypothesis_the_video_was_made_with(tmp_path, truth_preloaded):
    b, out, lines = fit_undecided(tmp_path, truth_preloaded)
    rec = out.result.settings["preload"]
    assert rec["preload"] is truth_preloaded, rec
    loss = rec["loss"]
    if truth_preloaded:      # settled: stress-free the model sags again from the scan
        assert loss["preloaded"] < 0.95 * loss["stress_free"], loss
    else:
        assert loss["stress_free"] < loss["preloaded"], loss
    assert any(line.startswith("preload: ") for line in lines)
    # written on the stage (the fit layer): the next simulation, evaluate and export start the same way
    assert api.read_scene(b["stage"]).settings.preload is truth_preloaded
    e = float(np.median(out.result.youngs))
    assert abs(e / E - 1) < 0.15, (truth_preloaded, e, rec)


def test_an_explicit_setting_is_not_second_guessed(tmp_path):
    # the truth settled, the stage said stress-free (init --no-preload): the fit does as told and decides nothing
    b = fs.build(tmp_path / "bar", E=E, density=E / E_OVER_RHO, n_frames=12, release=4, e_range=(1e3, 1e7),
                 lift=np.array([0.0, 0.03, 0.0]), preload=True, stage_preload=False)
    out = api.fit(b["stage"], iterations=1, contact_from=b["gt"], joint=False, progress=False,
                  log=lambda *a: None, settings_overrides=SETTINGS)
    assert "preload" not in out.result.settings
    assert api.read_scene(b["stage"]).settings.preload is False


def test_a_resumed_or_warm_fit_goes_on_as_the_fit_it_continues():
    from types import SimpleNamespace

    from physinteract_usd.app.fit import decided_preload

    undecided = SimpleNamespace(settings=SimpleNamespace(preload=None))
    said = SimpleNamespace(settings=SimpleNamespace(preload=False))
    ck = {"fingerprint": {"particles": 10, "frames": 5, "preload": True}}
    rep = {"settings": {"preload": {"preload": True, "loss": {}, "E": {}, "reason": ""}}}
    assert decided_preload(undecided, ck, None) is True              # the killed fit's checkpoint
    assert decided_preload(undecided, None, rep) is True             # the version it continues
    assert decided_preload(undecided, {"fingerprint": {}}, {"settings": {}}) is None   # a fit before the choice
    assert decided_preload(said, ck, rep) is False                   # the stage's own word wins
