"""The parts start's parts by shape (#24): where the colours make no regions, a composite object's thin and thick parts
(a glove's fingers and palm) are the parts the start fits one E each; an object of one thickness has none."""
import math
import types

import numpy as np
import pytest

from physinteract_usd.fit import regions as R

H = 0.005   # the lattice's spacing (metres)


def _lattice(lo, hi):
    ax = [np.arange(a, b) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


def _glove():
    """A palm (14 x 14 x 10 cells) with three fingers (5 x 5 cells, 14 long) hanging from it; (points, finger mask)."""
    palm = _lattice((0, 0, 0), (14, 14, 10))
    fingers = [_lattice((1 + 5 * i, -14, 2), (6 + 5 * i - 1, 0, 7)) for i in range(3)]
    idx = np.unique(np.concatenate([palm] + fingers), axis=0)
    return idx * H, idx[:, 1] < 0


def test_a_palm_with_fingers_splits_thin_from_thick_and_a_block_does_not():
    x, finger = _glove()
    graph = R.particle_graph(x, 1.6 * H)
    cl, (thin, thick) = R.thickness_clusters(x, H, np.ones(len(x), bool), graph)
    assert cl is not None
    agree = np.mean((cl == 0) == finger)
    assert agree > 0.9, agree                      # the thin class is the fingers
    assert thick > 1.5 * thin and 0.015 < thin < 0.035 and 0.035 < thick < 0.065, (thin, thick)
    assert R.separation(x, cl) > 1.4               # regions, not a pattern
    block = _lattice((0, 0, 0), (12, 20, 10)) * H  # one thickness: no parts
    cl2, _ = R.thickness_clusters(block, H, np.ones(len(block), bool), R.particle_graph(block, 1.6 * H))
    assert cl2 is None


@pytest.mark.parametrize("colours", ["none", "checker"])
def test_the_parts_start_fits_the_shape_parts_where_the_colours_make_no_regions(monkeypatch, colours):
    """The bowl problem of tests/test_trend_start.py on the glove: stiff palm, soft fingers (5x apart), colours of one
    part or a checker's interleaved classes. The parts start takes the shape's parts and recovers both E within 10%;
    with `parts_by_shape` off it has no parts and changes nothing."""
    import test_trend_start as T
    from physinteract_usd.fit import parts_start, select
    from physinteract_usd.fit import trend_start as ts

    x, finger = _glove()
    truth = np.where(finger, math.log(7.5e3), math.log(3.75e4))
    idx = np.round(x / H).astype(int)
    checker = (idx.sum(1) % 2).astype(np.int64)
    cands = [] if colours == "none" else [{"kind": "appearance", "parts": 2, "labels": checker}]
    monkeypatch.setattr(select, "part_candidates", lambda *a, **k: cands)
    monkeypatch.setattr(parts_start, "forwards_are_cheap", lambda prob: True)   # the cap's probes, as on CUDA
    for by_shape in (True, False):
        prob, calls = T._problem(truth, x)
        prob.scene.settings.particle_spacing = H
        mat = T._Mat(np.full(len(x), float(np.mean(truth))))
        s = types.SimpleNamespace(select_sweep_batch="never", select_holdout_every=3, select_penalty=0.002,
                                  parts_nest=True, parts_by_shape=by_shape, region_min_share=0.03, select_max_parts=4)
        total = lambda: float(prob.loss(mat.youngs().detach(), None, None, None)["rec"])   # noqa: E731
        said = []
        rec = ts.starts_hook(20, 0)(prob, mat, s, None, None, total, log=said.append)
        e = mat.youngs().detach().numpy()
        if not by_shape:
            assert not rec["used"] and rec["parts"] == 0 and len(calls) == 0
            assert np.allclose(e, math.exp(float(np.mean(truth))))
            continue
        assert rec["used"] and rec["by"] == "thickness" and rec["parts"] == 2, (rec, said)
        assert any("by thickness" in m for m in said), said
        assert abs(np.median(e[finger]) / 7.5e3 - 1) < 0.1 and abs(np.median(e[~finger]) / 3.75e4 - 1) < 0.1, (
            np.median(e[finger]), np.median(e[~finger]))
        assert rec["forwards"] == len(calls)


def test_a_glove_of_one_material_keeps_its_uniform_start(monkeypatch):
    """The same palm and fingers, one E throughout (the uniform start at it): the shape's parts are built and screened,
    but they render no better than the uniform E, so the start is not taken and the field is left exactly."""
    import test_trend_start as T
    from physinteract_usd.fit import parts_start, select
    from physinteract_usd.fit import trend_start as ts

    x, _ = _glove()
    truth = np.full(len(x), math.log(1.5e4))
    monkeypatch.setattr(select, "part_candidates", lambda *a, **k: [])
    monkeypatch.setattr(parts_start, "forwards_are_cheap", lambda prob: True)
    prob, calls = T._problem(truth, x)
    prob.scene.settings.particle_spacing = H
    mat = T._Mat(truth.copy())
    s = types.SimpleNamespace(select_sweep_batch="never", select_holdout_every=3, select_penalty=0.002,
                              parts_nest=True, parts_by_shape=True, region_min_share=0.03, select_max_parts=4)
    total = lambda: float(prob.loss(mat.youngs().detach(), None, None, None)["rec"])   # noqa: E731
    said = []
    rec = ts.starts_hook(20, 0)(prob, mat, s, None, None, total, log=said.append)
    assert rec["by"] == "thickness" and not rec["used"], (rec, said)
    assert np.array_equal(mat.log_e().detach().numpy(), truth)


def test_the_cli_turns_the_shape_parts_off(tmp_path, monkeypatch):
    """`fit --no-shape-parts` reaches the settings (parts_by_shape False); without it nothing is overridden there."""
    from physinteract_usd import api
    from physinteract_usd.cli import main
    from physinteract_usd.fit import FitSettings

    assert FitSettings().parts_by_shape is True
    seen = []

    def fake_fit(stage, **kw):
        seen.append(kw.get("settings_overrides") or {})
        raise SystemExit(0)

    monkeypatch.setattr(api, "fit", fake_fit)
    stage = tmp_path / "scene.usda"
    stage.write_text("#usda 1.0\n")
    for argv in (["fit", str(stage), "--no-shape-parts"], ["fit", str(stage)]):
        with pytest.raises(SystemExit):
            main(argv)
    assert seen[0]["parts_by_shape"] is False and "parts_by_shape" not in seen[1]
