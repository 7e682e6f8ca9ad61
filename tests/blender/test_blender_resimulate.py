"""The artist's path of issue 27 in Blender (pip bpy 5.0.1) against the real CLI: init with the
panel's settings on a 20 fps capture, hints from the viewport (the 3D cursor, selected points, a
timeline marker) through extract onto the stage and back, a short fit, the twin imported at the
stage's fps with the splats' own colours, a headless render, and a resimulation driven by an
animated Empty, imported beside the fitted twin.

One fitted stage per session (conftest's `twin`: init + extract + fit, about half a minute on a
free core); each test imports it afresh into an empty Blender file.
"""

from __future__ import annotations

import json
import shutil
import subprocess

import bpy
import numpy as np
import pytest
from conftest import STAGE_TO_BLENDER, TWIN_CONTACT, TWIN_FPS, clean_env
from mathutils import Matrix, Vector
from pxr import Usd, UsdGeom

Y_UP_TO_Z_UP = np.array(STAGE_TO_BLENDER, float)    # stage -> Blender
CONTACT_STAGE = TWIN_CONTACT
DRAG_BLENDER = (0.06, 0.0, 0.04)          # the Empty's move in Blender (stage: +x 6 cm, up 4 cm)
FPS = TWIN_FPS


def blender_point(p_stage) -> Vector:
    return Vector(Y_UP_TO_Z_UP @ np.asarray(p_stage, float))


def stage_points(path, time=None) -> np.ndarray:
    st = Usd.Stage.Open(str(path))
    attr = UsdGeom.Points(st.GetPrimAtPath("/World/Object/SimParticles")).GetPointsAttr()
    return np.asarray(attr.Get(Usd.TimeCode.Default() if time is None else time), float)


def contact_sets(addon, path) -> dict:
    return {c["name"]: c for c in addon.stagedata.contact_sets(str(path))}


def import_twin(addon, stage, **kw):
    bpy.ops.wm.read_homefile(use_empty=True)
    s = bpy.context.scene.physinteract
    for k, v in kw.items():
        setattr(s, k, v)
    s.stage_path = str(stage)
    addon.import_result(bpy.context, str(stage), {"frames": {"size": [48, 36]}}, role="fit", stage=str(stage))
    return s


# ----------------------------------------------------------------------------- settings
def test_panel_passes_inits_settings(twin):
    """The capture's suggested settings reached init (the sample's mass and substeps depend on them)."""
    st = Usd.Stage.Open(str(twin["stage"]))
    scene = st.GetPrimAtPath("/World/PhysInteract")
    g = lambda n: scene.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
    assert tuple(g("gridResolution")) == (12, 12, 12)
    assert (g("youngsModulusMin"), g("youngsModulusMax")) == (1000.0, 20000.0)
    assert g("poissonRatioMax") == pytest.approx(0.4)
    assert st.GetPrimAtPath("/World/Object/SimParticles").GetAttribute("physinteract:density").Get() == 150.0


def test_suggested_settings_of_the_sample(addon, empty_scene):
    """The bundled sample's README: the demo's settings, passed to init."""
    from conftest import REPO

    s = empty_scene.physinteract
    s.capture_dir = str(REPO / "samples" / "foam_bar")
    s.stage_path = "/tmp/never-written/scene.usda"
    assert bpy.ops.physinteract.suggested() == {"FINISHED"}, s.error
    argv = addon.build_job(bpy.context, "init").steps[0].argv
    line = " ".join(argv)
    for flag in ("--grid 24", "--padding 0.3", "--youngs-range 1000,60000", "--max-poisson 0.4", "--density 150",
                 "--no-preload"):
        assert flag in line, line
    assert s.preload == "STRESS_FREE" and "--preload" not in argv


# ------------------------------------------------------------------------------ 20 fps
def test_a_20_fps_stage_plays_at_20_fps(addon, twin):
    # what a new user hit: Blender's own USD import sets the frame range, not the fps
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.wm.usd_import(filepath=str(twin["stage"]), set_frame_range=True) == {"FINISHED"}
    assert bpy.context.scene.render.fps == 24
    s = import_twin(addon, twin["stage"])
    scene = bpy.context.scene
    assert scene.render.fps / scene.render.fps_base == pytest.approx(FPS)
    assert (scene.frame_start, scene.frame_end) == (0, 5)
    # frame k shows time code k (the fitted motion, not resampled at 24 fps)
    pc = bpy.data.objects["SimParticles"]
    to_stage = np.array(pc.matrix_world.inverted())
    for k in (0, 3, 5):
        scene.frame_set(k)
        got = addon.viewport.evaluated_points(pc)["position"]
        got = got @ to_stage[:3, :3].T + to_stage[:3, 3]
        np.testing.assert_allclose(got, stage_points(twin["stage"], k), atol=1e-5)
    assert s.last_collection in bpy.data.collections


def test_fps_fields(addon):
    f = addon.stagedata.fps_fields
    assert f(20.0) == (20, 1.0) and f(24) == (24, 1.0)
    whole, base = f(29.97)
    assert whole == 30 and whole / base == pytest.approx(29.97)


# ------------------------------------------------------------------------------- hints
def test_cursor_hint_is_the_cameras_pixel(twin, addon):
    """The 3D cursor became the pixel where the stage's camera sees that point (the capture's own
    projection: continuous coordinates, the CLI's K,U,V being the pixel centre - 0.5)."""
    from blender_capture import project

    t = twin["transforms"]
    k, u, v = twin["hints"]["pixel"].split(",")
    uv = project(np.array([CONTACT_STAGE]), np.array(t["transform_matrix"]), t["fl_x"], t["fl_y"], t["cx"], t["cy"])[0]
    assert int(k) == 2
    assert (float(u), float(v)) == pytest.approx((uv[0] - 0.5, uv[1] - 0.5), abs=0.02)
    # the video's camera, not whatever camera the artist renders with
    s = import_twin(addon, twin["stage"])
    scene = bpy.context.scene
    mine = bpy.data.objects.new("my camera", bpy.data.cameras.new("my camera"))
    scene.collection.objects.link(mine)
    mine.location = (1.0, -1.0, 0.5)
    scene.camera = mine
    scene.cursor.location = blender_point(CONTACT_STAGE)
    scene.frame_set(4)
    assert bpy.ops.physinteract.hint(action="CONTACT_CURSOR") == {"FINISHED"}, s.error
    k, u, v = s.hint_contact_pixel.split(",")
    assert int(k) == 4 and (float(u), float(v)) == pytest.approx((uv[0] - 0.5, uv[1] - 0.5), abs=0.02)
    scene.cursor.location = (5.0, 5.0, 5.0)
    with pytest.raises(RuntimeError, match="outside the video's frame|behind the camera"):
        bpy.ops.physinteract.hint(action="CONTACT_CURSOR")


def test_hints_round_trip_through_the_stage(twin, addon):
    stage = twin["stage"]
    sets = contact_sets(addon, stage)
    fixed = [c for c in sets.values() if c["type"] == "fixed"]
    hand = [c for c in sets.values() if c["type"] != "fixed"]
    assert len(hand) == 1 and hand[0]["type"] == "pointAdherent" and hand[0]["source"] == "user"
    assert len(fixed) == 1 and fixed[0]["source"] == "user"
    assert set(fixed[0]["indices"]) <= set(twin["hints"]["support_idx"].tolist())
    assert len(fixed[0]["indices"]) >= 0.8 * len(twin["hints"]["support_idx"])
    # the contact is near where the cursor was
    rest = twin["rest"]
    centroid = rest[hand[0]["indices"]].mean(0)
    assert np.linalg.norm(centroid - np.array(CONTACT_STAGE)) < 0.05
    if "--grasp-frame" in twin["hints"]["note"]:
        pytest.skip(f"this CLI's extract has no --grasp-frame: {twin['hints']['note']}")
    assert hand[0]["grasp"] == 1                      # the 'grasp' marker

    # shown back after an import: Empties at the contacts, markers, the panel's lines
    s = import_twin(addon, stage)
    coll = bpy.data.collections[s.last_collection]
    empties = {o.name: o for o in coll.all_objects if o.type == "EMPTY" and o.get("physinteract_owned") == "contact"}
    name = hand[0]["name"]
    e = empties[f"contact: {name}"]
    bpy.context.view_layer.update()
    assert e["physinteract_source"] == "user" and e["physinteract_grasp"] == 1
    assert np.allclose(np.array(e.matrix_world.translation), Y_UP_TO_Z_UP @ np.array(hand[0]["point"]), atol=1e-5)
    assert f"support: {fixed[0]['name']}" in empties
    markers = {m.name: m.frame for m in bpy.context.scene.timeline_markers}
    assert markers[f"PI {name} grasp"] == 1
    shown = json.loads(s.contacts_json)
    assert any("your hint" in addon.viewport.describe_contact(c) for c in shown)


def test_extract_argv_carries_every_hint(addon, empty_scene, tmp_path, cli):
    s = empty_scene.physinteract
    s.stage_path = str(tmp_path / "scene.usda")
    s.hint_type = "surfaceNonAdherent"
    s.hint_contact_particles = "4,5,6"
    s.hint_contact_pixel = "1,10.00,12.00"
    s.hint_support_particles = "1,2"
    s.hint_support_pixels = "0,3.5,4.5;2,7,8"
    s.hint_grasp_radius = 0.05
    empty_scene.timeline_markers.new("Grasp", frame=3)
    empty_scene.timeline_markers.new("release", frame=9)
    empty_scene.timeline_markers.new("PI hand grasp", frame=0)   # shown back: not a hint
    notes = []
    argv = addon.extract_argv(bpy.context, [cli], str(tmp_path / "scene.usda"), notes)
    line = " ".join(argv[1:])
    assert "--type surfaceNonAdherent" in line and "--hint-particles 4,5,6" in line
    assert "--hint-pixel" not in line and any("particles win" in n for n in notes)
    assert "--support-particles 1,2" in line
    assert "--support-pixel 0,3.5,4.5 --support-pixel 2,7,8" in line and "--grasp-radius 0.05" in line
    if addon.clicaps.has([cli], "extract", "--grasp-frame"):
        assert "--grasp-frame 3" in line and "--release-frame 9" in line
    else:
        assert any("no --grasp-frame" in n for n in notes)


# ------------------------------------------------------------------------------- the look
def test_splats_come_in_with_their_colours_and_sizes(twin, addon):
    import_twin(addon, twin["stage"])
    bpy.context.scene.frame_set(0)
    spl = bpy.data.objects["Splats"]
    st = Usd.Stage.Open(str(twin["stage"]))
    prim = st.GetPrimAtPath("/World/Object/Splats")
    n = len(prim.GetAttribute("positions").Get(0))
    ev = addon.viewport.evaluated_points(spl)
    assert len(ev["position"]) == n
    srgb = np.asarray(prim.GetAttribute("primvars:displayColor").Get(), float)
    np.testing.assert_allclose(ev["color"], addon.stagedata.srgb_to_linear(srgb), atol=1e-5)
    scales = np.asarray(prim.GetAttribute("scales").Get(0), float)
    np.testing.assert_allclose(ev["radius"], addon.stagedata.splat_radius(scales), rtol=1e-4)
    assert spl.data.materials[0].name == "PhysInteract splat colour"
    # the splats follow the fitted motion
    scene = bpy.context.scene
    sim = bpy.data.objects["SimParticles"]
    np.testing.assert_allclose(np.array(spl.matrix_world), np.array(sim.matrix_world), atol=1e-6)
    to_stage = np.array(spl.matrix_world.inverted())
    scene.frame_set(5)
    got = addon.viewport.evaluated_points(spl)["position"] @ to_stage[:3, :3].T + to_stage[:3, 3]
    np.testing.assert_allclose(got, np.asarray(prim.GetAttribute("positions").Get(5)), atol=1e-5)
    # the Size slider scales every radius
    scene.physinteract.splat_size = 2.0
    np.testing.assert_allclose(addon.viewport.evaluated_points(spl)["radius"],
                               2.0 * addon.stagedata.splat_radius(np.asarray(prim.GetAttribute("scales").Get(5))),
                               rtol=1e-4)


def test_headless_render_shows_the_objects_colours(twin, addon, tmp_path):
    """Cycles from the stage's camera: not blank, and the object's own colour (the capture's
    Gaussians are (0.8, 0.3, 0.2) +- noise in sRGB)."""
    import_twin(addon, twin["stage"])
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 8
    scene.cycles.device = "CPU"
    scene.view_settings.view_transform = "Standard"
    scene.render.resolution_percentage = 200
    scene.render.filepath = str(tmp_path / "twin.png")
    scene.frame_set(3)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(tmp_path / "twin.png"))
    w, h = img.size
    px = np.array(img.pixels[:], np.float32).reshape(h, w, img.channels)[..., :3]
    lit = px.max(axis=2) > 0.15
    assert lit.mean() > 0.05, f"blank render: {lit.mean():.3f} of the pixels lit"
    r, g, b = np.median(px[lit], axis=0)
    assert r > g > b and r > 0.5, (r, g, b)
    assert (r, g, b) == pytest.approx((0.8, 0.3, 0.2), abs=0.12)


def test_colour_by_residual_when_the_stage_has_one(twin, addon, project_python, tmp_path):
    """`report` writes primvars:physinteract:residual on SimParticles: the cloud is coloured by it
    (authored here with usd-core into a copy of the stage until the report verb exists)."""
    copy = tmp_path / "copy"
    shutil.copytree(twin["stage"].parent, copy)
    script = ("import sys, numpy as np\nimport physinteract_usd\nfrom pxr import Usd, Sdf, UsdGeom, Vt\n"
              "st = Usd.Stage.Open(sys.argv[1])\n"
              "st.SetEditTarget(Usd.EditTarget(Sdf.Layer.FindOrOpen(sys.argv[2])))\n"
              "p = st.GetPrimAtPath('/World/Object/SimParticles')\n"
              "n = len(UsdGeom.Points(p).GetPointsAttr().Get(0))\n"
              "UsdGeom.PrimvarsAPI(p).CreatePrimvar('physinteract:residual', Sdf.ValueTypeNames.FloatArray, "
              "UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(np.linspace(0, 1, n).astype(np.float32)))\n"
              "Sdf.Layer.FindOrOpen(sys.argv[2]).Save()\n")
    proc = subprocess.run([project_python, "-c", script, str(copy / "scene.usda"), str(copy / "scene.fit.usdc")],
                          capture_output=True, text=True, env=clean_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    s = import_twin(addon, copy / "scene.usda", colour_by="RESIDUAL")
    pc = bpy.data.objects["SimParticles"]
    assert "physinteract:residual" in pc.data.attributes
    assert pc.data.materials[0].name == "PhysInteract residual" and s.look_note == ""
    s.colour_by = "STIFFNESS"
    assert pc.data.materials[0].name == "PhysInteract Young's modulus"
    # without the primvar: one line, and the stiffness colours
    s = import_twin(addon, twin["stage"], colour_by="RESIDUAL")
    assert "no per-particle residual" in s.look_note
    assert bpy.data.objects["SimParticles"].data.materials[0].name == "PhysInteract Young's modulus"


# -------------------------------------------------------------------------- resimulation
def animate_empty(scene, name="Drag", size=0.04):
    e = bpy.data.objects.new(name, None)
    e.empty_display_type = "SPHERE"
    e.empty_display_size = size
    scene.collection.objects.link(e)
    e.location = blender_point(CONTACT_STAGE)
    e.keyframe_insert("location", frame=0)
    e.location = e.location + Vector(DRAG_BLENDER)
    e.keyframe_insert("location", frame=5)
    return e


def test_an_empty_becomes_a_spec_and_a_resimulation_beside_the_fit(twin, addon):
    stage = twin["stage"]
    s = import_twin(addon, stage)
    scene = bpy.context.scene
    fitted_coll = s.last_collection
    empty = animate_empty(scene)
    s.resim_empty = empty
    s.resim_kind = "drag"
    scene.frame_set(2)
    assert bpy.ops.physinteract.run(steps="simulate") == {"FINISHED"}, s.error
    assert scene.frame_current == 2                               # sampling the Empty restored it

    # the spec: the Empty's motion in the stage's frame (Y up), frames 0..5
    paths = addon.sim_paths(str(stage), "Drag")
    sp = json.loads(open(paths["spec"]).read())
    c = sp["contacts"][0]
    assert sp["frames"] == 6 and sp["keep_supports"] is True and c["type"] == "pointAdherent"
    assert c["grasp_frame"] == 0 and c["release_frame"] is None
    assert c["select"]["centre"] == pytest.approx(list(CONTACT_STAGE), abs=1e-6)
    assert c["select"]["radius"] == pytest.approx(0.04)
    traj = np.array(c["trajectory"])
    d_stage = Y_UP_TO_Z_UP.T @ np.array(DRAG_BLENDER)              # (0.06, 0.04, 0)
    np.testing.assert_allclose(traj[-1] - traj[0], d_stage, atol=1e-6)
    held = addon.spec.held_particles(sp, twin["rest"])
    np.testing.assert_allclose(traj[0], twin["rest"][held].mean(0), atol=1e-6)

    # imported beside the fitted twin, which is hidden
    sim_coll = bpy.data.collections[s.last_sim_collection]
    assert fitted_coll in bpy.data.collections and sim_coll.name != fitted_coll
    assert bpy.data.collections[fitted_coll].hide_render
    sim = next(o for o in sim_coll.all_objects if o.name.startswith("SimParticles [Drag]"))
    fit = addon.viewport.particles_in(fitted_coll)
    assert any(o.get("physinteract_owned") == "splats" for o in sim_coll.all_objects)

    def at(obj, k):
        scene.frame_set(k)
        x = addon.viewport.evaluated_points(obj)["position"]
        m = np.array(obj.matrix_world.inverted())
        return x @ m[:3, :3].T + m[:3, 3]

    r0, r5, f0, f5 = at(sim, 0), at(sim, 5), at(fit, 0), at(fit, 5)
    moved = (r5 - r0)[held].mean(0)
    assert np.linalg.norm(moved - d_stage) < 0.25 * np.linalg.norm(d_stage), moved    # follows the Empty
    differs = np.linalg.norm((r5 - f5)[held].mean(0))
    assert differs > 0.5 * np.linalg.norm(d_stage), differs                           # not the fitted motion
    fixed = [c for c in contact_sets(addon, stage).values() if c["type"] == "fixed"][0]["indices"]
    assert np.abs(r5[fixed] - r0[fixed]).max() < 1e-3                                 # the support holds
    far = np.linalg.norm(twin["rest"] - np.array(CONTACT_STAGE), axis=1) > 0.15
    assert np.linalg.norm((r5 - f5)[far], axis=1).mean() < np.linalg.norm((r5 - f5)[held], axis=1).mean() / 3

    # again: the same simulation is replaced, not piled up
    assert bpy.ops.physinteract.run(steps="simulate") == {"FINISHED"}, s.error
    assert len([c for c in bpy.data.collections if c.get("physinteract_role") == "sim"]) == 1


def test_spec_kinds_and_one_line_errors(addon):
    spec = addon.spec
    pos = np.array([[0.1, 0.15, 0.0]] * 3 + [[0.12, 0.16, 0.0]] * 3)
    poke = spec.build_spec("poke", pos, radius=0.02, name="my poke!")
    assert poke["name"] == "my_poke" and poke["contacts"][0]["type"] == "pointNonAdherent"
    assert poke["contacts"][0]["trajectory"] == pos.round(6).tolist()
    push = spec.build_spec("push", pos, normal=(0, 0, 2))
    assert push["contacts"][0]["normal"] == [0, 0, 1.0] and push["contacts"][0]["type"] == "surfaceNonAdherent"
    rest = np.array([[0.1, 0.15, 0.0], [0.11, 0.15, 0.0], [0.0, 0.0, 0.0]])
    drag = spec.build_spec("drag", pos, grasp=2, release=5, indices=[0, 1], rest=rest)
    traj = np.array(drag["contacts"][0]["trajectory"])
    np.testing.assert_allclose(traj[:3], [[0.105, 0.15, 0.0]] * 3)          # still until the grasp
    np.testing.assert_allclose(traj[3], [0.125, 0.16, 0.0])
    assert drag["contacts"][0]["release_frame"] == 5
    for kwargs, msg in (({"kind": "drag", "rest": rest, "radius": 0.001, "positions": pos + 1}, "no particle within"),
                        ({"kind": "drag", "rest": rest, "radius": 0.1, "positions": np.zeros((4, 3))}, "does not move"),
                        ({"kind": "poke", "positions": pos, "grasp": 5}, "grasp frame"),
                        ({"kind": "poke", "positions": pos, "radius": 0.0}, "radius"),
                        ({"kind": "drag", "positions": pos, "rest": rest, "indices": [7]}, "indices must lie"),
                        ({"kind": "wiggle", "positions": pos}, "kind must be")):
        with pytest.raises(spec.SpecError, match=msg):
            spec.build_spec(**kwargs)


def test_resimulate_without_an_empty_says_so(addon, twin):
    s = import_twin(addon, twin["stage"])
    with pytest.raises(RuntimeError, match="pick the Empty"):
        bpy.ops.physinteract.run(steps="simulate")
    assert s.error.startswith("pick the Empty")
    bpy.context.scene.cursor.location = (0.1, 0.0, 0.15)
    assert bpy.ops.physinteract.add_empty() == {"FINISHED"}
    e = s.resim_empty
    assert e.type == "EMPTY" and e.empty_display_size == pytest.approx(0.03)
    assert tuple(e.location) == pytest.approx((0.1, 0.0, 0.15))
    with pytest.raises(RuntimeError, match="does not move"):       # not keyframed yet
        bpy.ops.physinteract.run(steps="simulate")


def test_selected_points_and_a_push_become_specs(addon, twin):
    """Held points picked in Edit Mode; a surface push's normal is the Empty's +Z in the stage's
    frame (the spec is written when the job is planned, before anything runs)."""
    s = import_twin(addon, twin["stage"])
    scene = bpy.context.scene
    s.resim_empty = animate_empty(scene, "Pick")
    pc = bpy.data.objects["SimParticles"]
    picked = [3, 5, 8]
    sel = pc.data.attributes.get(".selection") or pc.data.attributes.new(".selection", "BOOLEAN", "POINT")
    mask = np.zeros(len(pc.data.points), bool)
    mask[picked] = True
    sel.data.foreach_set("value", mask)
    s.resim_contact = "SELECTION"
    s.resim_release = "LAST_KEY"
    job = addon.build_job(bpy.context, "simulate")
    assert [st.label for st in job.steps] == ["simulate", "import"]
    sp = json.loads(open(addon.sim_paths(str(twin["stage"]), "Pick")["spec"]).read())
    c = sp["contacts"][0]
    assert c["select"] == {"indices": picked} and c["release_frame"] == 5
    np.testing.assert_allclose(c["trajectory"][0], twin["rest"][picked].mean(0), atol=1e-6)

    s.resim_kind = "push"
    s.resim_empty.rotation_euler = (np.pi / 2, 0.0, 0.0)        # Blender +Z turned to -Y: stage +Z
    s.resim_name = "push it"
    job = addon.build_job(bpy.context, "simulate")
    sp = json.loads(open(addon.sim_paths(str(twin["stage"]), "push_it")["spec"]).read())
    c = sp["contacts"][0]
    assert c["type"] == "surfaceNonAdherent" and c["friction"] == 0.5
    np.testing.assert_allclose(c["normal"], [0.0, 0.0, 1.0], atol=1e-6)
    assert job.steps[0].argv[-2:] == ["--name", "push_it"]
    # a spec file the add-on did not write is left alone
    path = addon.sim_paths(str(twin["stage"]), "mine")["spec"]
    open(path, "w").write('{"contacts": []}')
    s.resim_name = "mine"
    with pytest.raises(RuntimeError, match="was not written by the add-on"):
        bpy.ops.physinteract.run(steps="simulate")
    assert open(path).read() == '{"contacts": []}'


def test_stage_matrix_matches_the_imports_axes(addon, twin):
    import_twin(addon, twin["stage"])
    pc = bpy.data.objects["SimParticles"]
    np.testing.assert_allclose(np.array(addon.viewport.stage_matrix(pc)),
                               np.array(addon.viewport.stage_matrix(None)), atol=1e-6)
    # moving the imported twin moves the stage frame with it
    pc.parent.matrix_world = Matrix.Translation((1.0, 2.0, 3.0)) @ pc.parent.matrix_world
    bpy.context.view_layer.update()
    p = addon.viewport.stage_matrix(pc) @ (blender_point(CONTACT_STAGE) + Vector((1.0, 2.0, 3.0)))
    assert tuple(p) == pytest.approx(CONTACT_STAGE, abs=1e-6)


# ------------------------------------------------------------------------- report
def test_report_curve(addon, twin, cli, tmp_path):
    copy = tmp_path / "copy"                 # `report` writes residual primvars into the stage
    shutil.copytree(twin["stage"].parent.parent, copy)   # with the capture: the stage's paths are relative
    stage = copy / "out" / "scene.usda"
    s = import_twin(addon, stage, colour_by="RESIDUAL")
    assert bpy.ops.physinteract.run(steps="report") == {"FINISHED"}, s.error
    rep = json.loads(s.report_json)
    frames = [f for f in rep["frames"] if f.get("psnr") is not None]
    assert len(frames) >= 5 and rep["psnr"] > 5
    if not addon.clicaps.has([cli], "report"):
        assert rep["source"] == "stage" and "no `report` verb" in s.note
    else:   # the CLI's report wrote the residual: the stage was imported again, coloured by it
        pc = addon.viewport.particles_in(s.last_collection)
        assert "physinteract:residual" in pc.data.attributes
        assert pc.data.materials[0].name == "PhysInteract residual" and s.look_note == ""
    # the curve on the timeline: 'Frame PSNR' keyed per frame
    scene = bpy.context.scene
    for f in frames[:3]:
        scene.frame_set(f["frame"])
        assert s.frame_psnr == pytest.approx(f["psnr"], rel=1e-5)
    log = []
    from test_blender_addon import FakeLayout

    bpy.types.PHYSINTERACT_PT_report.draw(type("P", (), {"layout": FakeLayout(log)})(), bpy.context)
    labels = [e[1] for e in log if e[0] == "label"]
    assert any(t.startswith("PSNR ") for t in labels), labels
