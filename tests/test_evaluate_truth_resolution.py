"""`evaluate` says when a synthetic truth was not simulated finer than the fit it scores (`metrics.truth_resolution`):
the 22nd session found three suite scenes whose truths (made for the size's grid 24) were coarser than their fits at
`init --grid auto`, and the fits' MA measured the truth's discretisation (docs/benchmarks/fit.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture_factory import make_capture
from physinteract_usd import api
from physinteract_usd import metrics as M
from physinteract_usd.cli import main
from version_helpers import fake_fit


def test_truth_resolution_known_answers():
    r = M.truth_resolution(0.007, 0.010)                    # synth's rule: the truth's cell 0.7x the fit's
    assert r["finer"] and r["note"] is None and r["ratio"] == pytest.approx(0.7)
    r = M.truth_resolution(0.0122, 0.0094)                  # bow_tie's old truth against its auto fit
    assert not r["finer"] and r["ratio"] == pytest.approx(1.298, abs=1e-3)
    assert "12.2 mm" in r["note"] and "9.4 mm" in r["note"] and "coarser than" in r["note"] and "17.4 mm" in r["note"]
    assert "as coarse as" in M.truth_resolution(0.010, 0.010)["note"]
    assert M.truth_resolution(None, 0.01) is None and M.truth_resolution(0.0, 0.01) is None


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval_res")
    cap = make_capture(root / "cap")
    api.init(root / "scene.usda", cap, grid=10)
    fake_fit(root / "scene.usda", 2.0e4, loss=0.5)
    from physinteract_usd.usd.stage import read_stage

    sd = read_stage(root / "scene.usda")
    gt = root / "gt"
    gt.mkdir()
    np.save(gt / "youngs_modulus.npy", np.full(len(sd.gaussians), 2.0e4))
    np.save(gt / "gaussian_positions.npy", np.repeat(sd.gaussians.means[None], sd.n_frames, 0))
    return root, float(sd.settings.cell_size)


def _gt_json(gt, dx):
    (gt / "gt.json").write_text(json.dumps({"gt_sim": {"dx": dx}}))


def test_evaluate_reports_a_coarser_truth(fitted, capsys):
    root, cell = fitted
    gt = root / "gt"
    _gt_json(gt, 1.5 * cell)
    d = api.evaluate(root / "scene.usda", gt)
    assert d["truth_resolution"]["finer"] is False
    assert d["truth_resolution"]["fit_cell_m"] == pytest.approx(cell)
    assert d["ma"] == pytest.approx(1.0)                     # the note changes no metric
    assert main(["evaluate", str(root / "scene.usda"), "--gt", str(gt)]) == 0
    assert "note: the ground truth was simulated on a" in capsys.readouterr().out
    _gt_json(gt, 0.7 * cell)
    assert api.evaluate(root / "scene.usda", gt)["truth_resolution"]["finer"] is True
    assert main(["evaluate", str(root / "scene.usda"), "--gt", str(gt)]) == 0
    assert "note:" not in capsys.readouterr().out
    (gt / "gt.json").write_text("{not json")                 # no gt_sim to read: no error, but said
    assert api.evaluate(root / "scene.usda", gt)["truth_resolution"] is None
    d = api.evaluate(root / "scene.usda", gt)
    assert "gt.json" in d["truth_resolution_unchecked"] and "not checked" in d["truth_resolution_unchecked"]
    assert main(["evaluate", str(root / "scene.usda"), "--gt", str(gt)]) == 0
    assert "the truth's resolution was not checked" in capsys.readouterr().out
    _gt_json(gt, 0.7 * cell)
    assert api.evaluate(root / "scene.usda", gt)["truth_resolution_unchecked"] is None
