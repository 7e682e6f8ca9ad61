"""`batch` end to end on three tiny synthetic items (the smallest synth scene, foam_bar, 4 frames,
a 12-cell grid, 2 fit iterations with one golden-section step and no confidence probes; the
diagnosis tests damping only, without refits), one of them broken (a corrupt transforms.json):
in the local process pool and on a local Ray cluster the test starts. Checked: the good items are
fitted, reported, diagnosed (when the verb is there) and exported, the broken one fails with its
one-line error while the rest go on, the summary CSV/HTML and the catalogue stage hold them, a rerun
reuses what is done, and a changed setting re-runs only its step and after."""

from __future__ import annotations

import csv
import json
import shutil
import time
from pathlib import Path

import pytest
from pxr import Usd, UsdGeom, UsdValidation

import physinteract_usd  # noqa: F401  (registers the schemas)
from physinteract_usd import api
from physinteract_usd.app.batch import diagnose_function
from physinteract_usd.batch.keys import STEPS
from physinteract_usd.cli import main
from physinteract_usd.errors import InputError

FRAMES = 4
COLUMNS = "source,name,iterations,grid,seed,grasp_frame,fit_settings,diagnose_settings"
TINY_FIT = "search_evals=1;confidence_probes=0;levels=[1];level_share=[1.0]"
TINY_DIAGNOSE = "refit=0;candidates=damping;max_pixels=1500"


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Two copies of one tiny synthetic capture and a broken one (transforms.json corrupt)."""
    root = tmp_path_factory.mktemp("batch_caps")
    api.synth("foam_bar", root / "a", size="small", frames=FRAMES, log=lambda *a: None)
    shutil.copytree(root / "a", root / "b")
    shutil.copytree(root / "a", root / "broken")
    (root / "broken" / "transforms.json").write_text('{"fl_x": 100, "fl_y": ')
    return root


def write_manifest(root, b_iterations=2):
    m = root / "manifest.csv"
    m.write_text(f"{COLUMNS}\n"
                 f"a,,2,12,,,{TINY_FIT},{TINY_DIAGNOSE}\n"
                 f"b,bee,{b_iterations},12,1,1,{TINY_FIT},{TINY_DIAGNOSE}\n"
                 f"broken,,2,12,,,{TINY_FIT},{TINY_DIAGNOSE}\n")
    return m


def check_first_run(res, out):
    assert sorted(res.ran) == ["a", "bee"] and res.failed == ["broken"] and not res.interrupted
    err = res.records["broken"]["error"]
    assert err.startswith("init: ") and "transforms.json" in err and "\n" not in err
    diag = diagnose_function() is not None
    for name in ("a", "bee"):
        r = res.records[name]
        assert r["status"] == "done", r
        assert [r["steps"][s]["status"] for s in ("init", "extract", "fit", "report", "export")] == ["ran"] * 5
        assert r["steps"]["diagnose"]["status"] == ("ran" if diag else "skipped")
        m = r["metrics"]
        assert m["version"] == 1 and m["iterations"] == 2 and m["final_loss"] > 0
        assert 15 < m["psnr"] < 80 and len(m["frames_psnr"]) == FRAMES
        assert m["verdict"] in ("adequate", "inadequate")
        if diag:
            assert m["diagnosis"] in ("adequate", "missing_effect", "unexplained")
            assert json.loads((out / "items" / name / "diagnose.json").read_text())["verdict"] == m["diagnosis"]
        for key in ("asset", "report_html", "report_json", "stage"):
            assert Path(r["outputs"][key]).is_file(), key
            assert Path(r["outputs"][key]).parent == out / "items" / name
        assert json.loads((out / "items" / name / "batch.json").read_text())["status"] == "done"
    # the hint reached extraction: bee's grasp is the user's, a's the extracted one
    hands = {n: [c for c in api.read_scene(out / "items" / n / "scene.usda").contacts if c.type != "fixed"][0]
             for n in ("a", "bee")}
    assert (hands["a"].source, hands["bee"].source, hands["bee"].grasp_frame) == ("extracted", "user", 1)
    assert res.records["bee"]["settings"]["seed"] == 1
    rows = {r["name"]: r for r in csv.DictReader(open(out / "summary.csv"))}
    assert [rows[n]["status"] for n in ("a", "bee", "broken")] == ["done", "done", "failed"]
    assert rows["broken"]["error"] == err and rows["a"]["asset"] == "items/a/asset.usdc"
    assert float(rows["bee"]["psnr"]) == pytest.approx(res.records["bee"]["metrics"]["psnr"], abs=0.01)
    page = (out / "summary.html").read_text()
    assert "href='items/a/report.html'" in page and "href='items/bee/report.html'" in page
    assert "transforms.json" in page
    check_catalogue(out / "catalogue.usda", ["a", "bee"])


def check_catalogue(path, names):
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == "/Catalogue"
    kids = [p.GetName() for p in stage.GetDefaultPrim().GetChildren()]
    assert kids == names
    for n in names:   # the reference brings the fitted object, its particles animated
        pts = UsdGeom.Points(stage.GetPrimAtPath(f"/Catalogue/{n}/Object/SimParticles"))
        assert pts and len(pts.GetPointsAttr().Get(0)) > 10
        assert pts.GetPointsAttr().GetNumTimeSamples() == FRAMES
        assert stage.GetPrimAtPath(f"/Catalogue/{n}").GetCustomDataByKey("physinteract:batch")["version"] == 1
    # side by side, not on top of each other
    xs = [UsdGeom.Xformable(stage.GetPrimAtPath(f"/Catalogue/{n}")).ComputeLocalToWorldTransform(0).ExtractTranslation()[0]
          for n in names]
    assert len(set(xs)) == len(names)
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(stage) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]


@pytest.fixture(scope="module")
def pool_run(captures):
    """The first run, in a pool of 2 workers."""
    m = write_manifest(captures)
    out = captures / "pool.batch"
    t0 = time.perf_counter()
    res = api.batch(m, out=out, workers=2, progress=False, log=lambda *a: None)
    print(f"\npool, 3 items, 2 workers: {time.perf_counter() - t0:.1f} s")
    return m, out, res


def test_pool_end_to_end(pool_run):
    m, out, res = pool_run
    check_first_run(res, out)


def test_pool_rerun_reuses_what_is_done(pool_run, capsys):
    """A rerun through the CLI: the done items are reused without running, the broken one fails
    again (exit 1, named on stderr)."""
    m, out, _ = pool_run
    t0 = time.perf_counter()
    code = main(["batch", str(m), "--out", str(out), "--no-progress"])
    took = time.perf_counter() - t0
    cap = capsys.readouterr()
    assert code == 1
    assert "broken failed: init: " in cap.err and "transforms.json" in cap.err
    assert "2 reused" in cap.out and "1 failed" in cap.out
    rows = {r["name"]: r for r in csv.DictReader(open(out / "summary.csv"))}
    assert [rows[n]["status"] for n in ("a", "bee", "broken")] == ["reused", "reused", "failed"]
    assert json.loads((out / "items" / "a" / "batch.json").read_text())["metrics"]["version"] == 1
    check_catalogue(out / "catalogue.usda", ["a", "bee"])
    print(f"rerun: {took:.1f} s")


@pytest.mark.slow   # ~25-55 s: a refit; the file's 3-minute budget (the keys' logic is unit-tested in test_batch_runner)
def test_pool_changed_setting_reruns_from_its_step(pool_run):
    """More iterations for one item: it runs again from its fit (a new version on its stage), the
    other is reused."""
    m, out, _ = pool_run
    m = write_manifest(m.parent, b_iterations=3)
    res = api.batch(m, out=out, workers=2, progress=False, log=lambda *a: None)
    assert res.reused == ["a"] and res.ran == ["bee"] and res.failed == ["broken"]
    steps = res.records["bee"]["steps"]
    assert [steps[s]["status"] for s in ("init", "extract", "fit")] == ["reused", "reused", "ran"]
    assert res.records["bee"]["metrics"]["version"] == 2 and res.records["bee"]["metrics"]["iterations"] == 3


def test_stage_item_fitted_in_place_then_reused(pool_run, tmp_path):
    """An existing stage as an item (JSON manifest): no init, its own contacts kept, a new fit
    version on it; a rerun reuses it although the run changed the stage's fit layer."""
    m, out, _ = pool_run
    src = out / "items" / "a"
    copy = out.parent / "stage_copy.batch" / "items" / "a"        # the same depth: its capture paths hold
    shutil.copytree(src, copy, ignore=shutil.ignore_patterns("batch.json", "log.txt", "*.html", "*.json"))
    stage = copy / "scene.usda"
    man = tmp_path / "m.json"
    man.write_text(json.dumps({"defaults": {"fit_settings": {"search_evals": 1, "confidence_probes": 0,
                                                             "levels": [1], "level_share": [1.0]},
                                            "skip": ["diagnose"]},
                               "items": [{"source": str(stage), "name": "staged", "iterations": 2}]}))
    res = api.batch(man, out=tmp_path / "out", workers=1, progress=False, log=lambda *a: None)
    r = res.records["staged"]
    assert r["status"] == "done", r["error"]
    assert [r["steps"][s]["status"] for s in STEPS] == ["skipped", "skipped", "ran", "ran", "skipped", "ran"]
    assert r["metrics"]["version"] == 2                           # the copy held v1: a new version on it
    assert len(api.read_scene(stage).reports) == 2
    assert (tmp_path / "out" / "items" / "staged" / "asset.usdc").is_file()
    res = api.batch(man, out=tmp_path / "out", workers=1, progress=False, log=lambda *a: None)
    assert res.reused == ["staged"] and not res.ran


def test_effects_switched_through_the_effects_verb(pool_run, tmp_path):
    """The manifest's effects go on through `effects add`; on a capture's own stage the ones it no
    longer lists go off, on a user's stage they stay."""
    from physinteract_usd.app.adapters import stage_effects
    from physinteract_usd.app.batch import _apply_effects

    _, out, _ = pool_run
    copy = out.parent / "fx.batch" / "items" / "a"
    shutil.copytree(out / "items" / "a", copy)
    stage = copy / "scene.usda"
    have = lambda: sorted(stage_effects(api.read_scene(stage)))   # noqa: E731
    assert _apply_effects({"kind": "capture"}, {"effects": ["damping", "ground"]}, stage, print) == "+damping, +ground"
    assert have() == ["damping", "ground"]
    assert _apply_effects({"kind": "stage"}, {"effects": ["damping"]}, stage, print) == ""
    assert have() == ["damping", "ground"]
    assert _apply_effects({"kind": "capture"}, {"effects": ["damping"]}, stage, print) == "-ground"
    assert have() == ["damping"]


def test_out_folder_not_ours_is_refused(captures, tmp_path):
    m = write_manifest(captures)
    (tmp_path / "x").write_text("mine")
    with pytest.raises(InputError, match="not written by `batch`"):
        api.batch(m, out=tmp_path, progress=False, log=lambda *a: None)
    assert (tmp_path / "x").read_text() == "mine" and not (tmp_path / "items").exists()


@pytest.mark.slow   # ~45 s alone (Ray's start ~8 s, its workers import torch and Warp afresh): the file's budget
def test_ray_end_to_end_and_rerun(captures):
    """On a local Ray cluster the test starts (2 CPUs): one task per item, the broken one fails
    alone, a rerun reuses what is done."""
    ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install physinteract-usd[ray]")
    m = write_manifest(captures)
    out = captures / "ray.batch"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        t0 = time.perf_counter()
        res = api.batch(m, out=out, ray="", progress=False, log=lambda *a: None)
        print(f"ray, 3 items, 2 CPUs: {time.perf_counter() - t0:.1f} s")
        check_first_run(res, out)
        res = api.batch(m, out=out, ray="", progress=False, log=lambda *a: None)
        assert res.reused == ["a", "bee"] and res.failed == ["broken"] and not res.ran
        assert ray.is_initialized()          # the cluster the caller started is left running
    finally:
        ray.shutdown()


@pytest.mark.slow
def test_sigterm_stops_cleanly_keeping_what_finished(captures, tmp_path):
    """SIGTERM to a running `batch`: the finished item is kept, the running fit writes its best
    iterate (an interrupted version) and its item is recorded as interrupted, exit 130; a rerun
    would start that item from its fit."""
    import signal
    import subprocess
    import sys

    from physinteract_usd.batch.keys import first_stale_step

    m = tmp_path / "m.csv"
    m.write_text("source,name,iterations,grid,fit_settings,skip\n"
                 f"{captures / 'a'},quick,2,12,{TINY_FIT},diagnose\n"
                 f"{captures / 'b'},long,400,12,{TINY_FIT};plateau_patience=1000;plateau_patience_searched=1000,diagnose\n")   # no convergence stop
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "physinteract_usd", "batch", str(m), "--out", str(out), "--workers", "1",
                          "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = out / "items" / "long" / "log.txt"
    deadline = time.time() + 240
    while time.time() < deadline and not (log.exists() and "--- fit" in log.read_text()):
        assert p.poll() is None, p.communicate()
        time.sleep(0.5)
    time.sleep(4.0)   # a few iterations into the fit
    t0 = time.perf_counter()
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    took = time.perf_counter() - t0
    assert p.returncode == 130, err
    print(f"SIGTERM to exit: {took:.1f} s")
    assert took < 30
    recs = {n: json.loads((out / "items" / n / "batch.json").read_text()) for n in ("quick", "long")}
    assert recs["quick"]["status"] == "done"
    assert recs["long"]["status"] == "interrupted" and recs["long"]["error"].startswith("fit: interrupted")
    sd = api.read_scene(out / "items" / "long" / "scene.usda")
    assert [r.get("status") for r in sd.reports] == ["interrupted"]
    rows = {r["name"]: r["status"] for r in csv.DictReader(open(out / "summary.csv"))}
    assert rows == {"quick": "done", "long": "interrupted"}
    from physinteract_usd.app.batch import load_manifest, resolve_settings
    from physinteract_usd.batch.keys import fingerprint, step_keys

    item = [i for i in load_manifest(m) if i.name == "long"][0]
    s = resolve_settings(item, {})
    s["diagnose_available"] = diagnose_function() is not None
    keys = step_keys(s, fingerprint(item.source, item.kind), physinteract_usd.__version__)
    assert first_stale_step(recs["long"]["keys"], keys) == "fit"
