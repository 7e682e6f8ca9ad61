"""The synthetic truth's pin rule (#24): the fit's PHYSINTERACT_PIN_RULE never reaches the truth (the 19th session's
suite A/B under the band ran band fits against default-rule truths); PHYSINTERACT_TRUTH_PIN_RULE sets it, unset is
the rule every capture was made with (4, 0), and gt.json records it."""

from __future__ import annotations

import pytest

from physinteract_usd import simulation
from physinteract_usd.errors import InputError
from physinteract_usd.synth.generate import SIZES, GroundTruth, truth_pin_rule
from physinteract_usd.synth.scenes import SCENES


def _model():
    return GroundTruth(SCENES["foam_bar"], SIZES["small"], 4).model()


def test_the_truth_keeps_the_default_rule_whatever_the_fits_rule(monkeypatch):
    monkeypatch.delenv("PHYSINTERACT_TRUTH_PIN_RULE", raising=False)
    monkeypatch.setenv("PHYSINTERACT_PIN_RULE", "band")
    monkeypatch.setattr(simulation, "PIN_RULE", simulation.CLAMP_BAND)
    m = _model()
    assert (m.pin_gain, m.pin_floor) == (4.0, 0.0) == truth_pin_rule()


def test_the_truths_rule_is_set_by_its_own_variable(monkeypatch):
    monkeypatch.setenv("PHYSINTERACT_TRUTH_PIN_RULE", "band")
    m = _model()
    assert (m.pin_gain, m.pin_floor) == simulation.CLAMP_BAND
    monkeypatch.setenv("PHYSINTERACT_TRUTH_PIN_RULE", "2,0.1")
    assert truth_pin_rule() == (2.0, 0.1)
    monkeypatch.setenv("PHYSINTERACT_TRUTH_PIN_RULE", "clamp")
    with pytest.raises(InputError, match="PHYSINTERACT_TRUTH_PIN_RULE"):
        truth_pin_rule()


def test_gt_json_records_the_truths_rule(tmp_path, monkeypatch):
    from physinteract_usd.synth.generate import generate

    monkeypatch.setenv("PHYSINTERACT_TRUTH_PIN_RULE", "band")
    info = generate("foam_bar", tmp_path / "cap", frames=3, log=lambda *a: None)
    assert info["gt_sim"]["pin_rule"] == [5.0, 0.4]
