"""Fit versions (docs/versions.md): every fit is a version that stays readable and restorable; the
current one is the best by loss (`--keep-best`, the default) or the newest (`--no-keep-best`); an
interrupted fit never replaces a complete one; `versions list|use`; a stage fitted before versions
existed keeps its fit; `init --force` needs `--discard-fits`; what a stage authors is checked on
read, naming the layer; the exported asset depends on no other file.

The versions come from `version_helpers.fake_fit` (the real writer, a hand-made FitResult: a
uniform E and the rest pose shifted up), so no optimiser runs here; tests/test_fit_stop.py runs
real fits and stops them."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdUtils, UsdValidation, Vt

import physinteract_usd  # noqa: F401  (registers the schemas)
from capture_factory import make_capture
from physinteract_usd import api
from physinteract_usd.cli import main
from physinteract_usd.contacts import ContactSet
from physinteract_usd.usd.layout import LayerPaths
from physinteract_usd.usd.stage import read_stage
from version_helpers import fake_fit, tree_md5

PARTICLES = "/World/Object/SimParticles"


@pytest.fixture(scope="module")
def initialised(tmp_path_factory):
    root = tmp_path_factory.mktemp("versions") / "base"
    cap = make_capture(root / "cap")
    (root / "s").mkdir()
    api.init(root / "s" / "scene.usda", cap, grid=10)
    return root


@pytest.fixture
def stage(initialised, tmp_path):
    shutil.copytree(initialised, tmp_path / "w")
    return tmp_path / "w" / "s" / "scene.usda"


def _fit_layer_e(stage):
    layer = Sdf.Layer.FindOrOpen(str(LayerPaths.of(stage).fit))
    layer.Reload(force=True)
    a = layer.GetAttributeAtPath(f"{PARTICLES}.primvars:physinteract:youngsModulus")
    return None if a is None else float(np.asarray(a.default)[0])


def _shown(stage):
    sd = read_stage(stage)
    return sd.current_version, float(sd.youngs_modulus[0])


# ------------------------------------------------------------------------------ keep-best
def test_every_fit_is_a_version_and_the_best_stays_current(stage):
    a = fake_fit(stage, 2e4, loss=0.5)
    assert (a["version"], a["current"], a["made_current"]) == (1, 1, True)
    b = fake_fit(stage, 3e4, loss=0.7)           # worse: kept as a version, not shown
    assert (b["version"], b["current"], b["made_current"]) == (2, 1, False)
    assert "not below v1's" in b["reason"] and "versions use 2" in b["reason"]
    assert _shown(stage) == (1, pytest.approx(2e4)) and _fit_layer_e(stage) == pytest.approx(2e4)
    c = fake_fit(stage, 4e4, loss=0.3)           # better: current
    assert (c["version"], c["current"]) == (3, 3) and "below v1's" in c["reason"]
    assert _shown(stage) == (3, pytest.approx(4e4))
    sd = read_stage(stage)
    assert [r["version"] for r in sd.reports] == [1, 2, 3]
    assert [r["current"] for r in sd.reports] == [False, False, True]
    for r, loss in zip(sd.reports, (0.5, 0.7, 0.3)):
        # what the report verb reads, and what a version adds
        assert r["final_loss"] == pytest.approx(loss) and r["effects"] == [] and len(r["psnr"]) == sd.n_frames
        assert r["status"] == "complete" and r["created"].endswith("+00:00")
        assert r["metrics"]["psnr"] == pytest.approx(np.mean(r["psnr"]))
        assert r["snapshot"] and LayerPaths.of(stage).version_layer(r["version"]).exists()


def test_no_keep_best_takes_the_newest(stage):
    fake_fit(stage, 2e4, loss=0.3)
    out = fake_fit(stage, 3e4, loss=0.9, keep_best=False)
    assert out["made_current"] and out["reason"] == "--no-keep-best"
    assert _shown(stage) == (2, pytest.approx(3e4))


def test_an_interrupted_fit_never_replaces_a_complete_one(stage):
    fake_fit(stage, 2e4, loss=0.5)
    for keep_best in (True, False):
        out = fake_fit(stage, 9e3, loss=0.1, interrupted=True, keep_best=keep_best)
        assert not out["made_current"] and "interrupted" in out["reason"]
        assert _shown(stage) == (1, pytest.approx(2e4))
    sd = read_stage(stage)
    assert [r["status"] for r in sd.reports] == ["complete", "interrupted", "interrupted"]


def test_an_interrupted_first_fit_is_shown_until_a_complete_one_comes(stage):
    assert fake_fit(stage, 2e4, loss=0.2, interrupted=True)["made_current"]    # better than no fit
    out = fake_fit(stage, 3e4, loss=0.6)
    assert out["made_current"] and "v1 was interrupted" in out["reason"]
    assert _shown(stage) == (2, pytest.approx(3e4))


# ----------------------------------------------------------------------------------- use
def test_use_restores_material_animation_contacts_and_trajectories(stage):
    sd = read_stage(stage)
    T = sd.n_frames
    hand = ContactSet("hand", "pointAdherent", np.arange(0, 8), 0, None,
                      np.linspace(0, 0.01, T)[:, None] * [0, 1, 0] + sd.particles_positions[:8].mean(0))
    clamp = ContactSet("clamp", "fixed", np.arange(20, 30))
    t1 = hand.trajectory + [0.002, 0, 0]
    fake_fit(stage, 2e4, loss=0.5, contacts=[hand, clamp], trajectories={"hand": t1}, shift=0.01)
    fake_fit(stage, 5e4, loss=0.1, contacts=[clamp], shift=0.03)
    s2 = read_stage(stage)
    assert s2.current_version == 2 and [c.name for c in s2.contacts] == ["clamp"] and not s2.trajectories

    assert main(["versions", "use", str(stage), "1"]) == 0
    s1 = read_stage(stage)
    assert s1.current_version == 1 and s1.youngs_modulus[0] == pytest.approx(2e4)
    assert sorted(c.name for c in s1.contacts) == ["clamp", "hand"]
    fitted = {t.name: t.positions for t in s1.trajectories}
    np.testing.assert_allclose(fitted["hand_fitted"], t1, atol=1e-6)
    us = Usd.Stage.Open(str(stage))
    pts = UsdGeom.Points(us.GetPrimAtPath(PARTICLES)).GetPointsAttr()
    np.testing.assert_allclose(np.asarray(pts.Get(1))[:, 1] - sd.particles_positions[:, 1], 0.01, atol=1e-6)
    assert [r["version"] for r in s1.reports] == [1, 2]          # both still there

    assert main(["versions", "use", str(stage), "2"]) == 0
    assert _shown(stage) == (2, pytest.approx(5e4))
    assert [c.name for c in read_stage(stage).contacts] == ["clamp"]


def test_versions_list(stage, capsys):
    assert main(["versions", "list", str(stage)]) == 0
    assert "no fit versions yet" in capsys.readouterr().out
    fake_fit(stage, 2e4, loss=0.5)
    fake_fit(stage, 3e4, loss=0.7)
    assert main(["versions", "list", str(stage), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["current"] == 1 and [v["version"] for v in d["versions"]] == [1, 2]
    v1 = d["versions"][0]
    for key in ("status", "created", "effects", "final_loss", "psnr", "psnr_masked", "ssim", "iou", "iterations",
                "current", "snapshot"):
        assert key in v1, key
    assert v1["current"] and not d["versions"][1]["current"] and v1["psnr"] == pytest.approx(31.5)
    assert main(["versions", "list", str(stage)]) == 0
    text = capsys.readouterr().out
    assert "*      v1" in text and "current: v1" in text


# ------------------------------------------------------------------------ never lost
def test_a_stage_fitted_before_versions_keeps_its_fit(stage):
    """A fit layer as written before versions existed (the fit's content and report, no
    currentVersion, no scene.versions/): a better new fit snapshots the old content before
    replacing it, so the old fit is still restorable."""
    fake_fit(stage, 2e4, loss=0.5)
    lp = LayerPaths.of(stage)
    layer = Sdf.Layer.FindOrOpen(str(lp.fit))
    spec = layer.GetPrimAtPath("/World/PhysInteract")
    spec.RemoveProperty(spec.attributes["physinteract:currentVersion"])
    layer.Save()
    shutil.rmtree(lp.versions)
    assert read_stage(stage).current_version == 1                  # the newest fit is what it shows
    out = fake_fit(stage, 4e4, loss=0.2)
    assert out["made_current"] and lp.version_layer(1).exists()
    assert main(["versions", "use", str(stage), "1"]) == 0
    assert _shown(stage) == (1, pytest.approx(2e4))


def test_a_crash_between_snapshot_and_fit_layer_loses_nothing(stage, monkeypatch):
    import physinteract_usd.usd.versions as V

    fake_fit(stage, 2e4, loss=0.5)
    before = tree_md5(stage.parent)

    def crash(layer, path):
        raise OSError(f"{path}: disk full")

    monkeypatch.setattr(V, "save_layer", crash)
    with pytest.raises(OSError):
        fake_fit(stage, 3e4, loss=0.1)
    monkeypatch.undo()
    after = tree_md5(stage.parent)
    assert {k for k in after if after[k] != before.get(k)} == {"scene.versions/v2.usdc"}   # only the snapshot
    sd = read_stage(stage)
    assert [(r["version"], r["current"]) for r in sd.reports] == [(1, True), (2, False)]   # v2 still listed
    assert fake_fit(stage, 4e4, loss=0.9)["version"] == 3           # numbers are never reused
    assert main(["versions", "use", str(stage), "2"]) == 0
    assert _shown(stage) == (2, pytest.approx(3e4))


def test_init_force_discards_fits_only_when_told(stage, capsys):
    fake_fit(stage, 2e4, loss=0.5)
    cap = stage.parent.parent / "cap"
    root_text = stage.read_text()
    before = tree_md5(stage.parent)
    assert main(["init", str(stage), "--capture", str(cap), "--grid", "10", "--force"]) == 2
    assert "--discard-fits" in capsys.readouterr().err and tree_md5(stage.parent) == before
    assert main(["init", str(stage), "--capture", str(cap), "--grid", "10", "--force", "--discard-fits"]) == 0
    assert stage.read_text() == root_text                           # the user's layer survives
    assert not LayerPaths.of(stage).versions.exists()
    assert read_stage(stage).reports == []


# ------------------------------------------------------------------ validation on read
def test_a_bad_value_in_the_fit_layer_is_blamed_on_the_fit_layer(stage, capsys):
    fake_fit(stage, 2e4, loss=0.5)
    lp = LayerPaths.of(stage)
    layer = Sdf.Layer.FindOrOpen(str(lp.fit))
    a = layer.GetAttributeAtPath(f"{PARTICLES}.primvars:physinteract:youngsModulus")
    e = np.asarray(a.default, np.float32).copy()
    e[5] = np.nan
    a.default = Vt.FloatArray.FromNumpy(e)
    layer.Save()
    assert main(["info", str(stage)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(lp.fit) in err and "index 5" in err and "not finite" in err and len(err.splitlines()) == 1
    # the version's snapshot is intact: making it current again repairs the stage (`versions`
    # reads no more of the stage than it needs, so it works on this one)
    assert main(["versions", "use", str(stage), "1"]) == 0 and main(["info", str(stage)]) == 0
    assert _shown(stage) == (1, pytest.approx(2e4))


# ---------------------------------------------------------------------------- export
def test_the_exported_asset_depends_on_nothing(stage, tmp_path, capsys):
    fake_fit(stage, 2e4, loss=0.5, shift=0.01)
    out = tmp_path / "twin.usdc"
    assert main(["export", str(stage), str(out)]) == 0
    far = tmp_path / "elsewhere"
    far.mkdir()
    shutil.copy(out, far / out.name)
    layers, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(far / out.name)))
    assert [lay.realPath for lay in layers] == [str(far / out.name)] and not assets and not unresolved
    s = Usd.Stage.Open(str(far / out.name))
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(s) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]
    assert s.GetPrimAtPath("/World/PhysInteract/FitReport_v1")
    # an existing file is replaced only with --force
    capsys.readouterr()
    assert main(["export", str(stage), str(out)]) == 2 and "--force" in capsys.readouterr().err
    fake_fit(stage, 5e4, loss=0.1)
    assert main(["export", str(stage), str(out), "--force"]) == 0
    us = Usd.Stage.Open(str(out))
    e = us.GetPrimAtPath(PARTICLES).GetAttribute("primvars:physinteract:youngsModulus").Get()
    assert e[0] == pytest.approx(5e4)


def test_export_keeps_capture_paths_only_when_asked(stage, tmp_path):
    out = tmp_path / "twin.usda"
    assert main(["export", str(stage), str(out), "--capture-paths", "absolute"]) == 0
    us = Usd.Stage.Open(str(out))
    frames = us.GetPrimAtPath("/World/PhysInteract").GetAttribute("physinteract:frames").Get()
    assert len(frames) == read_stage(stage).n_frames
    for a in frames:
        assert a.path.startswith("/") and (tmp_path / a.path).exists(), a.path
