"""Every bad input is one line on stderr naming the file, layer, prim or flag, with exit code 2 (3 for
a simulation that goes unstable or leaves its domain), and changes nothing: each case runs the
command line on a private copy of a capture, an initialised stage and a fitted one, and compares
the md5 of every file in that copy before and after.

The fitted stage's versions come from `version_helpers.fake_fit` (the real writer, a hand-made
result): no optimiser runs here. Captures are tiny (tests/capture_factory.py)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from pxr import Sdf, Vt

import physinteract_usd  # noqa: F401  (registers the schemas)
from capture_factory import make_capture
from physinteract_usd import api
from physinteract_usd.cli import main
from version_helpers import fake_fit, tree_md5, unwritable

PARTICLES = "/World/Object/SimParticles"
SPLATS = "/World/Object/Splats"
SCENE = "/World/PhysInteract"


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_inputs") / "base"
    cap = make_capture(root / "cap")
    (root / "new").mkdir()
    (root / "stage").mkdir()
    api.init(root / "stage" / "scene.usda", cap, grid=10)
    shutil.copytree(root / "stage", root / "fitted")
    fake_fit(root / "fitted" / "scene.usda", 2.0e4, loss=0.5)
    gt = root / "gt"
    gt.mkdir()
    from physinteract_usd.usd.stage import read_stage

    sd = read_stage(root / "fitted" / "scene.usda")
    np.save(gt / "youngs_modulus.npy", np.full(len(sd.gaussians), 2.0e4))
    np.save(gt / "gaussian_positions.npy", np.repeat(sd.gaussians.means[None], sd.n_frames, 0))
    return root


# ----------------------------------------------------------------------------------- setups
def _author(stage, prim, name, type_name, value):
    """Author `name` on `prim` in the stage's root layer (the user's), as a user would."""
    layer = Sdf.Layer.FindOrOpen(str(stage))
    spec = Sdf.CreatePrimInLayer(layer, prim)
    attr = spec.attributes.get(name) or Sdf.AttributeSpec(spec, name, type_name)
    attr.default = value
    layer.Save()


def _count(stage, prim="/World/Object/SimParticles"):
    from pxr import Usd

    s = Usd.Stage.Open(str(stage))
    return len(s.GetPrimAtPath(prim).GetAttribute("points" if prim == PARTICLES else "positions").Get())


def _e_values(w, bad, stage="stage", prim=PARTICLES):
    st = w / stage / "scene.usda"
    n = _count(st, prim)
    e = np.full(n, 2.0e4, np.float32)
    e[3] = bad
    _author(st, prim, "primvars:physinteract:youngsModulus", Sdf.ValueTypeNames.FloatArray, Vt.FloatArray.FromNumpy(e))


def _transforms(w, change):
    p = w / "cap" / "transforms.json"
    tj = json.loads(p.read_text())
    change(tj)
    p.write_text(json.dumps(tj))


def _scale_rotation(tj):
    m = np.array(tj["transform_matrix"])
    m[:3, 0] *= 1.5
    tj["transform_matrix"] = m.tolist()


def _mirror_rotation(tj):
    m = np.array(tj["transform_matrix"])
    m[:3, 0] *= -1.0
    tj["transform_matrix"] = m.tolist()


def _masks(w, value, only_first=False):
    from physinteract_usd.frames import write_mask

    for p in sorted((w / "cap" / "masks").iterdir()):
        write_mask(p, np.full((48, 64), value, bool))
        if only_first:
            break


def _triangle_mesh(w):
    (w / "cap" / "object.ply").unlink()
    (w / "cap" / "object.obj").write_text("v 0 0.1 0\nv 0.1 0.1 0\nv 0 0.2 0\nf 1 2 3\n")


def _truncated_video(w):
    from physinteract_usd.frames import write_video

    shutil.rmtree(w / "cap" / "frames")
    write_video(w / "cap" / "video.mp4", np.random.default_rng(0).random((4, 48, 64, 3)), 24.0)
    b = (w / "cap" / "video.mp4").read_bytes()
    (w / "cap" / "video.mp4").write_bytes(b[: len(b) // 2])


def _orphan(w, keep):
    """A stage folder whose root layer is gone, `keep` ("fit" or "init") left behind."""
    d = w / "orphan"
    shutil.copytree(w / "fitted", d)
    (d / "scene.usda").unlink()
    for other in ("fit", "init"):
        if other != keep:
            (d / f"scene.{other}.usdc").unlink()
    shutil.rmtree(d / "scene.versions")


def _foreign_root(w):
    d = w / "foreign"
    d.mkdir()
    (d / "scene.usda").write_text('#usda 1.0\n(\n    defaultPrim = "Thing"\n)\n\ndef Xform "Thing"\n{\n}\n')


def _foreign_fit_layer(w):
    d = w / "foreignfit"
    d.mkdir()
    (d / "scene.fit.usdc").write_bytes(b"not ours at all")


def _camera_skew(w):
    from pxr import Gf

    st = w / "stage" / "scene.usda"
    layer = Sdf.Layer.FindOrOpen(str(st))
    spec = Sdf.CreatePrimInLayer(layer, "/World/Camera")
    attr = spec.attributes.get("xformOp:transform") or Sdf.AttributeSpec(spec, "xformOp:transform",
                                                                         Sdf.ValueTypeNames.Matrix4d)
    m = Gf.Matrix4d(1.0)
    m.SetRow(0, Gf.Vec4d(1.0, 0.4, 0.0, 0.0))   # a shear
    m.SetRow(3, Gf.Vec4d(0.3, 0.3, 0.6, 1.0))
    attr.default = m
    layer.Save()


def _contact_out_of_range(w):
    st = w / "stage" / "scene.usda"
    layer = Sdf.Layer.FindOrOpen(str(st))
    spec = Sdf.CreatePrimInLayer(layer, SCENE + "/grip")
    spec.specifier = Sdf.SpecifierDef
    spec.typeName = "PhysInteractContactSet"
    a = Sdf.AttributeSpec(spec, "physinteract:particleIndices", Sdf.ValueTypeNames.IntArray)
    a.default = Vt.IntArray([0, 1, 10 ** 6])
    Sdf.AttributeSpec(spec, "physinteract:contactType", Sdf.ValueTypeNames.Token).default = "fixed"
    layer.Save()


def _remove_snapshot(w):
    (w / "fitted" / "scene.versions" / "v1.usdc").unlink()


def _existing_file(w):
    (w / "twin.usdc").write_bytes(b"somebody else's file")


def _spec(w, text, name="pull.json"):
    (w / name).write_text(text)


def _soft_stage(w):
    cap = w / "cap"
    (w / "soft").mkdir()
    api.init(w / "soft" / "scene.usda", cap, grid=10, youngs_range=(1e-3, 1e-2))
    _spec(w, json.dumps({"frames": 30, "contacts": [{"type": "fixed", "select": {"centre": [0.0, 0.25, 0.0],
                                                                                  "radius": 0.03}}]}), "hold.json")


# --------------------------------------------------------------------------------- the table
# id, argv ({w}: the work folder; {stage}: an initialised stage; {fitted}: a stage with v1; {cap}),
# exit code, what the one line must name, setup(w) (run on the copy before the md5s are taken)
INIT = ["init", "{w}/new/scene.usda", "--capture", "{cap}", "--grid", "10"]
CASES = [
    # init: outputs
    ("init-unwritable-folder", ["init", "{w}/ro/scene.usda", "--capture", "{cap}"], 2, ["/ro", "not writable"], None),
    ("init-stage-is-a-folder", ["init", "{w}/dir.usda", "--capture", "{cap}"], 2, ["dir.usda", "is a folder"],
     lambda w: (w / "dir.usda").mkdir()),
    ("init-root-not-usda", ["init", "{w}/new/scene.txt", "--capture", "{cap}"], 2, ["scene.txt", ".usda"], None),
    ("init-missing-output-folder", ["init", "{w}/nowhere/scene.usda", "--capture", "{cap}"], 2,
     ["nowhere", "does not exist"], None),
    ("init-existing-stage", ["init", "{stage}", "--capture", "{cap}"], 2, ["scene.usda", "already exists"], None),
    ("init-force-on-fitted-stage", ["init", "{fitted}", "--capture", "{cap}", "--force"], 2,
     ["--force", "1 fit version", "--discard-fits"], None),
    ("init-fit-layer-without-root", ["init", "{w}/orphan/scene.usda", "--capture", "{cap}"], 2,
     ["scene.fit.usdc", "without its root layer"], lambda w: _orphan(w, "fit")),
    ("init-init-layer-without-root", ["init", "{w}/orphan/scene.usda", "--capture", "{cap}"], 2,
     ["scene.init.usdc", "without its root layer"], lambda w: _orphan(w, "init")),
    ("init-force-foreign-root", ["init", "{w}/foreign/scene.usda", "--capture", "{cap}", "--force"], 2,
     ["foreign/scene.usda", "another tool"], _foreign_root),
    ("init-force-foreign-fit-layer", ["init", "{w}/foreignfit/scene.usda", "--capture", "{cap}", "--force"], 2,
     ["scene.fit.usdc", "another tool"], _foreign_fit_layer),
    # init: flags
    ("init-youngs-inf", INIT + ["--youngs-range", "1e3,inf"], 2, ["--youngs-range", "finite"], None),
    ("init-youngs-1e300", INIT + ["--youngs-range", "1e9,1e300"], 2, ["--youngs-range", "32-bit"], None),
    ("init-youngs-nan", INIT + ["--youngs-range", "nan,1e6"], 2, ["--youngs-range"], None),
    ("init-youngs-min-above-max", INIT + ["--youngs-range", "1e6,1e3"], 2, ["--youngs-range", "MIN < MAX"], None),
    ("init-youngs-not-numbers", INIT + ["--youngs-range", "soft,hard"], 2, ["--youngs-range"], None),
    ("init-youngs-hours", INIT + ["--youngs-range", "1e9,1e12"], 2, ["--youngs-range", "substeps per frame", "--yes"],
     None),
    ("init-padding-negative", INIT + ["--padding", "-1"], 2, ["--padding"], None),
    ("init-padding-zero", INIT + ["--padding", "0"], 2, ["--padding"], None),
    ("init-grid-too-small", INIT[:-1] + ["4"], 2, ["--grid"], None),
    ("init-density-negative", INIT + ["--density", "-5"], 2, ["--density"], None),
    ("init-poisson-too-high", INIT + ["--poisson", "0.7"], 2, ["--poisson"], None),
    ("init-fps-zero", INIT + ["--fps", "0"], 2, ["--fps"], None),
    # init: the capture
    ("init-camera-not-orthonormal", INIT, 2, ["transforms.json", "not orthonormal"],
     lambda w: _transforms(w, _scale_rotation)),
    ("init-camera-reflection", INIT, 2, ["transforms.json", "reflection"], lambda w: _transforms(w, _mirror_rotation)),
    ("init-one-open-triangle", INIT, 2, ["object.obj", "flat"], _triangle_mesh),
    ("init-masks-all-black", INIT, 2, ["masks", "empty (all black)"], lambda w: _masks(w, False)),
    ("init-masks-all-white", INIT, 2, ["masks/000000.png", "whole frame"], lambda w: _masks(w, True)),
    ("init-first-mask-black", INIT, 2, ["masks/000000.png", "first mask is empty"],
     lambda w: _masks(w, False, only_first=True)),
    ("init-truncated-video", INIT, 2, ["video.mp4", "cannot be decoded"], _truncated_video),
    ("init-missing-capture", ["init", "{w}/new/scene.usda", "--capture", "{w}/nope"], 2, ["nope"], None),
    # fit
    ("fit-zero-iterations", ["fit", "{fitted}", "--iterations", "0"], 2, ["--iterations"], None),
    ("fit-negative-iterations", ["fit", "{fitted}", "--iterations", "-5"], 2, ["--iterations"], None),
    ("fit-billion-iterations", ["fit", "{fitted}", "--iterations", "1000000000"], 2,
     ["--iterations", "would take about", "--yes"], None),
    ("fit-hours-of-substeps", ["fit", "{stage}"], 2, ["scene.usda", "substeps per frame", "--yes"],
     lambda w: _author(w / "stage" / "scene.usda", SCENE, "physinteract:substeps", Sdf.ValueTypeNames.Int, 400000)),
    ("fit-checkpoint-every-negative", ["fit", "{fitted}", "--checkpoint-every", "-1"], 2, ["--checkpoint-every"], None),
    ("fit-appearance-negative", ["fit", "{fitted}", "--appearance", "-1"], 2, ["--appearance"], None),
    ("fit-unknown-device", ["fit", "{fitted}", "--device", "tpu"], 2, ["--device"], None),
    ("fit-resume-without-fit", ["fit", "{stage}", "--resume"], 2, ["scene.usda", "nothing to resume"], None),
    ("fit-contact-from-missing", ["fit", "{stage}", "--contact-from", "{w}/nogt"], 2, ["nogt"], None),
    ("fit-negative-e-authored", ["fit", "{stage}", "--iterations", "2"], 2,
     ["stage/scene.usda", PARTICLES, "youngsModulus", "below"], lambda w: _e_values(w, -1.0)),
    # authored values, on read (every verb refuses them)
    ("info-negative-e", ["info", "{stage}"], 2, ["stage/scene.usda", PARTICLES, "youngsModulus", "-1"],
     lambda w: _e_values(w, -1.0)),
    ("info-nan-e", ["info", "{stage}"], 2, ["stage/scene.usda", "youngsModulus", "not finite"],
     lambda w: _e_values(w, float("nan"))),
    ("info-e-above-range", ["info", "{stage}"], 2, ["youngsModulus", "above", "--youngs-range"],
     lambda w: _e_values(w, 1e9)),
    ("info-e-count", ["info", "{stage}"], 2, ["youngsModulus", "values for"],
     lambda w: _author(w / "stage" / "scene.usda", PARTICLES, "primvars:physinteract:youngsModulus",
                       Sdf.ValueTypeNames.FloatArray, Vt.FloatArray([2e4, 2e4, 2e4]))),
    ("info-poisson-out-of-range", ["info", "{stage}"], 2, ["poissonRatio"],
     lambda w: _author(w / "stage" / "scene.usda", PARTICLES, "primvars:physinteract:poissonRatio",
                       Sdf.ValueTypeNames.FloatArray, Vt.FloatArray([0.7] * _count(w / "stage" / "scene.usda")))),
    ("info-camera-sheared", ["info", "{stage}"], 2, ["stage/scene.usda", "/World/Camera", "not orthonormal"],
     _camera_skew),
    ("info-fps-zero", ["info", "{stage}"], 2, ["stage/scene.usda", "physinteract:fps"],
     lambda w: _author(w / "stage" / "scene.usda", SCENE, "physinteract:fps", Sdf.ValueTypeNames.Double, 0.0)),
    ("info-substeps-zero", ["info", "{stage}"], 2, ["physinteract:substeps"],
     lambda w: _author(w / "stage" / "scene.usda", SCENE, "physinteract:substeps", Sdf.ValueTypeNames.Int, 0)),
    ("info-contact-index-out-of-range", ["info", "{stage}"], 2, ["/World/PhysInteract/grip", "particleIndices"],
     _contact_out_of_range),
    ("info-not-a-stage", ["info", "{w}/cap/transforms.json"], 2, ["transforms.json"], None),
    ("export-nan-e", ["export", "{stage}", "{w}/twin.usdc"], 2, ["stage/scene.usda", "not finite"],
     lambda w: _e_values(w, float("nan"))),
    ("evaluate-nan-splat-e", ["evaluate", "{fitted}", "--gt", "{w}/gt"], 2,
     ["fitted/scene.usda", SPLATS, "not finite"], lambda w: _e_values(w, float("nan"), "fitted", SPLATS)),
    ("evaluate-corrupt-gt-array", ["evaluate", "{fitted}", "--gt", "{w}/gt"], 2,
     ["gaussian_positions.npy", "not a readable .npy array"],
     lambda w: (w / "gt" / "gaussian_positions.npy").write_text("not an array")),
    ("evaluate-gt-array-of-objects", ["evaluate", "{fitted}", "--gt", "{w}/gt"], 2,
     ["youngs_modulus.npy", "not a readable .npy array"],
     lambda w: np.save(w / "gt" / "youngs_modulus.npy", np.array([{"E": 1}], dtype=object), allow_pickle=True)),
    ("simulate-negative-e", ["simulate", "{stage}", "--interaction", "{w}/pull.json"], 2, ["youngsModulus"],
     lambda w: (_e_values(w, -1.0), _spec(w, json.dumps({"contacts": [{"type": "fixed", "select": {"indices": [0]}}]})))),
    # export
    ("export-unwritable-folder", ["export", "{fitted}", "{w}/ro/twin.usdc"], 2, ["/ro", "not writable"], None),
    ("export-path-is-a-folder", ["export", "{fitted}", "{w}/cap"], 2, ["cap", "is a folder"], None),
    ("export-existing-file", ["export", "{fitted}", "{w}/twin.usdc"], 2, ["twin.usdc", "--force"], _existing_file),
    ("export-bad-extension", ["export", "{fitted}", "{w}/twin.txt"], 2, ["twin.txt", ".usdc"], None),
    ("export-onto-its-own-layer", ["export", "{fitted}", "{w}/fitted/scene.fit.usdc"], 2,
     ["scene.fit.usdc", "layer of the stage itself"], None),
    # versions
    ("versions-use-unknown", ["versions", "use", "{fitted}", "7"], 2, ["fitted/scene.usda", "no fit version 7", "v1"],
     None),
    ("versions-use-zero", ["versions", "use", "{fitted}", "0"], 2, ["VERSION"], None),
    ("versions-use-not-a-number", ["versions", "use", "{fitted}", "latest"], 2, ["VERSION", "latest"], None),
    ("versions-use-lost-snapshot", ["versions", "use", "{fitted}", "1"], 2, ["v1.usdc", "missing"], _remove_snapshot),
    ("versions-list-not-a-stage", ["versions", "list", "{w}/cap/transforms.json"], 2, ["transforms.json"], None),
    # simulate
    ("simulate-missing-spec", ["simulate", "{fitted}", "--interaction", "{w}/none.json"], 2, ["none.json"], None),
    ("simulate-too-soft", ["simulate", "{w}/soft/scene.usda", "--interaction", "{w}/hold.json"], 3,
     ["left the grid domain", "--padding", "--youngs-range"], _soft_stage),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(base, tmp_path, capfd, case):
    name, argv, code, names, setup = case
    w = tmp_path / "w"
    shutil.copytree(base, w)
    if setup is not None:
        setup(w)
    subs = {"w": str(w), "stage": str(w / "stage" / "scene.usda"), "fitted": str(w / "fitted" / "scene.usda"),
            "cap": str(w / "cap")}
    args = [a.format(**subs) for a in argv]
    before = tree_md5(w)
    capfd.readouterr()
    with unwritable(w / "ro") as ro_ok:
        if "/ro/" in " ".join(argv) and not ro_ok:
            pytest.skip("cannot make a folder unwritable here")
        try:
            got = main(args)
        except SystemExit as exc:       # argparse: a malformed flag value
            got = exc.code
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert got == code, err
    assert len(lines) == 1, err        # one line: no traceback, no Warp / FFmpeg noise before it
    if code == 3:
        assert "GridSpec" not in lines[0]
    for n in names:
        assert n in lines[0], (n, lines[0])
    after = tree_md5(w)
    assert after == before, {k for k in set(before) | set(after) if before.get(k) != after.get(k)}


def test_the_table_is_long_enough():
    assert len(CASES) >= 40


# ------------------------------------------------------------------- as a new user runs them
def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "physinteract_usd", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


def test_no_noise_before_the_line_in_a_fresh_process(base, tmp_path):
    """In a process of its own (Warp not yet initialised, FFmpeg's log on): a truncated video and a
    fit of a billion iterations are each exactly one line on stderr."""
    w = tmp_path / "w"
    shutil.copytree(base, w)
    _truncated_video(w)
    r = _cli("init", w / "new.usda", "--capture", w / "cap", cwd=w)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "moov" not in r.stderr and "Warp" not in r.stderr
    r = _cli("fit", w / "fitted" / "scene.usda", "--iterations", "1000000000", cwd=w)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Warp CUDA" not in r.stderr and "--iterations" in r.stderr


def test_yes_goes_on_where_the_cost_warning_stopped(base, tmp_path, capfd):
    """`--yes` is what the warning asks for: with it, the stage of 1e9..1e12 Pa is written (its
    substeps are what the warning counted)."""
    w = tmp_path / "w"
    shutil.copytree(base, w)
    args = ["init", str(w / "new" / "scene.usda"), "--capture", str(w / "cap"), "--grid", "10", "--youngs-range",
            "1e9,1e12"]
    assert main(args) == 2
    count = int(capfd.readouterr().err.split(" substeps")[0].split()[-1].replace(",", ""))
    assert count > 10_000
    assert main(args + ["--yes"]) == 0
    assert api.info(w / "new" / "scene.usda")["simulation"]["substeps_per_frame"] == count


def test_a_corrupt_sublayer_is_named_not_skipped(tmp_path):
    """USD skips a sublayer it cannot read (a warning); the stage would read as unfitted. Our open
    names the layer instead."""
    from physinteract_usd.errors import InputError
    from physinteract_usd.usd.stage import open_stage

    root = tmp_path / "scene.usda"
    root.write_text('#usda 1.0\n(\n    subLayers = [@./scene.fit.usdc@]\n)\n')
    (tmp_path / "scene.fit.usdc").write_bytes(b"PXR-USDC" + bytes(range(200)))
    before = (tmp_path / "scene.fit.usdc").read_bytes()
    with pytest.raises(InputError, match="scene.fit.usdc: cannot be read as a USD layer"):
        open_stage(root)
    assert (tmp_path / "scene.fit.usdc").read_bytes() == before
