"""`synth --random SEED --truth-for-auto N`: the world capture's truth finer than the fit `init --grid auto
--max-particles N` makes of it too (the 22nd session: without it the truth is no finer than that fit on 72% of dev
seeds 0-119; docs/benchmarks/world_fits.md). Default captures are unchanged: the option draws nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest

import physinteract_usd  # noqa: F401
from physinteract_usd import api
from physinteract_usd import metrics as M
from physinteract_usd.cli import main
from physinteract_usd.errors import InputError
from physinteract_usd.synth.world import FIT_PADDING, World, draw_world
from physinteract_usd.thickness import auto_grid


def test_the_option_draws_nothing():
    for seed in (2, 9):
        a, b = draw_world(seed, "dev"), draw_world(seed, "dev", {"truth_for_auto": 15000})
        assert a.pop("truth_for_auto") is None and b.pop("truth_for_auto") == 15000
        assert a == b                      # every drawn value the same: today's captures do not move


@pytest.mark.parametrize("seed", [2, 9])      # two thin sheets whose truth is coarser than the auto fit today
def test_the_truth_is_finer_than_the_auto_fit(seed):
    plain = World(draw_world(seed, "dev"))
    fine = World(draw_world(seed, "dev", {"truth_for_auto": 15000}))
    n, _ = auto_grid(plain._thinnest(), plain._volume(), plain.extent, FIT_PADDING, max_particles=15000)
    cell = (1 + 2 * FIT_PADDING) * plain.extent / n
    assert 2 * plain.h > 0.95 * cell                         # today: no finer than that fit (the finding)
    assert 2 * fine.h <= 0.85 * cell * (1 + 1e-9)           # with the option: 0.85x its cell at most
    assert fine.finer_than == {"init_grid": "auto", "max_particles": 15000, "grid": n, "cell": pytest.approx(cell)}
    assert plain.finer_than is None
    assert fine.fit_grid == plain.fit_grid                   # the README's suggestion is not changed


def test_only_for_world_captures_and_a_cap(tmp_path, capsys):
    with pytest.raises(InputError, match="--truth-for-auto"):
        api.synth("foam_bar", tmp_path / "a", truth_for_auto=15000)
    for bad in (50, True, 1.5):
        with pytest.raises(InputError, match="--truth-for-auto"):
            api.synth(None, tmp_path / "b", random=1, truth_for_auto=bad)
    assert main(["synth", "foam_bar", str(tmp_path / "c"), "--truth-for-auto", "15000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--truth-for-auto" in err[0]
    assert not (tmp_path / "a").exists() and not (tmp_path / "c").exists()


def test_a_tiny_capture_records_it_and_evaluate_reads_a_finer_truth(tmp_path):
    """A tiny capture (a thin bar on a floor, few frames) made with the option: gt.json says which fit the truth is
    finer than, and the truth's cell is finer than the stage `init --grid auto` at that cap makes."""
    ov = {"width": 96, "aspect": "4:3", "fps": 20.0, "frames": 6, "masks": "clean", "encoding": "png", "noise": 0.0,
          "blur": 1, "flicker": 0.0, "gaussians": 600, "e_ratio": 1.0, "e_field": "uniform", "scenario": "floor",
          "shape": "bar", "interaction": "pointAdherent", "look": "sphere", "e_max": 2e4, "length": 0.16,
          "thickness": 0.2, "truth_for_auto": 3000, "settle": False}
    cap = tmp_path / "cap"
    info = api.synth(None, cap, random=7, split="dev", overrides=ov, log=lambda *a: None)
    ft = info["gt_sim"]["finer_than"]
    assert ft["init_grid"] == "auto" and ft["max_particles"] == 3000
    s = info["suggested_init"]
    api.init(tmp_path / "s.usda", cap, grid="auto", max_particles=3000, padding=s["padding"],
             youngs_range=tuple(s["youngs_range"]), max_poisson=s["max_poisson"], density=s["density"],
             log=lambda *a: None)
    from physinteract_usd.usd.stage import read_stage

    stage_cell = read_stage(tmp_path / "s.usda").settings.cell_size
    gt = json.loads((cap / "gt" / "gt.json").read_text())
    r = M.truth_resolution(gt["gt_sim"]["dx"], stage_cell)
    assert r["finer"], r
    assert np.isclose(ft["cell"], stage_cell, rtol=0.15)    # the estimate of init's auto cell, from the shape


def test_world_suite_generate_makes_again_a_capture_made_for_another_truth(tmp_path, monkeypatch):
    """gpu_world.sh now makes the truth finer by default (GRID=auto): a capture already in WORK made for another
    --truth-for-auto is made again (with its stage), one made for this one is reused."""
    import importlib.util
    from pathlib import Path
    p = Path(__file__).resolve().parents[1] / "benchmarks" / "world_suite.py"
    spec = importlib.util.spec_from_file_location("world_suite_t", p)
    ws = importlib.util.module_from_spec(spec)
    monkeypatch.syspath_prepend(str(p.parent))
    spec.loader.exec_module(ws)
    made = []

    def fake_synth(scene, out, random=None, truth_for_auto=None, **kw):
        made.append((out.name, truth_for_auto))
        (out / "gt").mkdir(parents=True)
        ft = None if truth_for_auto is None else {"init_grid": "auto", "max_particles": truth_for_auto}
        (out / "gt" / "gt.json").write_text(json.dumps({"split": "dev", "gt_sim": {"finer_than": ft}}))

    monkeypatch.setattr(ws.api, "synth", fake_synth)
    work = tmp_path / "w"
    ws.generate(work, "dev", [1], "cpu", log=lambda *a, **k: None)                 # today's truth
    (work / "dev_0001.stage").mkdir()                                              # a stage made from it
    ws.generate(work, "dev", [1], "cpu", log=lambda *a, **k: None)                 # reused
    assert made == [("dev_0001", None)]
    lines = []
    ws.generate(work, "dev", [1], "cpu", log=lambda *a, **k: lines.append(a[0]), truth_for_auto=15000)
    assert made[-1] == ("dev_0001", 15000) and not (work / "dev_0001.stage").exists()
    assert "made for --truth-for-auto None, not 15000" in lines[0]
    ws.generate(work, "dev", [1], "cpu", log=lambda *a, **k: None, truth_for_auto=15000)   # reused
    assert len(made) == 2 and ws.made_for(work / "dev_0001" / "gt" / "gt.json") == 15000


def test_world_suite_table_says_ma_by_scenario_with_floor_apart(monkeypatch):
    import importlib.util
    from pathlib import Path
    p = Path(__file__).resolve().parents[1] / "benchmarks" / "world_suite.py"
    spec = importlib.util.spec_from_file_location("world_suite_t2", p)
    ws = importlib.util.module_from_spec(spec)
    monkeypatch.syspath_prepend(str(p.parent))
    spec.loader.exec_module(ws)
    rows = [{"scene": "a", "scenario": "hanging", "fit": {"ma": 1.0}}, {"scene": "b", "scenario": "hanging", "fit": {"ma": 0.5}},
            {"scene": "c", "scenario": "floor", "fit": {"ma": 0.0}}, {"scene": "d", "scenario": "clamped", "fit": None},
            {"scene": "e", "error": "generation failed"}]
    line = ws.ma_by_scenario(rows)
    assert line.startswith("MA by scenario (fits): hanging 0.750 (2), floor 0.000 (1); all but floor 0.750 (2)")
    assert "nodes brakes a roll" in line
    pen = [dict(r, fit=dict(r["fit"] or {}, ground_contact="penalty")) if r.get("scenario") == "floor" else r for r in rows]
    line = ws.ma_by_scenario(pen)
    assert "brakes" not in line and "the ground at the particles" in line
    assert ws.ma_by_scenario(rows[:2]) == "MA by scenario (fits): hanging 0.750 (2)"
    assert ws.ma_by_scenario(rows[3:]) == ""
