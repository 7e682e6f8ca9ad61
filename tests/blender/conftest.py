"""Blender tests: run INSIDE the Blender venv, `.venv-blender/bin/python -m pytest tests/blender`
(scripts/test-blender.sh makes the venv and runs them).

Blender's environment has bpy 5.0.1 with its own USD (pxr 25.08) and numpy<2, and neither the
project nor usd-core: nothing here imports physinteract_usd. Stages are made by the project's
real CLI through subprocess, as the add-on does for users:

- PHYSINTERACT_CLI     the `physinteract-usd` executable (default <repo>/.venv/bin/physinteract-usd)
- PHYSINTERACT_PYTHON  the project venv's python, for the small usd-core side scripts that list
                       what the project's stage holds (default: beside the CLI, else its #! line)

Under any other interpreter (the project venv's pytest over tests/) these files are not collected.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent

try:
    import bpy  # noqa: F401
except ImportError:  # not Blender's venv: leave these tests to scripts/test-blender.sh
    collect_ignore_glob = ["test_*.py"]
    bpy = None

if bpy is not None:
    sys.path.insert(0, str(HERE))
    try:
        import pxr  # noqa: F401
    except ImportError:  # the bpy wheel keeps Blender's USD Python modules in its own site-packages
        sys.path.append(os.path.join(bpy.utils.resource_path("LOCAL"), "python", "lib",
                                     f"python{sys.version_info.major}.{sys.version_info.minor}",
                                     "site-packages"))

BLENDER_USD_MAX_CRATE = (0, 13, 0)  # the newest usdc version Blender 5.0.1's USD 25.08 reads


def pytest_collection_modifyitems(items):
    for item in items:
        if str(item.fspath).startswith(str(HERE)):
            item.add_marker(pytest.mark.blender)


# ---------------------------------------------------------------------------- project side
@pytest.fixture(scope="session")
def cli() -> str:
    path = os.environ.get("PHYSINTERACT_CLI") or str(REPO / ".venv" / "bin" / "physinteract-usd")
    if not (os.path.isfile(path) and os.access(path, os.X_OK)):
        pytest.fail(f"{path}: the project's physinteract-usd CLI is missing: set PHYSINTERACT_CLI or "
                    "install the project into .venv", pytrace=False)
    return path


@pytest.fixture(scope="session")
def project_python(cli) -> str:
    env = os.environ.get("PHYSINTERACT_PYTHON")
    if env:
        return env
    sibling = Path(cli).with_name("python")
    if sibling.exists():
        return str(sibling)
    first = Path(cli).read_text(errors="replace").splitlines()[0]
    if first.startswith("#!"):
        return first[2:].strip().split()[0]
    pytest.fail(f"{cli}: cannot tell the project's python: set PHYSINTERACT_PYTHON", pytrace=False)


def clean_env() -> dict:
    """The environment for project subprocesses, without what Blender adds for its own USD."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("PXR_") and k not in ("PYTHONPATH", "PYTHONHOME", "MATERIALX_SEARCH_PATH")}
    return env


def run_cli(cli, *args, check=True) -> subprocess.CompletedProcess:
    proc = subprocess.run([cli, *map(str, args)], capture_output=True, text=True, env=clean_env(),
                          timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"physinteract-usd {' '.join(map(str, args))} exited {proc.returncode}:\n"
                             f"{proc.stderr}")
    return proc


# what the project's usd-core sees in a stage: prims, types, applied schemas, authored attributes,
# time samples, stage metadata, and the crate version of every .usdc layer
DESCRIBE = r"""
import json, sys
import physinteract_usd  # registers the PhysInteract schemas
from pxr import Usd, UsdGeom, Sdf
stage = Usd.Stage.Open(sys.argv[1])
prims = {}
for p in stage.TraverseAll():
    attrs = {}
    for a in p.GetAuthoredAttributes():
        v = a.Get(Usd.TimeCode.EarliestTime())
        attrs[a.GetName()] = {"n": len(v) if hasattr(v, "__len__") and not isinstance(v, str) else None,
                              "samples": list(a.GetTimeSamples())}
    prims[str(p.GetPath())] = {"type": str(p.GetTypeName()), "applied": list(p.GetAppliedSchemas()),
                               "attributes": attrs}
crate = {}
for layer in stage.GetLayerStack(includeSessionLayers=False):
    if layer.realPath.endswith(".usdc"):
        with open(layer.realPath, "rb") as f:
            head = f.read(16)
        crate[layer.realPath] = [head[8], head[9], head[10]] if head[:8] == b"PXR-USDC" else None
print(json.dumps({"usd": list(Usd.GetVersion()), "prims": prims, "crate": crate,
                  "layers": [l.realPath for l in stage.GetLayerStack(includeSessionLayers=False)],
                  "defaultPrim": stage.GetDefaultPrim().GetName(), "upAxis": str(UsdGeom.GetStageUpAxis(stage)),
                  "metersPerUnit": UsdGeom.GetStageMetersPerUnit(stage),
                  "fps": stage.GetTimeCodesPerSecond(),
                  "start": stage.GetStartTimeCode(), "end": stage.GetEndTimeCode()}))
"""

# stands in for `fit` until it exists: time-sampled SimParticles points in scene.fit.usdc, each
# frame k shifted by (0.01 k, 0, 0), authored with the project's usd-core
ANIMATE = r"""
import sys
import numpy as np
import physinteract_usd  # noqa: F401
from pxr import Sdf, Usd, UsdGeom, Vt
root, fit = sys.argv[1], sys.argv[2]
stage = Usd.Stage.Open(root)
stage.SetEditTarget(Usd.EditTarget(Sdf.Layer.FindOrOpen(fit)))
pts = UsdGeom.Points(stage.GetPrimAtPath("/World/Object/SimParticles")).GetPointsAttr()
x0 = np.array(pts.Get(), dtype=np.float32)
for k in range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1):
    pts.Set(Vt.Vec3fArray.FromNumpy(x0 + np.float32([0.01 * k, 0.0, 0.0])), Usd.TimeCode(k))
Sdf.Layer.FindOrOpen(fit).Save()
"""


def describe(project_python, stage_path) -> dict:
    proc = subprocess.run([project_python, "-c", DESCRIBE, str(stage_path)], capture_output=True,
                          text=True, env=clean_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


class Made:
    """A capture folder and the stage `init` made from it, with what usd-core sees in it."""

    def __init__(self, capture: Path, stage: Path, described: dict, transforms: dict):
        self.capture, self.stage, self.described, self.transforms = capture, stage, described, transforms

    @property
    def prims(self) -> dict:
        return self.described["prims"]


@pytest.fixture(scope="session")
def stages(tmp_path_factory, cli, project_python) -> dict:
    """Stages written by the real CLI: 'gaussians' (3DGS PLY), 'mesh' (OBJ, principal point off
    centre), 'animated' (the gaussians stage plus time-sampled points in its fit layer)."""
    from blender_capture import make_capture

    root = tmp_path_factory.mktemp("stages")
    out = {}
    for name, kw in (("gaussians", {}), ("mesh", {"mesh": True, "cx": 20.0, "cy": 15.0})):
        cap = make_capture(root / f"cap_{name}", **kw)
        stage = root / name / "scene.usda"
        stage.parent.mkdir()
        run_cli(cli, "init", stage, "--capture", cap, "--grid", "16")
        out[name] = Made(cap, stage, describe(project_python, stage),
                         json.loads((cap / "transforms.json").read_text()))
    anim = root / "animated"
    shutil.copytree(out["gaussians"].stage.parent, anim)
    proc = subprocess.run([project_python, "-c", ANIMATE, str(anim / "scene.usda"), str(anim / "scene.fit.usdc")],
                          capture_output=True, text=True, env=clean_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    out["animated"] = Made(out["gaussians"].capture, anim / "scene.usda",
                           describe(project_python, anim / "scene.usda"), out["gaussians"].transforms)
    return out


# ----------------------------------------------------------------------------- Blender side
@pytest.fixture
def empty_scene():
    """A new, empty Blender file (the add-on, when registered, stays registered)."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True)
    return bpy.context.scene


@pytest.fixture(scope="session")
def addon(cli):
    """The add-on, enabled the way Blender enables add-ons, with its preference set to the CLI."""
    import addon_utils
    import bpy

    sys.path.insert(0, str(REPO / "blender_addon"))
    errors = []
    mod = addon_utils.enable("physinteract_usd_blender", default_set=True, handle_error=errors.append)
    assert mod is not None and not errors, errors
    bpy.context.preferences.addons["physinteract_usd_blender"].preferences.cli_path = cli
    yield mod
    addon_utils.disable("physinteract_usd_blender", default_set=True)


# ------------------------------------------------------------------- a fitted twin (issue 27)
TWIN_FPS = 20.0
TWIN_CONTACT = (0.1, 0.15, 0.0)       # the sphere's +x side (stage frame), in view of the capture's camera
STAGE_TO_BLENDER = ((1, 0, 0), (0, 0, -1), (0, 1, 0))


@pytest.fixture(scope="session")
def twin(tmp_path_factory, addon):
    """A fitted 20 fps stage made through the panel, with hints set in the viewport: the capture's
    suggested init settings (its README), the contact where the 3D cursor is at frame 2, the lowest
    points selected as the support, a 'grasp' marker at frame 1; then extract and a one-iteration
    fit (about half a minute on a free core)."""
    import bpy
    import numpy as np
    from blender_capture import make_capture
    from mathutils import Vector
    from pxr import Usd, UsdGeom

    root = tmp_path_factory.mktemp("twin")
    cap = make_capture(root / "cap", n_frames=6, fps=TWIN_FPS)
    # what `physinteract-usd synth` writes into a capture's README, read by the panel's button
    (cap / "README.txt").write_text("Suggested:\n  physinteract-usd init scene.usda --capture cap --grid 12 "
                                    "--youngs-range 1000,20000 --max-poisson 0.4 --density 150\n")
    stage = root / "out" / "scene.usda"
    bpy.ops.wm.read_homefile(use_empty=True)
    s = bpy.context.scene.physinteract
    s.capture_dir = str(cap)
    s.stage_path = str(stage)
    assert bpy.ops.physinteract.suggested() == {"FINISHED"}, s.error
    s.fit_iterations = 1
    assert bpy.ops.physinteract.run(steps="init,import_stage") == {"FINISHED"}, s.error
    scene = bpy.context.scene

    scene.frame_set(2)
    scene.cursor.location = Vector(np.array(STAGE_TO_BLENDER, float) @ np.array(TWIN_CONTACT))
    assert bpy.ops.physinteract.hint(action="CONTACT_CURSOR") == {"FINISHED"}, s.error
    s.hint_type = "pointAdherent"
    usd = Usd.Stage.Open(str(stage))   # kept: a prim of a stage already freed is invalid
    attr = UsdGeom.Points(usd.GetPrimAtPath("/World/Object/SimParticles")).GetPointsAttr()
    rest = np.asarray(attr.Get(Usd.TimeCode.Default()), float)
    support = np.flatnonzero(rest[:, 1] < rest[:, 1].min() + 0.02)
    pc = bpy.data.objects["SimParticles"]
    sel = pc.data.attributes.get(".selection") or pc.data.attributes.new(".selection", "BOOLEAN", "POINT")
    mask = np.zeros(len(pc.data.points), bool)
    mask[support] = True
    sel.data.foreach_set("value", mask)
    bpy.context.view_layer.objects.active = pc
    assert bpy.ops.physinteract.hint(action="SUPPORT_POINTS") == {"FINISHED"}, s.error
    scene.frame_set(1)
    assert bpy.ops.physinteract.hint(action="GRASP") == {"FINISHED"}
    hints = {"pixel": s.hint_contact_pixel, "support": s.hint_support_particles, "support_idx": support}
    assert bpy.ops.physinteract.run(steps="extract,fit") == {"FINISHED"}, s.error
    hints["note"] = s.note
    return {"stage": stage, "capture": cap, "hints": hints, "rest": rest,
            "transforms": json.loads((cap / "transforms.json").read_text())}
