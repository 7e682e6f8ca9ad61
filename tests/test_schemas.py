"""The codeless PhysInteract schemas: registered, documented fallbacks, apply guards, round trip."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import physinteract_usd  # noqa: F401  (registers the schemas)
from physinteract_usd.usd import API_SCHEMAS, EFFECT_APIS, SCHEMA_DIR, SCHEMA_TYPES
from pxr import Sdf, Usd

REPO = Path(__file__).resolve().parents[1]


def test_every_schema_is_registered():
    reg = Usd.SchemaRegistry()
    for t in SCHEMA_TYPES:
        assert reg.FindConcretePrimDefinition(t) is not None, t
        assert reg.IsConcrete(t)
    for api in API_SCHEMAS:
        assert reg.FindAppliedAPIPrimDefinition(api) is not None, api
        assert reg.GetAPISchemaTypeName(api) == api, api  # an API schema under its own name ('' for a typed one)
        assert reg.IsAppliedAPISchema(api) and not reg.IsMultipleApplyAPISchema(api), api  # apiSchemaType = "singleApply"
    assert set(EFFECT_APIS) == {"damping", "plasticity", "ground", "viscoelasticity"}


def test_generated_files_are_up_to_date():
    r = subprocess.run([sys.executable, "-m", "pxr.Usd.usdGenSchema", "-v", "-q",
                        str(SCHEMA_DIR / "schema.usda"), str(SCHEMA_DIR)], capture_output=True, text=True,
                       cwd=REPO)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.parametrize("attr,value", [
    ("physinteract:plasticity:yieldStress", float("inf")),
    ("physinteract:damping:coefficient", 0.0),
    ("physinteract:viscoelasticity:modulus", 0.0),
    ("physinteract:ground:friction", 0.5),
])
def test_effect_fallbacks_are_the_null_values(attr, value):
    stage = Usd.Stage.CreateInMemory()
    scene = stage.DefinePrim("/World/PhysInteract", "PhysInteractScene")
    api = [a for e, a in EFFECT_APIS.items() if f":{e}:" in attr][0]
    scene.ApplyAPI(api)
    assert scene.GetAttribute(attr).Get() == value


def test_typed_fallbacks():
    stage = Usd.Stage.CreateInMemory()
    cs = stage.DefinePrim("/C", "PhysInteractContactSet")
    assert cs.GetAttribute("physinteract:contactType").Get() == "pointAdherent"
    tokens = cs.GetAttribute("physinteract:contactType").GetMetadata("allowedTokens")
    assert list(tokens) == ["pointAdherent", "pointNonAdherent", "surfaceNonAdherent", "fixed"]
    scene = stage.DefinePrim("/S", "PhysInteractScene")
    assert tuple(scene.GetAttribute("physinteract:gravity").Get()) == pytest.approx((0, -9.81, 0))
    pts = stage.DefinePrim("/P", "Points")
    pts.ApplyAPI("PhysInteractMaterialFieldAPI")
    assert pts.GetAttribute("physinteract:constitutiveModel").Get() == "fixedCorotated"
    assert pts.GetAttribute("physinteract:density").Get() == 1000.0


def test_can_apply_guards():
    stage = Usd.Stage.CreateInMemory()
    scene = stage.DefinePrim("/S", "PhysInteractScene")
    pts = stage.DefinePrim("/P", "Points")
    mesh = stage.DefinePrim("/M", "Mesh")
    for api in EFFECT_APIS.values():
        assert scene.CanApplyAPI(api)
        assert not pts.CanApplyAPI(api)
        assert not mesh.CanApplyAPI(api)
    assert pts.CanApplyAPI("PhysInteractMaterialFieldAPI")
    assert not mesh.CanApplyAPI("PhysInteractMaterialFieldAPI")
    assert not scene.CanApplyAPI("PhysInteractMaterialFieldAPI")


def test_round_trip_in_a_fresh_process(tmp_path):
    """Author every schema attribute with a non-fallback value, save, read back elsewhere."""
    path = tmp_path / "rt.usda"
    stage = Usd.Stage.CreateNew(str(path))
    reg = Usd.SchemaRegistry()
    prims = {}
    for i, t in enumerate(SCHEMA_TYPES):
        prims[t] = stage.DefinePrim(f"/T{i}", t)
    pts = stage.DefinePrim("/P", "Points")
    pts.ApplyAPI("PhysInteractMaterialFieldAPI")
    for api in EFFECT_APIS.values():
        prims["PhysInteractScene"].ApplyAPI(api)
    expected = {}
    for path_prim in list(prims.values()) + [pts]:
        for name in path_prim.GetPrimDefinition().GetPropertyNames():
            prop = path_prim.GetPrimDefinition().GetSchemaPropertySpec(name)
            if not name.startswith(("physinteract:", "primvars:physinteract:")):
                continue
            if isinstance(prop, Sdf.RelationshipSpec):
                path_prim.GetRelationship(name).SetTargets([Sdf.Path("/P")])
                expected[(str(path_prim.GetPath()), name)] = "rel:/P"
                continue
            attr = path_prim.GetAttribute(name)
            tn = attr.GetTypeName()
            allowed = prop.GetInfo("allowedTokens") if prop.HasInfo("allowedTokens") else None
            value = _sample_value(tn, allowed)
            assert attr.Set(value), (name, tn)
            expected[(str(path_prim.GetPath()), name)] = repr(attr.Get())
    stage.Save()
    code = textwrap.dedent(f"""
        import physinteract_usd, json
        from pxr import Usd
        st = Usd.Stage.Open({str(path)!r})
        out = {{}}
        for prim in st.Traverse():
            for name in prim.GetPrimDefinition().GetPropertyNames():
                if not name.startswith(("physinteract:", "primvars:physinteract:")):
                    continue
                rel = prim.GetRelationship(name)
                if rel:
                    out[str(prim.GetPath()) + "|" + name] = "rel:" + str(rel.GetTargets()[0])
                else:
                    out[str(prim.GetPath()) + "|" + name] = repr(prim.GetAttribute(name).Get())
        print(json.dumps(out))
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    import json

    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert len(expected) > 40
    for (p, n), v in expected.items():
        assert got[f"{p}|{n}"] == v, (p, n)
    del reg


def _sample_value(tn, allowed):
    from pxr import Gf, Sdf, Vt

    if allowed:
        return allowed[-1]
    t = str(tn)
    table = {
        "string": "hello", "int": 7, "double": 2.5, "float": 1.25, "bool": True, "token": "x",
        "point3f": Gf.Vec3f(1, 2, 3), "float3": Gf.Vec3f(4, 5, 6), "vector3f": Gf.Vec3f(1, 0, 0),
        "int3": Gf.Vec3i(3, 4, 5), "int2": Gf.Vec2i(640, 480), "asset": Sdf.AssetPath("./v.mp4"),
        "asset[]": Sdf.AssetPathArray([Sdf.AssetPath("./a.png"), Sdf.AssetPath("./b.png")]),
        "int[]": Vt.IntArray([1, 2, 3]), "float[]": Vt.FloatArray([0.5, 1.5]),
        "token[]": Vt.TokenArray(["damping", "ground"]),
    }
    return table[t]
