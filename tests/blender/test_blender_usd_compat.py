"""Issue 2's definition of done, Blender half: a stage `init` writes (usd-core 26.x) opens in
Blender's own USD (25.08, bundled with bpy 5.0.1) with every prim present."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import BLENDER_USD_MAX_CRATE, REPO, clean_env
from pxr import Sdf, Usd, UsdGeom

KINDS = ("gaussians", "mesh", "animated")


def test_blender_usd_is_25_08():
    # what these findings were measured against; a newer Blender may import more (ParticleField)
    assert Usd.GetVersion()[:2] == (0, 25), Usd.GetVersion()


@pytest.mark.parametrize("kind", KINDS)
def test_crate_version_readable_by_blender_usd(stages, kind):
    made = stages[kind]
    assert made.described["crate"], "no .usdc layer in the stage"
    for path, version in made.described["crate"].items():
        assert version is not None, f"{path}: not a usdc crate file"
        assert tuple(version) <= BLENDER_USD_MAX_CRATE, (
            f"{path}: crate {'.'.join(map(str, version))} written by usd-core "
            f"{'.'.join(map(str, made.described['usd']))} is newer than Blender's USD 25.08 reads "
            f"({'.'.join(map(str, BLENDER_USD_MAX_CRATE))}): write with "
            "USD_WRITE_NEW_USDC_FILES_AS_VERSION=0.13.0 or avoid the newer feature")
        layer = Sdf.Layer.FindOrOpen(path)
        assert layer is not None, f"{path}: Blender's USD cannot open it"


@pytest.mark.parametrize("kind", KINDS)
def test_composed_stage_opens_with_every_prim(stages, kind):
    made = stages[kind]
    d = made.described
    stage = Usd.Stage.Open(str(made.stage))
    assert stage is not None
    layers = [os.path.realpath(layer.realPath) for layer in stage.GetLayerStack(includeSessionLayers=False)]
    assert layers == [os.path.realpath(p) for p in d["layers"]]
    assert [os.path.basename(p) for p in layers] == ["scene.usda", "scene.fit.usdc", "scene.init.usdc"]
    assert stage.GetDefaultPrim().GetName() == d["defaultPrim"] == "World"
    assert UsdGeom.GetStageUpAxis(stage) == d["upAxis"] == "Y"
    assert UsdGeom.GetStageMetersPerUnit(stage) == d["metersPerUnit"] == 1.0
    assert stage.GetTimeCodesPerSecond() == d["fps"]
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (d["start"], d["end"])

    ours = {str(p.GetPath()): p for p in stage.TraverseAll()}
    assert sorted(ours) == sorted(d["prims"]), "prim paths differ between usd-core 26 and Blender's USD"
    for path, want in d["prims"].items():
        prim = ours[path]
        assert prim.IsDefined(), path
        assert str(prim.GetTypeName()) == want["type"], path
        got = {a.GetName(): a for a in prim.GetAuthoredAttributes()}
        assert sorted(got) == sorted(want["attributes"]), path
        for name, w in want["attributes"].items():
            a = got[name]
            assert list(a.GetTimeSamples()) == w["samples"], f"{path}.{name}"
            if w["n"] is not None:
                assert len(a.Get(Usd.TimeCode.EarliestTime())) == w["n"], f"{path}.{name}"
    expected = {"/World", "/World/Object", "/World/Object/Splats", "/World/Object/SimParticles",
                "/World/Camera", "/World/PhysInteract"} | ({"/World/Object/Mesh"} if kind == "mesh" else set())
    assert expected <= set(ours)


def test_splats_are_data_without_a_schema_in_blender_usd(stages):
    """USD 25.08 predates UsdVol.ParticleField3DGaussianSplat: the prim keeps its type name and
    attributes (readable as plain data) but has no schema type, so no importer handles it."""
    stage = Usd.Stage.Open(str(stages["gaussians"].stage))
    splats = stage.GetPrimAtPath("/World/Object/Splats")
    assert splats.GetTypeName() == "ParticleField3DGaussianSplat"
    assert splats.GetPrimTypeInfo().GetSchemaType().isUnknown
    n = stages["gaussians"].prims["/World/Object/Splats"]["attributes"]["positions"]["n"]
    assert len(splats.GetAttribute("positions").Get()) == n
    assert splats.GetAttribute("radiance:sphericalHarmonicsDegree").Get() == 0
    assert len(splats.GetAttribute("primvars:displayColor").Get()) == n   # per-Gaussian primvars read as data


SCHEMA_CHECK = r"""
import os, sys
import bpy
sys.path.append(os.path.join(bpy.utils.resource_path("LOCAL"), "python", "lib", "python3.11", "site-packages"))
from pxr import Plug, Usd
assert Plug.Registry().RegisterPlugins(sys.argv[1]), "nothing registered"
reg = Usd.SchemaRegistry()
for t in ("PhysInteractScene", "PhysInteractContactSet", "PhysInteractTrajectory", "PhysInteractFitReport"):
    assert reg.FindConcretePrimDefinition(t) is not None, t
for api in ("PhysInteractMaterialFieldAPI", "PhysInteractDampingAPI", "PhysInteractPlasticityAPI",
            "PhysInteractGroundAPI", "PhysInteractViscoelasticityAPI"):
    assert reg.FindAppliedAPIPrimDefinition(api) is not None, api
stage = Usd.Stage.Open(sys.argv[2])
scene = stage.GetPrimAtPath("/World/PhysInteract")
assert scene.GetPrimTypeInfo().GetSchemaType().typeName == "PhysInteractScene"
assert "physinteract:gridResolution" in scene.GetPrimDefinition().GetPropertyNames()
assert tuple(scene.GetAttribute("physinteract:gridResolution").Get())[0] == 16
pts = stage.GetPrimAtPath("/World/Object/SimParticles")
assert pts.HasAPI("PhysInteractMaterialFieldAPI")
assert pts.GetAttribute("physinteract:constitutiveModel").Get() == "fixedCorotated"
print("ok")
"""


def test_project_schemas_register_in_blender_usd(stages):
    """The codeless schemas (schemas/plugInfo.json + generatedSchema.usda) load in USD 25.08: run
    in a fresh Blender python, since plugins must be registered before the first stage opens."""
    proc = subprocess.run([sys.executable, "-c", SCHEMA_CHECK, str(REPO / "schemas"),
                           str(stages["gaussians"].stage)], capture_output=True, text=True,
                          env=clean_env(), timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stdout + proc.stderr
