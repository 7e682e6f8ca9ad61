"""What Blender's own USD importer (`bpy.ops.wm.usd_import`) makes of a physinteract-usd stage."""

from __future__ import annotations

import bpy
import numpy as np
import pytest
from mathutils import Matrix
from pxr import Usd, UsdGeom

PRIMVARS = ("physinteract:youngsModulus", "physinteract:poissonRatio", "physinteract:volume",
            "physinteract:isSurface", "displayColor")
Y_UP_TO_Z_UP = Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))


def usd_import(path, **kw):
    before = set(bpy.data.objects)
    assert bpy.ops.wm.usd_import(filepath=str(path), **kw) == {"FINISHED"}
    return {o.name: o for o in bpy.data.objects if o not in before}


def attr_array(data, name, n, width=1):
    a = data.attributes[name]
    out = np.empty(n * width, np.float32 if a.data_type.startswith("FLOAT") else np.int32)
    key = {"FLOAT_VECTOR": "vector", "FLOAT_COLOR": "color"}.get(a.data_type, "value")
    if a.data_type == "FLOAT_COLOR":
        out = np.empty(n * 4, np.float32)
    a.data.foreach_get(key, out)
    return out.reshape(n, -1) if out.size != n else out


def world_points(obj, n):
    co = attr_array(obj.data, "position", n, 3)
    m = np.array(obj.matrix_world)
    return co @ m[:3, :3].T + m[:3, 3]


@pytest.mark.parametrize("kind", ["gaussians", "mesh"])
def test_sim_particles_become_a_point_cloud_with_primvars(stages, empty_scene, kind):
    made = stages[kind]
    objs = usd_import(made.stage)
    pc = objs["SimParticles"]
    assert pc.type == "POINTCLOUD"
    n = made.prims["/World/Object/SimParticles"]["attributes"]["points"]["n"]
    assert len(pc.data.points) == n
    for name in PRIMVARS:
        assert name in pc.data.attributes, f"primvars:{name} was not imported"
        assert pc.data.attributes[name].domain == "POINT"
    stage = Usd.Stage.Open(str(made.stage))
    prim = stage.GetPrimAtPath("/World/Object/SimParticles")
    e_usd = np.array(prim.GetAttribute("primvars:physinteract:youngsModulus").Get(), np.float32)
    np.testing.assert_array_equal(attr_array(pc.data, "physinteract:youngsModulus", n), e_usd)
    surf = np.array(prim.GetAttribute("primvars:physinteract:isSurface").Get(), np.int32)
    np.testing.assert_array_equal(attr_array(pc.data, "physinteract:isSurface", n), surf)
    # positions: USD's Y-up metres, through Blender's Y-up -> Z-up conversion
    pts = np.array(UsdGeom.Points(prim).GetPointsAttr().Get(), np.float64)
    np.testing.assert_allclose(world_points(pc, n), pts @ np.array(Y_UP_TO_Z_UP)[:3, :3].T, atol=1e-6)
    width = float(UsdGeom.Points(prim).GetWidthsAttr().Get()[0])
    np.testing.assert_allclose(attr_array(pc.data, "radius", n), width / 2, rtol=1e-6)


@pytest.mark.parametrize("kind", ["gaussians", "mesh"])
def test_what_blender_imports_and_skips(stages, empty_scene, kind):
    """Imported: Xforms (as empties), Points, Mesh, Camera. Skipped: the Gaussian splats
    (ParticleField3DGaussianSplat is unknown to USD 25.08) and the PhysInteract prims (typed
    prims of a codeless schema Blender has no importer for; their data stays in the USD file)."""
    objs = usd_import(stages[kind].stage)
    types = {name: o.type for name, o in objs.items()}
    if kind == "mesh":
        assert types == {"World": "EMPTY", "Object": "EMPTY", "Mesh": "MESH", "SimParticles": "POINTCLOUD",
                         "Camera": "CAMERA"}
        mesh = objs["Mesh"]
        n = stages[kind].prims["/World/Object/Mesh"]["attributes"]["points"]["n"]
        assert len(mesh.data.vertices) == n
    else:
        # /World/Object has one importable child left, so Blender merges the Xform into it
        assert types == {"World": "EMPTY", "SimParticles": "POINTCLOUD", "Camera": "CAMERA"}
    assert not any(name.startswith(("Splats", "PhysInteract")) for name in objs)
    # plain (non-primvar) attributes such as physinteract:density are not imported anywhere
    pc = objs["SimParticles"]
    assert "physinteract:density" not in pc.data.attributes and "physinteract:density" not in pc.keys()


def test_frame_range_and_fps(stages, empty_scene):
    made = stages["gaussians"]
    usd_import(made.stage)
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (made.described["start"], made.described["end"])
    assert scene.render.fps / scene.render.fps_base == pytest.approx(made.described["fps"])


def test_camera_matches_transforms_json(stages, empty_scene):
    """Intrinsics (principal point off centre) and pose survive into Blender's camera."""
    made = stages["mesh"]
    t = made.transforms
    cam = usd_import(made.stage)["Camera"]
    c = cam.data
    assert c.type == "PERSP" and c.sensor_fit == "HORIZONTAL"
    w, h = t["w"], t["h"]
    assert c.sensor_height / c.sensor_width == pytest.approx(h / w)
    fx = c.lens / c.sensor_width * w
    fy = c.lens / c.sensor_height * h
    # Blender's shifts are fractions of the larger film side (here the width), y up
    cx = w / 2 - c.shift_x * w
    cy = h / 2 + c.shift_y * w
    assert (fx, fy, cx, cy) == pytest.approx((t["fl_x"], t["fl_y"], t["cx"], t["cy"]), abs=1e-3)
    np.testing.assert_allclose(np.array(cam.matrix_world), np.array(Y_UP_TO_Z_UP) @ np.array(t["transform_matrix"]),
                               atol=1e-5)


def test_time_sampled_points_import_as_animation(stages, empty_scene):
    """Points time-sampled in scene.fit.usdc (what `fit` writes) play back as an animated point
    cloud: a Mesh Sequence Cache modifier that reads the USD file each frame."""
    made = stages["animated"]
    assert made.prims["/World/Object/SimParticles"]["attributes"]["points"]["samples"] == [0.0, 1.0, 2.0]
    pc = usd_import(made.stage)["SimParticles"]
    mods = [m for m in pc.modifiers if m.type == "MESH_SEQUENCE_CACHE"]
    assert len(mods) == 1 and mods[0].object_path == "/World/Object/SimParticles"
    scene = bpy.context.scene
    n = made.prims["/World/Object/SimParticles"]["attributes"]["points"]["n"]
    scene.frame_set(0)
    ev = pc.evaluated_get(bpy.context.evaluated_depsgraph_get())
    x0 = world_points(ev, n)
    for k in (1, 2):
        scene.frame_set(k)
        ev = pc.evaluated_get(bpy.context.evaluated_depsgraph_get())
        xk = world_points(ev, n)
        np.testing.assert_allclose(xk - x0, np.tile([0.01 * k, 0.0, 0.0], (n, 1)), atol=1e-6)
        assert "physinteract:youngsModulus" in ev.data.attributes


def test_camera_film_back_is_36_mm_in_blender(stages, empty_scene):
    c = usd_import(stages["gaussians"].stage)["Camera"].data
    assert c.sensor_width == pytest.approx(36.0, rel=1e-4)
