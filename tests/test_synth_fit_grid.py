"""`synth --fit-grid N`: the capture suggests init grid N and its truth is simulated on a cell
gt_ratio x that grid's (a finer truth for a finer fit); the default is unchanged."""

from __future__ import annotations

import dataclasses

import pytest

from physinteract_usd.errors import InputError
from physinteract_usd.synth.generate import SIZES, GroundTruth, generate
from physinteract_usd.synth.scenes import SCENES


def test_the_truth_follows_the_suggested_grid():
    spec = SCENES["foam_bar"]
    base = GroundTruth(spec, SIZES["small"], 4)
    fine = GroundTruth(spec, dataclasses.replace(SIZES["small"], fit_grid=48), 4)
    assert SIZES["small"].fit_grid == 24
    assert fine.spacing == pytest.approx(0.5 * base.spacing)
    assert fine.grid.dx == pytest.approx(0.5 * base.grid.dx, rel=1e-6)
    assert fine.substeps >= 1.9 * base.substeps          # the truth steps at most half the fit's dt


def test_a_bad_fit_grid_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="--fit-grid"):
        generate("foam_bar", tmp_path / "x", frames=4, fit_grid=4)
