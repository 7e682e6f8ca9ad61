"""`simulate` and `export` on a fitted tiny stage (tests/fit_scene.py): a new interaction writes its
own time-sampled layer and moves what it pulls while the supports hold; bad interaction specs are
one-line errors with exit code 2; exports are self-contained USD files (.usdc, .usda, .usdz) and
PLY sequences that match the animation, and never overwrite the stage they come from."""

import json
import shutil

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

import fit_scene as fs
import physinteract_usd  # noqa: F401  (registers the schemas)
from physinteract_usd import api
from physinteract_usd.cli import main
from physinteract_usd.gaussians import read_ply
from physinteract_usd.usd.fit_io import read_splat_animation
from physinteract_usd.usd.layout import LayerPaths
from physinteract_usd.usd.stage import read_stage

PARTICLES = "/World/Object/SimParticles"
SPLATS = "/World/Object/Splats"
FIT_SETTINGS = dict(fs.SMOKE_SETTINGS, levels=(1,), level_share=(1.0,), confidence_probes=1)


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def _snapshot(folder):
    """Bytes and mtimes of every file in a folder (recursively)."""
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    b = fs.build(tmp_path_factory.mktemp("simexp") / "scene")
    api.fit(b["stage"], iterations=2, contact_from=b["gt"], progress=False, log=lambda *a: None,
            settings_overrides=FIT_SETTINGS)
    return b


@pytest.fixture
def stage(fitted, tmp_path):
    """A private copy of the fitted scene (tests write next to it)."""
    return fs.copy_scene(fitted["root"], tmp_path / "scene")


def _points(stage_path, prim=PARTICLES, attr="points"):
    s = Usd.Stage.Open(str(stage_path))
    a = s.GetPrimAtPath(prim).GetAttribute(attr)
    return a.GetTimeSamples(), [np.asarray(a.Get(t), np.float64) for t in a.GetTimeSamples()]


# ------------------------------------------------------------------------------------ simulate
def test_simulate_pulls_what_it_selects_and_the_supports_hold(stage, capsys):
    sd = read_stage(stage)
    lp = LayerPaths.of(stage)
    mine = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (lp.root, lp.init, lp.fit)}
    spec = {"name": "lift", "frames": 6, "contacts": [
        {"type": "pointAdherent", "select": {"centre": fs.HAND_CENTRE.tolist(), "radius": fs.HAND_RADIUS},
         "grasp_frame": 1, "displacement": [0.0, 0.05, 0.02]}]}
    path = stage.parent / "lift.json"
    path.write_text(json.dumps(spec))
    code, out, err = run(["simulate", stage, "--interaction", path], capsys)
    assert code == 0, err
    layer, view = stage.with_name("scene.sim.lift.usdc"), stage.with_name("scene.sim.lift.usda")
    assert layer.exists() and view.exists() and str(view) in out
    # nothing of the user's (nor the fit) was touched
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in mine} == mine
    assert "sim" not in " ".join(Sdf.Layer.FindOrOpen(str(lp.root)).subLayerPaths)
    # the new layer: time-sampled particles and splats, frames 0..5, the spec recorded
    sl = Sdf.Layer.FindOrOpen(str(layer))
    data = dict(sl.customLayerData)["physinteract"]
    assert data["layer"] == "simulation" and json.loads(data["interaction"]) == spec
    times, pts = _points(view)
    assert times == list(range(6))
    x0 = sd.particles_positions
    np.testing.assert_allclose(pts[0], x0, atol=1e-6)  # frame 0 at rest
    for name in ("positions", "orientations", "scales"):
        assert _points(view, SPLATS, name)[0] == list(range(6)), name
    # the pulled particles follow the commanded displacement; the support's stay put
    hand = np.where(np.linalg.norm(x0 - fs.HAND_CENTRE, axis=1) <= fs.HAND_RADIUS)[0]
    support = next(c for c in sd.contacts if c.type == "fixed").indices
    # grasped at frame 1: free before (the free end drops under gravity), then moved by the
    # displacement from where it was grasped
    assert (pts[1][hand, 1] - x0[hand, 1]).mean() < -3e-3
    moved = pts[-1][hand].mean(0) - pts[1][hand].mean(0)
    np.testing.assert_allclose(moved, [0.0, 0.05, 0.02], atol=0.002)
    assert np.ptp(pts[-1][hand] - pts[1][hand], axis=0).max() < 1e-3  # all of them, rigidly
    assert np.abs(pts[-1][support] - x0[support]).max() < 1e-4
    free = np.setdiff1d(np.arange(len(x0)), np.concatenate([hand, support]))
    assert np.abs(pts[-1][free] - x0[free]).max() > 0.01  # the span between bends along
    # the view composes the simulation over the fitted stage: material and splats still there
    s = Usd.Stage.Open(str(view))
    e = UsdGeom.PrimvarsAPI(s.GetPrimAtPath(SPLATS)).GetPrimvar("physinteract:youngsModulus").Get()
    assert len(e) == len(sd.gaussians)


def test_simulate_velocity_on_a_stage_contact_without_supports(stage, capsys):
    spec = {"frames": 4, "keep_supports": False,
            "contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}, "velocity": [0.0, 0.0, -0.24]}]}
    path = stage.parent / "push.json"
    path.write_text(json.dumps(spec))
    code, _, err = run(["simulate", stage, "--interaction", path, "--name", "push_back"], capsys)
    assert code == 0, err
    times, pts = _points(stage.with_name("scene.sim.push_back.usda"))
    assert times == list(range(4))
    sd = read_stage(stage)
    hand = next(c for c in sd.contacts if c.name == "hand").indices
    x0 = sd.particles_positions
    # 3 frames at 0.24 m/s and 24 fps: 3 cm back
    np.testing.assert_allclose(pts[-1][hand].mean(0) - x0[hand].mean(0), [0, 0, -0.03], atol=0.004)
    # no support kept: the held end sags under gravity now
    support = next(c for c in sd.contacts if c.type == "fixed").indices
    assert (pts[-1][support, 1] - x0[support, 1]).mean() < -1e-3


BAD_SPECS = [
    ("{not json", "not valid JSON"),
    ("[]", "non-empty 'contacts' list"),
    ({"contacts": []}, "non-empty 'contacts' list"),
    ({"frames": 1, "contacts": [{"type": "fixed", "select": {"indices": [0]}}]}, "'frames' must be at least 2"),
    ({"contacts": [{"type": "grab"}]}, "contacts[0]: type must be"),
    ({"contacts": [{"type": "pointAdherent", "displacement": [0, 0.1, 0]}]}, "contacts[0]: needs 'select'"),
    ({"contacts": [{"type": "pointAdherent", "select": {"centre": [5, 5, 5], "radius": 0.01},
                    "displacement": [0, 0.1, 0]}]}, "contacts[0]: no particle within"),
    ({"contacts": [{"type": "pointAdherent", "select": {"indices": [0, 99999]}, "displacement": [0, 0.1, 0]}]},
     "contacts[0]: indices must lie in"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "claw"}, "displacement": [0, 0.1, 0]}]},
     "no contact set 'claw'"),
    ({"contacts": [{"type": "pointAdherent", "select": {"radius": 0.1}, "displacement": [0, 0.1, 0]}]},
     "'select' needs centre+radius"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}}]}, "give a trajectory"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}, "trajectory": [[0, 0, 0]]}]},
     "trajectory must be 5 positions"),
    ({"contacts": [{"type": "pointNonAdherent", "trajectory": [[0, 0.2, 0]] * 5}]}, "needs a radius > 0"),
    ({"name": "a b", "contacts": [{"type": "pointAdherent", "select": {"contact": "hand"},
                                    "displacement": [0, 0.1, 0]}]}, "letters, digits"),
    # malformed values: named, never a traceback
    ({"contacts": [1]}, "contacts[0]: expected an object"),
    ({"frames": "x", "contacts": [{"type": "fixed", "select": {"contact": "hand"}}]}, "'frames' must be an integer"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}, "displacement": [0, 0.1]}]},
     "'displacement' must be three numbers"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}, "velocity": "up"}]},
     "'velocity' must be three numbers"),
    ({"contacts": [{"type": "pointAdherent", "select": {"centre": [0, 0.1], "radius": 0.1},
                    "displacement": [0, 0.1, 0]}]}, "'centre' must be three numbers"),
    ({"contacts": [{"type": "pointAdherent", "select": {"indices": [1.5]}, "displacement": [0, 0.1, 0]}]},
     "'indices' must be a non-empty list of integers"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}, "grasp_frame": 9,
                    "displacement": [0, 0.1, 0]}]}, "grasp_frame must lie in [0, 4)"),
    ({"contacts": [{"type": "pointAdherent", "select": {"contact": "hand"}, "grasp_frame": 3, "release_frame": 2,
                    "displacement": [0, 0.1, 0]}]}, "release_frame must lie in (3, 5]"),
    ({"contacts": [{"type": "fixed", "select": {"contact": "hand"}},
                   {"type": "pointAdherent", "select": {"contact": "hand"}, "displacement": [0, 0.1, 0]}]},
     "hold the same particles"),
    ({"contacts": [{"type": "surfaceNonAdherent", "normal": [0, 0, 0], "trajectory": [[0, 0.1, 0]] * 5}]},
     "'normal' must be a non-zero vector"),
    ({"contacts": [{"type": "pointNonAdherent", "radius": 0.02, "displacement": [0, 0.1, 0]}]},
     "collider needs a 'trajectory'"),
]


@pytest.mark.parametrize("spec,message", BAD_SPECS, ids=[m for _, m in BAD_SPECS])
def test_bad_interaction_specs_are_one_line_errors(fitted, tmp_path, capsys, spec, message):
    stage = fitted["stage"]
    before = _snapshot(stage.parent)
    path = tmp_path / "spec.json"
    path.write_text(spec if isinstance(spec, str) else json.dumps(spec))
    code, out, err = run(["simulate", stage, "--interaction", path], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("physinteract-usd simulate: error:"), err
    assert message in lines[0]
    if "letters, digits" not in message:
        assert str(path) in lines[0]  # names the file
    assert _snapshot(stage.parent) == before  # nothing written


def test_missing_spec_file(fitted, tmp_path, capsys):
    code, _, err = run(["simulate", fitted["stage"], "--interaction", tmp_path / "nope.json"], capsys)
    assert code == 2 and "nope.json" in err and "file not found" in err and len(err.strip().splitlines()) == 1


# -------------------------------------------------------------------------------------- export
def _check_self_contained(path, src_stage):
    """`path` opens alone (no other layer used) and holds the fitted stage's points, material
    primvars, animation and report."""
    s = Usd.Stage.Open(str(path))
    used = [lay.realPath for lay in s.GetUsedLayers() if not lay.anonymous]
    if path.suffix == ".usdz":
        assert all(u.startswith(str(path)) for u in used), used  # only what is inside the package
    else:
        assert used == [str(path)], used
    assert not s.GetRootLayer().subLayerPaths
    src = Usd.Stage.Open(str(src_stage))
    assert s.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert UsdGeom.GetStageUpAxis(s) == UsdGeom.GetStageUpAxis(src)
    for prim in (PARTICLES, SPLATS):
        a, b = s.GetPrimAtPath(prim), src.GetPrimAtPath(prim)
        assert a and a.GetTypeName() == b.GetTypeName()
        for name in ("youngsModulus", "poissonRatio", "confidence"):
            pa = UsdGeom.PrimvarsAPI(a).GetPrimvar(f"physinteract:{name}")
            assert pa, (prim, name)
            np.testing.assert_array_equal(np.asarray(pa.Get()),
                                          np.asarray(UsdGeom.PrimvarsAPI(b).GetPrimvar(f"physinteract:{name}").Get()))
    for prim, attr in ((PARTICLES, "points"), (SPLATS, "positions"), (SPLATS, "orientations"), (SPLATS, "scales")):
        a, b = s.GetPrimAtPath(prim).GetAttribute(attr), src.GetPrimAtPath(prim).GetAttribute(attr)
        assert a.GetTimeSamples() == b.GetTimeSamples() == list(range(fs.N_FRAMES)), (prim, attr)
        for t in (0, fs.N_FRAMES - 1):
            assert a.Get(t) == b.Get(t), (prim, attr, t)
    np.testing.assert_array_equal(np.asarray(s.GetPrimAtPath(PARTICLES).GetAttribute("points").Get()),
                                  np.asarray(src.GetPrimAtPath(PARTICLES).GetAttribute("points").Get()))
    assert s.GetPrimAtPath("/World/PhysInteract/FitReport_v1").GetTypeName() == "PhysInteractFitReport"
    assert s.GetPrimAtPath("/World/PhysInteract/hand_fitted").GetAttribute("physinteract:position").GetNumTimeSamples() == fs.N_FRAMES
    assert s.GetTimeCodesPerSecond() == fs.FPS and s.GetEndTimeCode() == fs.N_FRAMES - 1
    return s


@pytest.mark.parametrize("ext", [".usdc", ".usda", ".usdz"])
def test_export_is_self_contained(stage, tmp_path, capsys, ext):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / f"twin{ext}"
    before = _snapshot(stage.parent)
    code, text, err = run(["export", stage, out], capsys)
    assert code == 0, err
    assert str(out) in text
    assert _snapshot(stage.parent) == before  # the source is untouched
    s = _check_self_contained(out, stage)
    frames = s.GetPrimAtPath("/World/PhysInteract").GetAttribute("physinteract:frames").Get()
    assert frames is None  # the capture's frames are the capture's: the asset names no other file
    if ext == ".usda":
        assert "subLayers" not in out.read_text()
    # moved away from everything it came from, it still opens with all its data
    far = tmp_path / "elsewhere"
    far.mkdir()
    moved = far / out.name
    shutil.copy(out, moved)
    _check_self_contained(moved, stage)


def test_export_ply_sequence_matches_the_animation(stage, tmp_path, capsys):
    plys = tmp_path / "plys"
    code, text, err = run(["export", stage, tmp_path / "twin.usdc", "--ply-sequence", plys], capsys)
    assert code == 0, err
    assert f"{fs.N_FRAMES} PLY frames" in text
    files = sorted(plys.iterdir())
    assert [f.name for f in files] == [f"{k:06d}.ply" for k in range(fs.N_FRAMES)]
    anim = read_splat_animation(stage)
    g0 = read_stage(stage).gaussians
    for k, f in enumerate(files):
        g = read_ply(f)  # a readable INRIA-layout 3DGS PLY
        assert len(g) == len(g0)
        np.testing.assert_allclose(g.means, anim["positions"][k], atol=1e-6)
        np.testing.assert_allclose(g.scales, anim["scales"][k], rtol=1e-4)
        q = g.quats / np.linalg.norm(g.quats, axis=1, keepdims=True)
        dots = np.abs((q * anim["quats"][k]).sum(1))
        assert dots.min() > 0.9999
        np.testing.assert_allclose(g.opacities, g0.opacities, atol=1e-5)
        np.testing.assert_allclose(g.sh, g0.sh, atol=1e-5)
    np.testing.assert_allclose(read_ply(files[0]).means, g0.means, atol=1e-5)       # frame 0: the input
    assert np.abs(read_ply(files[-1]).means - g0.means).max() > 0.01                  # then it moves
    # a folder that is not empty is refused, before anything is written
    code, _, err = run(["export", stage, tmp_path / "twin2.usdc", "--ply-sequence", plys], capsys)
    assert code == 2 and "not empty" in err
    assert not (tmp_path / "twin2.usdc").exists()


def test_export_never_overwrites_the_stage(stage, capsys):
    lp = LayerPaths.of(stage)
    before = _snapshot(stage.parent)
    for target in (lp.root, lp.fit, lp.init):
        code, _, err = run(["export", stage, target], capsys)
        assert code == 2, target
        assert "would overwrite a layer of the stage itself" in err and len(err.strip().splitlines()) == 1
    assert _snapshot(stage.parent) == before
    # nor a simulation view's own layer (its stage is the view over the fitted stage)
    spec = stage.parent / "s.json"
    spec.write_text(json.dumps({"frames": 3, "contacts": [
        {"type": "pointAdherent", "select": {"contact": "hand"}, "displacement": [0, 0.02, 0]}]}))
    assert run(["simulate", stage, "--interaction", spec], capsys)[0] == 0
    view, sim_layer = stage.with_name("scene.sim.s.usda"), stage.with_name("scene.sim.s.usdc")
    before = _snapshot(stage.parent)
    for target in (sim_layer, view, lp.fit):
        code, _, err = run(["export", view, target], capsys)
        assert code == 2 and "would overwrite a layer of the stage itself" in err, target
    assert _snapshot(stage.parent) == before
    assert run(["export", view, stage.parent / "sim_twin.usda"], capsys)[0] == 0  # elsewhere: fine
    assert Usd.Stage.Open(str(stage.parent / "sim_twin.usda")).GetPrimAtPath(PARTICLES).GetAttribute(
        "points").GetTimeSamples() == [0, 1, 2]
    code, _, err = run(["export", stage, stage.parent / "twin.obj"], capsys)
    assert code == 2 and ".usdz" in err
    code, _, err = run(["export", stage, stage.parent / "missing" / "twin.usdc"], capsys)
    assert code == 2 and "does not exist" in err
