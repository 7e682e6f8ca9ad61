"""PhysInteract USD for Blender: "Fit material from video" in the 3D viewport's sidebar.

A thin client: it runs the `physinteract-usd` command line (init, extract, fit, export, simulate,
and report / diagnose / effects / versions when the installed CLI has them) as subprocesses,
never blocking the interface (a modal operator polls them on a timer), and imports the resulting
USD with Blender's own importer as animated point clouds. No physics here.

Modules: `runner` (subprocess jobs, progress, cancel; no bpy), `clicaps` (what the CLI offers),
`spec` (the `simulate` interaction spec), `stagedata` (what Blender's pxr reads from a stage; the
splats as points), `viewport` (the Empty, selections, the cursor, markers, materials).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty


def _ensure_pxr() -> None:
    """pip bpy keeps Blender's USD Python modules in its own site-packages (a Blender binary has
    them on sys.path already)."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        sys.path.append(os.path.join(bpy.utils.resource_path("LOCAL"), "python", "lib",
                                     f"python{sys.version_info.major}.{sys.version_info.minor}", "site-packages"))


_ensure_pxr()

from . import clicaps, runner, spec, stagedata, viewport  # noqa: E402
from .viewport import PRIMVAR_E, youngs_material  # noqa: E402,F401  (youngs_material: public API)

bl_info = {  # legacy add-on install; as an extension, blender_manifest.toml is used instead
    "name": "PhysInteract USD",
    "author": "physinteract-usd",
    "version": (0, 2, 0),
    "blender": (4, 2, 0),
    "location": "3D Viewport > Sidebar > PhysInteract",
    "description": "Fit a soft object's material from a video of a hand handling it, import the "
                   "digital twin as an animated point cloud, resimulate it under a new interaction",
    "category": "Physics",
}

ADDON_ID = __package__ or __name__
EFFECTS = ("damping", "plasticity", "ground", "viscoelasticity")
SPEC_MARK = "physinteract-usd-blender"

_JOB: runner.Job | None = None


class UserError(Exception):
    """A setting the user must fix: shown as one line, nothing run."""


# ------------------------------------------------------------------------------- preferences
def _cli_changed(self, context):
    clicaps.clear()


class PHYSINTERACT_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    cli_path: StringProperty(
        name="physinteract-usd", subtype="FILE_PATH", default="", update=_cli_changed,
        description="The physinteract-usd executable (or a command line such as "
                    "'/path/to/python -m physinteract_usd'). Empty: found on PATH")

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "cli_path")
        try:
            col.label(text="Using: " + " ".join(runner.resolve_cli(self.cli_path)))
        except runner.CliNotFound as exc:
            col.label(text=str(exc), icon="ERROR")


def cli_setting(context) -> str:
    """The preference, or the PHYSINTERACT_CLI environment variable, or empty (PATH)."""
    addon = context.preferences.addons.get(ADDON_ID)
    pref = addon.preferences.cli_path if addon is not None and addon.preferences is not None else ""
    return pref or os.environ.get("PHYSINTERACT_CLI", "")


# ---------------------------------------------------------------------------------- settings
def _recolour(self, context):
    obj = viewport.particles_in(self.last_collection)
    if obj is not None:
        self.look_note = viewport.colour_particles(obj, self.colour_by, _e_range(self))
    sim = viewport.particles_in(self.last_sim_collection)
    if sim is not None:
        viewport.colour_particles(sim, self.colour_by, _e_range(self))


def _resize(self, context):
    for coll_name in (self.last_collection, self.last_sim_collection):
        coll = bpy.data.collections.get(coll_name or "")
        for o in coll.all_objects if coll is not None else []:
            if o.get(viewport.OWNED) == "splats":
                viewport.set_look_size(o, self.splat_size)


def _rerender(self, context):
    for coll_name in (self.last_collection, self.last_sim_collection):
        obj = viewport.particles_in(coll_name)
        if obj is not None:
            obj.hide_render = not self.render_particles and _has_splats(coll_name)


def _has_splats(coll_name) -> bool:
    coll = bpy.data.collections.get(coll_name or "")
    return coll is not None and any(o.get(viewport.OWNED) == "splats" for o in coll.all_objects)


def _is_empty(self, obj):
    return obj.type == "EMPTY"


class PHYSINTERACT_PG_settings(bpy.types.PropertyGroup):
    capture_dir: StringProperty(name="Capture", subtype="DIR_PATH",
                                description="Capture folder: object file, frames/ or video.mp4, "
                                            "transforms.json, optional masks/")
    video: StringProperty(name="Video", subtype="FILE_PATH",
                          description="Video file or folder of frames (empty: the capture folder's)")
    camera: StringProperty(name="Camera", subtype="FILE_PATH",
                           description="nerfstudio transforms.json (empty: the capture folder's)")
    masks: StringProperty(name="Masks", subtype="DIR_PATH",
                          description="Folder of object silhouettes, one per frame (optional)")
    masks_amodal: BoolProperty(name="Amodal masks", default=False,
                               description="The masks include the object behind the hand")
    object_source: EnumProperty(
        name="Object", default="CAPTURE",
        items=[("CAPTURE", "Capture file", "The capture folder's object file (object.ply, .obj, ...)"),
               ("SELECTED", "Selected mesh", "Export the active mesh object (world space, Y up) and "
                                             "use it as the object")])
    stage_path: StringProperty(name="Stage", subtype="FILE_PATH",
                               description="Root layer of the stage to write (.usda). Empty: "
                                           "scene.usda in the capture folder")
    export_path: StringProperty(name="Export", subtype="FILE_PATH",
                                description="Where `export` writes the simulation-ready asset. "
                                            "Empty: <stage>_twin.usdc beside the stage")
    grid: IntProperty(name="Grid", default=32, min=8, max=256,
                      description="MPM grid cells along the longest side of the domain")
    fps: FloatProperty(name="FPS", default=0.0, min=0.0,
                       description="Frame rate when neither transforms.json nor the video gives one "
                                   "(0: from the capture)")
    force: BoolProperty(name="Replace generated layers", default=False,
                        description="init --force: rewrite the generated layers of an existing stage "
                                    "(your root layer is kept)")
    discard_fits: BoolProperty(name="Discard fit versions", default=False,
                               description="init --force --discard-fits: a fitted stage's fit versions go too "
                                           "(without it the CLI refuses to re-init a fitted stage)")
    accept_slow: BoolProperty(name="Accept slow fits", default=False,
                              description="init --yes: go on when a frame needs so many substeps that fits "
                                          "would take hours")
    replace_import: BoolProperty(name="Replace previous import", default=True,
                                 description="Remove the objects of the previous import first")
    # init's settings (0: the CLI's default)
    padding: FloatProperty(name="Padding", default=0.0, min=0.0, soft_max=2.0,
                           description="init --padding: domain margin around the object, as a fraction "
                                       "of its extent (0: the CLI's default, 0.5)")
    youngs_min: FloatProperty(name="E min (Pa)", default=0.0, min=0.0,
                              description="init --youngs-range MIN (Pa; 0 with E max 0: the CLI's 1e3)")
    youngs_max: FloatProperty(name="E max (Pa)", default=0.0, min=0.0,
                              description="init --youngs-range MAX (Pa; sets the substep; 0: the CLI's 1e6)")
    poisson: FloatProperty(name="Poisson", default=0.0, min=0.0, max=0.49,
                           description="init --poisson: starting Poisson ratio (0: the CLI's 0.3)")
    max_poisson: FloatProperty(name="Max Poisson", default=0.0, min=0.0, max=0.499,
                               description="init --max-poisson: the largest Poisson ratio the fit may use "
                                           "(0: the CLI's 0.45)")
    density: FloatProperty(name="Density", default=0.0, min=0.0,
                           description="init --density in kg/m^3 (0: the CLI's 1000)")
    model: EnumProperty(name="Model", default="DEFAULT",
                        items=[("DEFAULT", "Default", "The CLI's default (fixed corotated)"),
                               ("fixedCorotated", "Fixed corotated", ""), ("neoHookean", "Neo-Hookean", "")])
    preload: EnumProperty(name="Scan", default="DEFAULT",
                          items=[("DEFAULT", "The fit decides", "init without --preload / --no-preload: the first fit "
                                  "decides by the frames whether the scan carries the object's weight"),
                                 ("PRELOAD", "Carries its weight", "init --preload: the scan shows the object at rest "
                                  "on its supports, already sagged"),
                                 ("STRESS_FREE", "Unloaded", "init --no-preload: scanned unloaded, it sags in the "
                                  "video")])
    fit_iterations: IntProperty(name="Iterations", default=0, min=0,
                                description="fit --iterations (0: the CLI's default)")
    sim_ready_path: StringProperty(name="Sim-ready", subtype="FILE_PATH",
                                   description="Where the Simulation-ready export writes (export --sim-ready "
                                               "--force): a TetMesh with the deformable-physics schemas. "
                                               "Empty: <export>_simready.usdc beside the export")
    sim_ready_summary: StringProperty(name="Sim-ready summary", default="",
                                      description="What the last Simulation-ready export wrote")
    # hints for extract
    hint_type: EnumProperty(
        name="Type", default="AUTO",
        items=[("AUTO", "Detect", "Let extract detect the interaction type"),
               ("pointAdherent", "Grasp / pull", "pointAdherent"),
               ("pointNonAdherent", "Poke", "pointNonAdherent"),
               ("surfaceNonAdherent", "Surface push", "surfaceNonAdherent")],
        description="extract --type")
    hint_contact_particles: StringProperty(name="Contact particles", default="",
                                           description="extract --hint-particles I,J,...")
    hint_contact_pixel: StringProperty(name="Contact pixel", default="",
                                       description="extract --hint-pixel K,U,V (frame, column, row)")
    hint_support_particles: StringProperty(name="Support particles", default="",
                                           description="extract --support-particles I,J,...")
    hint_support_pixels: StringProperty(name="Support pixels", default="",
                                        description="extract --support-pixel K,U,V, several separated by ';'")
    hint_grasp_radius: FloatProperty(name="Grasp radius", default=0.0, min=0.0, unit="LENGTH",
                                     description="extract --grasp-radius in metres (0: the CLI's default)")
    use_markers: BoolProperty(name="Grasp / release from markers", default=True,
                              description="Pass timeline markers named 'grasp' and 'release' as "
                                          "extract --grasp-frame / --release-frame")
    # resimulation
    resim_empty: PointerProperty(name="Empty", type=bpy.types.Object, poll=_is_empty,
                                 description="The Empty whose animation is the new interaction")
    resim_kind: EnumProperty(
        name="Kind", default="drag",
        items=[("drag", "Drag", "pointAdherent: the particles within the Empty's radius (or the selected "
                                "points) are held and follow the Empty"),
               ("poke", "Poke", "pointNonAdherent: a sphere of the Empty's radius pushes the object"),
               ("push", "Surface push", "surfaceNonAdherent: a plane through the Empty, normal its +Z")])
    resim_contact: EnumProperty(
        name="Held", default="RADIUS",
        items=[("RADIUS", "Within the Empty", "Particles within the Empty's display size at the grasp frame"),
               ("SELECTION", "Selected points", "The selected points of the imported SimParticles cloud")])
    resim_release: EnumProperty(
        name="Release", default="NEVER",
        items=[("NEVER", "Never", "Held to the end"),
               ("LAST_KEY", "At the last key", "Let go at the Empty's last keyframe")])
    resim_frames: IntProperty(name="Frames", default=0, min=0,
                              description="Frames to simulate (0: as many as the stage has)")
    resim_keep_supports: BoolProperty(name="Keep supports", default=True,
                                      description="Keep the fitted stage's supports (fixed contact sets)")
    resim_friction: FloatProperty(name="Friction", default=0.5, min=0.0, description="Surface push friction")
    resim_name: StringProperty(name="Name", default="",
                               description="The simulation's name (empty: the Empty's name)")
    # the look
    colour_by: EnumProperty(
        name="Colour by", default="STIFFNESS", update=_recolour,
        items=[("STIFFNESS", "Stiffness", "log10 of Young's modulus (blue soft, red stiff)"),
               ("CONFIDENCE", "Confidence", "The fit's confidence (red low, green high)"),
               ("RESIDUAL", "Residual", "The report's per-particle residual (bright: the model misses there)")])
    splat_look: BoolProperty(name="Splat colours", default=True,
                             description="Also import the Gaussian splats as a point cloud with their own "
                                         "colours and sizes")
    splat_size: FloatProperty(name="Splat size", default=1.0, min=0.0, soft_max=4.0, update=_resize,
                              description="Scale of the splat points' radius")
    render_particles: BoolProperty(name="Render particles", default=False, update=_rerender,
                                   description="Render the SimParticles cloud too (off: with the splats imported, "
                                               "renders show the splats' own colours only)")
    # state shown in the panel
    running: BoolProperty(default=False, options={"SKIP_SAVE"})
    status: StringProperty(default="", options={"SKIP_SAVE"})
    error: StringProperty(default="", options={"SKIP_SAVE"})
    note: StringProperty(default="", options={"SKIP_SAVE"})
    progress: FloatProperty(default=-1.0, options={"SKIP_SAVE"})
    look_note: StringProperty(default="")
    last_collection: StringProperty(default="")
    last_sim_collection: StringProperty(default="")
    info_json: StringProperty(default="")
    contacts_json: StringProperty(default="")
    report_json: StringProperty(default="")
    diagnose_json: StringProperty(default="")
    versions_json: StringProperty(default="")
    frame_psnr: FloatProperty(name="Frame PSNR", default=0.0,
                              description="The report's per-frame PSNR, keyed per frame (Graph Editor)")


def _e_range(settings):
    try:
        return ((json.loads(settings.info_json or "{}").get("simulation") or {}).get("youngs_range_pa"))
    except ValueError:
        return None


# ------------------------------------------------------------------------------------- paths
def _abs(path: str, what: str) -> str:
    if path.startswith("//") and not bpy.data.filepath:
        raise UserError(f"{what} '{path}' is relative to the .blend file: save it first or give an "
                        "absolute path")
    return os.path.normpath(bpy.path.abspath(path)) if path else ""


def resolved_paths(settings) -> dict:
    capture = _abs(settings.capture_dir, "capture folder")
    stage = _abs(settings.stage_path, "stage")
    if not stage:
        if not capture:
            raise UserError("set the capture folder (or the stage path)")
        stage = os.path.join(capture, "scene.usda")
    if not stage.lower().endswith((".usda", ".usd")):
        stage += ".usda"
    export = _abs(settings.export_path, "export path")
    if not export:
        export = str(Path(stage).with_name(Path(stage).stem + "_twin.usdc"))
    sim_ready = _abs(settings.sim_ready_path, "sim-ready path")
    if not sim_ready:
        sim_ready = str(Path(export).with_name(Path(export).stem + "_simready.usdc"))
    return {"capture": capture, "stage": stage, "export": export, "sim_ready": sim_ready,
            "video": _abs(settings.video, "video"), "camera": _abs(settings.camera, "camera"),
            "masks": _abs(settings.masks, "masks")}


def sim_paths(stage: str, name: str) -> dict:
    """What `simulate --name NAME` writes beside the stage, and where the add-on puts the spec."""
    p = Path(stage)
    return {"view": str(p.with_name(f"{p.stem}.sim.{name}.usda")),
            "layer": str(p.with_name(f"{p.stem}.sim.{name}.usdc")),
            "spec": str(p.with_name(f"{p.stem}.sim.{name}.json"))}


# ------------------------------------------------------------------------ the selected mesh
def export_selected_mesh(context, path: str) -> str:
    """The active mesh object, in world space, as an OBJ with Y up (the stage's axes)."""
    obj = context.active_object
    if obj is None or obj.type != "MESH":
        raise UserError("object source is 'Selected mesh' but the active object is not a mesh")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    selected = [o for o in context.view_layer.objects if o.select_get()]
    try:
        for o in selected:
            o.select_set(False)
        obj.select_set(True)
        bpy.ops.wm.obj_export(filepath=path, export_selected_objects=True, forward_axis="NEGATIVE_Z",
                              up_axis="Y", apply_modifiers=True, export_materials=False,
                              export_uv=False, export_normals=False, export_triangulated_mesh=True,
                              export_colors=True)
    finally:
        obj.select_set(False)
        for o in selected:
            o.select_set(True)
    if not os.path.exists(path):
        raise UserError(f"{path}: the OBJ export of '{obj.name}' failed")
    return path


# ---------------------------------------------------------------------------------- import
def import_result(context, path: str, info: dict | None = None, replace: bool = True,
                  role: str = "fit", stage: str | None = None) -> list:
    """Import a stage, exported asset (role "fit") or a resimulation's view stage (role "sim")
    with Blender's USD importer; returns the new objects.

    Time-sampled SimParticles become an animated POINTCLOUD (a Mesh Sequence Cache modifier
    reading the USD file), primvars become attributes; the camera comes along (role "fit"). Then:
    the scene's fps and frame range are the stage's; the particles get the material `colour_by`
    asks for; the Gaussian splats (skipped by Blender's USD) come in as a second, coloured point
    cloud (`stagedata.write_splat_points`); the stage's contact sets are shown as Empties and
    markers (role "fit"). A resimulation goes into its own collection beside the fitted twin
    (which is hidden, viewport and render, so the new motion is what plays)."""
    if not os.path.exists(path):
        raise RuntimeError(f"{path}: file not found")
    stagedata.reload_layers(path)   # what the CLI rewrote since the last import
    scene = context.scene
    settings = scene.physinteract
    notes = []
    if role == "fit" and replace and settings.last_collection:
        _remove_collection(settings.last_collection)
    if role == "sim":
        for c in list(bpy.data.collections):
            if c.get("physinteract_file") == os.path.abspath(path):
                _remove_collection(c.name)
    before = set(bpy.data.objects)
    colls_before = set(bpy.data.collections)
    result = bpy.ops.wm.usd_import(filepath=path, import_cameras=(role == "fit"), import_points=True,
                                   import_meshes=True, set_frame_range=True, create_collection=True)
    if "FINISHED" not in result:
        raise RuntimeError(f"{path}: Blender's USD import failed")
    new = [o for o in bpy.data.objects if o not in before]
    new_colls = [c for c in bpy.data.collections if c not in colls_before]
    coll = new_colls[0] if new_colls else scene.collection
    if new_colls:
        coll["physinteract_file"] = os.path.abspath(path)
        coll["physinteract_role"] = role
    if role == "fit":
        settings.last_collection = coll.name if new_colls else ""
        cams = [o for o in new if o.type == "CAMERA"]
        if cams:
            scene.camera = cams[0]
        if info:
            settings.info_json = json.dumps(info)
            size = (info.get("frames") or {}).get("size")
            if size:
                scene.render.resolution_x, scene.render.resolution_y = int(size[0]), int(size[1])
                scene.render.resolution_percentage = 100
    else:
        settings.last_sim_collection = coll.name if new_colls else ""
    # the stage's clock: Blender's USD import sets the frame range but leaves the scene at 24 fps
    tm = stagedata.timing(path)
    scene.render.fps, scene.render.fps_base = stagedata.fps_fields(tm["fps"])
    scene.frame_start, scene.frame_end = tm["start"], tm["end"]
    particles = [o for o in new if viewport.is_particles(o)]
    for o in particles:
        note = viewport.colour_particles(o, settings.colour_by, _e_range(settings))
        if note:
            notes.append(note)
        if role == "sim":
            o.name = f"SimParticles [{Path(path).stem.split('.sim.')[-1]}]"
    if settings.splat_look and particles:
        splats = _import_splat_look(context, path, coll, particles[0], settings.splat_size)
        new += splats
        if splats:  # renders show the splats' colours; the particles stay in the viewport
            for o in particles:
                o.hide_render = not settings.render_particles
    if role == "fit" and particles:
        contacts = stagedata.contact_sets(path)
        if not contacts and stage and os.path.exists(stage):
            contacts = stagedata.contact_sets(stage)
        settings.contacts_json = stagedata.dumps(contacts)
        new += viewport.show_contacts(scene, particles[0], contacts, coll)
    if role == "sim" and settings.last_collection in bpy.data.collections:
        fitted = bpy.data.collections[settings.last_collection]
        fitted.hide_render = True
        lc = _layer_collection(context.view_layer.layer_collection, fitted.name)
        if lc is not None:
            lc.hide_viewport = True
    settings.look_note = "; ".join(notes)
    return new


def _import_splat_look(context, path, coll, particles, size) -> list:
    """The splats as a second point cloud in `coll`, placed like the particles, coloured and sized."""
    out = stagedata.write_splat_points(path)
    if out is None:
        return []
    view_layer = context.view_layer
    active = view_layer.active_layer_collection
    lc = _layer_collection(view_layer.layer_collection, coll.name)
    before = set(bpy.data.objects)
    try:
        if lc is not None:
            view_layer.active_layer_collection = lc
        result = bpy.ops.wm.usd_import(filepath=str(out), import_cameras=False, import_points=True,
                                       set_frame_range=False, create_collection=False)
    finally:
        view_layer.active_layer_collection = active
    if "FINISHED" not in result:
        raise RuntimeError(f"{out}: Blender's USD import failed")
    new = [o for o in bpy.data.objects if o not in before]
    for o in new:
        if o.name not in coll.objects:
            for c in list(o.users_collection):
                c.objects.unlink(o)
            coll.objects.link(o)
        if o.type == "POINTCLOUD":
            o.name = "Splats" if "sim" not in coll.get("physinteract_role", "") else f"Splats [{coll.name}]"
            o[viewport.OWNED] = "splats"
            o.parent = particles.parent
            o.matrix_world = particles.matrix_world.copy()
            viewport.apply_splat_look(o, size)
    return new


def _layer_collection(root, name):
    if root.collection.name == name:
        return root
    for child in root.children:
        found = _layer_collection(child, name)
        if found is not None:
            return found
    return None


def _remove_collection(name: str) -> None:
    coll = bpy.data.collections.get(name)
    if coll is None:
        return
    caches = {m.cache_file for o in coll.all_objects for m in o.modifiers
              if m.type == "MESH_SEQUENCE_CACHE" and m.cache_file is not None}
    for o in list(coll.all_objects):
        bpy.data.objects.remove(o, do_unlink=True)
    for child in list(coll.children_recursive):
        bpy.data.collections.remove(child)
    bpy.data.collections.remove(coll)
    unused = [c for c in caches if c.users == 0]
    if unused:  # the import's cache files hold the USD layers open
        bpy.data.batch_remove(unused)


# ------------------------------------------------------------------------------ report data
def store_report(context, report: dict) -> None:
    """Keep the report for the panel, and key `frame_psnr` per frame (the error curve in the
    Graph Editor, on the timeline's frames)."""
    settings = context.scene.physinteract
    settings.report_json = json.dumps(report)
    scene = context.scene
    _clear_curve(scene)
    for f in report.get("frames") or []:
        if f.get("psnr") is None:
            continue
        settings.frame_psnr = float(f["psnr"])
        settings.keyframe_insert("frame_psnr", frame=int(f["frame"]))


def _store_versions(out: str) -> None:
    try:
        bpy.context.scene.physinteract.versions_json = json.dumps(parse_json(out))
    except ValueError:
        bpy.context.scene.physinteract.versions_json = ""   # an older `versions` without --json


def _reimport_for_residual(context, stage: str) -> None:
    """`report` writes the per-particle residual into the stage: when the imported stage's cloud
    lacks it, import the stage again so the residual can colour it."""
    s = context.scene.physinteract
    coll = bpy.data.collections.get(s.last_collection or "")
    obj = viewport.particles_in(s.last_collection)
    if coll is None or obj is None or coll.get("physinteract_file") != os.path.abspath(stage):
        return
    if viewport.PRIMVAR_RESIDUAL in obj.data.attributes or not stagedata.has_primvar(
            stage, stagedata.PARTICLES, viewport.PRIMVAR_RESIDUAL):
        return
    info = json.loads(s.info_json or "{}") or None
    import_result(context, stage, info, True, role="fit", stage=stage)


def _clear_curve(scene) -> None:
    ad = scene.animation_data
    if ad is None or ad.action is None:
        return
    try:
        from bpy_extras import anim_utils

        bag = anim_utils.animdata_get_channelbag_for_assigned_slot(ad)
        fc = bag.fcurves.find("physinteract.frame_psnr") if bag is not None else None
        if fc is not None:
            bag.fcurves.remove(fc)
    except (ImportError, AttributeError, RuntimeError):
        pass


def report_at(report: dict, frame: int) -> dict | None:
    return next((f for f in report.get("frames") or [] if f.get("frame") == frame), None)


# ------------------------------------------------------------------------------------- jobs
STEP_CHOICES = ("init", "extract", "fit", "export", "export_sim_ready", "import", "import_stage", "all",
                "simulate", "report", "diagnose")


def _parse_steps(steps: str) -> list[str]:
    names = [s.strip() for s in steps.split(",") if s.strip()]
    bad = [s for s in names if s not in STEP_CHOICES and not s.startswith(("effect:", "version:"))]
    if bad or not names:
        raise UserError(f"unknown step(s) {', '.join(bad) or '(none)'}: expected {', '.join(STEP_CHOICES)}, "
                        "effect:NAME or version:N")
    return names


def extract_argv(context, cli, stage, notes: list) -> list:
    """`extract` with the viewport's hints: the type, the contact (particles or a pixel), the
    supports, the grasp radius, and the 'grasp' / 'release' timeline markers when the CLI has
    --grasp-frame / --release-frame."""
    s = context.scene.physinteract
    argv = runner.verb_argv(cli, "extract", stage)
    if s.hint_type != "AUTO":
        argv += ["--type", s.hint_type]
    try:
        contact = viewport.parse_indices(s.hint_contact_particles)
        supports = viewport.parse_indices(s.hint_support_particles)
    except viewport.ViewportError as exc:
        raise UserError(f"hints: {exc}") from None
    if contact:
        argv += ["--hint-particles", viewport.compact_indices(contact)]
        if s.hint_contact_pixel.strip():
            notes.append("the contact particles win over the contact pixel")
    elif s.hint_contact_pixel.strip():
        argv += ["--hint-pixel", s.hint_contact_pixel.strip()]
    if supports:
        argv += ["--support-particles", viewport.compact_indices(supports)]
    for px in (p.strip() for p in s.hint_support_pixels.split(";")):
        if px:
            argv += ["--support-pixel", px]
    if s.hint_grasp_radius > 0:
        argv += ["--grasp-radius", f"{s.hint_grasp_radius:g}"]
    if s.use_markers:
        for name, flag in (("grasp", "--grasp-frame"), ("release", "--release-frame")):
            frame = viewport.marker_frame(context.scene, name)
            if frame is None:
                continue
            if clicaps.has(cli, "extract", flag):
                argv += [flag, str(int(frame))]
            else:
                notes.append(f"the '{name}' marker was not passed: this physinteract-usd's extract has no {flag}")
    return argv


def build_simulation(context, cli, stage: str) -> tuple[list, str]:
    """The resimulation: the interaction spec from the Empty (written beside the stage), the
    `simulate` step and the import of its view stage. Raises UserError before anything runs."""
    scene = context.scene
    s = scene.physinteract
    if not os.path.exists(stage):
        raise UserError(f"{stage}: the stage does not exist yet (run init and fit first)")
    empty = s.resim_empty or (context.active_object if context.active_object is not None
                              and context.active_object.type == "EMPTY" else None)
    if empty is None:
        raise UserError("pick the Empty whose animation is the new interaction (Resimulate > Empty)")
    particles = viewport.particles_in(s.last_collection)
    to_stage = viewport.stage_matrix(particles)
    try:
        tm = stagedata.timing(stage)
        n = s.resim_frames or (tm["end"] - tm["start"] + 1)
        sampled = viewport.sample_empty(scene, empty, n, to_stage)
        keys = viewport.keyframe_frames(empty)
        grasp = min(max(keys[0] if keys else 0, 0), n - 2)
        release = None
        if s.resim_release == "LAST_KEY" and keys and grasp < keys[-1] <= n:
            release = keys[-1]
        indices = None
        if s.resim_kind == "drag" and s.resim_contact == "SELECTION":
            obj = context.active_object if viewport.is_particles(context.active_object) else particles
            indices = viewport.selected_points(obj)
            if not indices:
                raise UserError("'Held: Selected points' but no point of the SimParticles cloud is selected")
        rest = stagedata.rest_points(stage) if s.resim_kind == "drag" else None
        name = spec.sim_name(s.resim_name or empty.name)
        sp = spec.build_spec(s.resim_kind, sampled["positions"], grasp=grasp, release=release,
                             radius=sampled["radius"], normal=sampled["axis"][grasp], indices=indices,
                             rest=rest, name=name, keep_supports=s.resim_keep_supports,
                             friction=s.resim_friction, source=SPEC_MARK)
    except (spec.SpecError, viewport.ViewportError, stagedata.StageError) as exc:
        raise UserError(f"resimulate: {exc}") from None
    paths = sim_paths(stage, name)
    _write_spec(paths["spec"], sp)
    steps = [runner.CliStep("simulate", [*cli, "simulate", stage, "--interaction", paths["spec"], "--name", name]),
             runner.PyStep("import", lambda view=paths["view"]: import_result(
                 bpy.context, view, None, True, role="sim", stage=stage))]
    return steps, name


def _write_spec(path: str, sp: dict) -> None:
    """The spec beside the stage; a file of that name the add-on did not write is left alone."""
    if os.path.exists(path):
        try:
            old = json.loads(Path(path).read_text())
        except (OSError, ValueError):
            old = None
        if not isinstance(old, dict) or old.get("source") != SPEC_MARK:
            raise UserError(f"{path}: exists and was not written by the add-on: rename the simulation")
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(sp, f, indent=1)
    os.replace(tmp, path)


def _optional_flags(cli, verb, notes, pairs) -> list:
    """The flags asked for that the CLI's verb has; a note for each it lacks."""
    out = []
    for flag, wanted in pairs:
        if not wanted:
            continue
        if clicaps.has(cli, verb, flag):
            out.append(flag)
        else:
            notes.append(f"{verb} ran without {flag}: this physinteract-usd lacks it")
    return out


def build_job(context, steps: str) -> runner.Job:
    """The steps as a runner.Job. Raises UserError / runner.CliNotFound before anything runs."""
    settings = context.scene.physinteract
    names = _parse_steps(steps)
    p = resolved_paths(settings)
    cli = runner.resolve_cli(cli_setting(context))
    has = lambda verb, flag=None: clicaps.has(cli, verb, flag)  # noqa: E731
    if "all" in names:
        names = (["init"] if settings.force or not os.path.exists(p["stage"]) else []) + \
            ["extract", "fit", "export", "import"]
    info: dict = {}
    notes: list = []
    job_steps = []

    def import_steps(name):
        target = p["stage"] if name == "import_stage" else p["export"]
        out = [runner.CliStep("info", runner.verb_argv(cli, "info", p["stage"], "--json"),
                              on_done=lambda out, info=info: info.update(parse_json(out)))]
        if has("versions"):  # optional: a failure here is a note, the import goes on
            out.append(runner.CliStep("versions list", [*cli, "versions", "list", p["stage"], "--json"],
                                      on_done=_store_versions, optional=True))
        out.append(runner.PyStep("import", lambda target=target, info=info: import_result(
            bpy.context, target, info, bpy.context.scene.physinteract.replace_import,
            role="fit", stage=p["stage"])))
        return out

    def report_steps():
        if has("report"):
            return [runner.CliStep("report", runner.verb_argv(cli, "report", p["stage"], "--json"),
                                   on_done=lambda out: store_report(bpy.context, parse_json(out))),
                    runner.PyStep("residual", lambda: _reimport_for_residual(bpy.context, p["stage"]))]
        notes.append("this physinteract-usd has no `report` verb: per-frame PSNR, SSIM and IoU from the "
                     "stage's fit report")
        return [runner.PyStep("report", lambda: store_report(bpy.context, stagedata.report_from_stage(p["stage"])))]

    fit_argv = runner.verb_argv(cli, "fit", p["stage"]) + (
        ["--iterations", str(settings.fit_iterations)] if settings.fit_iterations else [])
    for name in names:
        if name == "init":
            if not p["capture"] and not (p["video"] and p["camera"]):
                raise UserError("set the capture folder (or both the video and the camera)")
            if (settings.youngs_min > 0) != (settings.youngs_max > 0):
                raise UserError("give both E min and E max (or neither)")
            if settings.youngs_min and settings.youngs_min >= settings.youngs_max:
                raise UserError(f"E min {settings.youngs_min:g} must be below E max {settings.youngs_max:g}")
            obj = None
            if settings.object_source == "SELECTED":
                obj = export_selected_mesh(context, str(Path(p["stage"]).with_name(
                    Path(p["stage"]).stem + ".object.obj")))
            os.makedirs(os.path.dirname(p["stage"]) or ".", exist_ok=True)
            job_steps.append(runner.CliStep("init", runner.init_argv(
                cli, p["stage"], capture=p["capture"] or None, object=obj, video=p["video"] or None,
                camera=p["camera"] or None, masks=p["masks"] or None, masks_amodal=settings.masks_amodal,
                fps=settings.fps or None, grid=settings.grid, force=settings.force,
                padding=settings.padding or None, youngs_range=(settings.youngs_min, settings.youngs_max),
                poisson=settings.poisson or None, max_poisson=settings.max_poisson or None,
                density=settings.density or None,
                model=None if settings.model == "DEFAULT" else settings.model)
                + _optional_flags(cli, "init", notes, (("--discard-fits", settings.force and settings.discard_fits),
                                                       ("--yes", settings.accept_slow),
                                                       ("--preload", settings.preload == "PRELOAD"),
                                                       ("--no-preload", settings.preload == "STRESS_FREE")))))
        elif name == "extract":
            job_steps.append(runner.CliStep("extract", extract_argv(context, cli, p["stage"], notes)))
        elif name == "fit":
            job_steps.append(runner.CliStep("fit", fit_argv))
        elif name == "export":
            job_steps.append(runner.CliStep("export", runner.verb_argv(cli, "export", p["stage"], p["export"])))
        elif name == "export_sim_ready":   # its own file: the plain export stays what the panel imports
            if not has("export", "--sim-ready"):
                raise UserError("this physinteract-usd's export has no --sim-ready yet: update the project")
            if os.path.normcase(os.path.abspath(p["sim_ready"])) == os.path.normcase(os.path.abspath(p["stage"])):
                raise UserError(f"the sim-ready path {p['sim_ready']} is the stage itself: choose another file")
            job_steps.append(runner.CliStep(
                "export --sim-ready", runner.verb_argv(cli, "export", p["stage"], p["sim_ready"], "--sim-ready", "--force"),
                on_done=lambda out: setattr(bpy.context.scene.physinteract, "sim_ready_summary", sim_ready_summary(out))))
        elif name in ("import", "import_stage"):
            job_steps += import_steps(name)
        elif name == "simulate":
            more, _ = build_simulation(context, cli, p["stage"])
            job_steps += more
        elif name == "report":
            job_steps += report_steps()
        elif name == "diagnose":
            if not has("diagnose"):
                raise UserError("this physinteract-usd has no `diagnose` verb yet: update the project")
            job_steps.append(runner.CliStep("diagnose", runner.verb_argv(cli, "diagnose", p["stage"], "--json"),
                                            on_done=lambda out: setattr(bpy.context.scene.physinteract,
                                                                        "diagnose_json", json.dumps(parse_json(out)))))
        elif name.startswith("effect:"):
            effect = name.split(":", 1)[1]
            if effect not in EFFECTS:
                raise UserError(f"unknown effect '{effect}': expected {', '.join(EFFECTS)}")
            if not has("effects"):
                raise UserError("this physinteract-usd has no `effects` verb yet: update the project")
            job_steps.append(runner.CliStep(f"effects add {effect}", [*cli, "effects", "add", p["stage"], effect]))
            job_steps.append(runner.CliStep("fit", fit_argv))
            job_steps += import_steps("import_stage")
            job_steps += report_steps()
        elif name.startswith("version:"):
            if not has("versions"):
                raise UserError("this physinteract-usd has no `versions` verb yet: update the project")
            job_steps.append(runner.CliStep("versions use", [*cli, "versions", "use", p["stage"], name.split(":", 1)[1]]))
            job_steps += import_steps("import_stage")
    job = runner.Job(job_steps)
    job.notes = notes
    return job


def parse_json(out: str) -> dict:
    """The JSON object a `--json` verb prints, skipping any banner lines before it (Warp prints
    one to stdout when it initialises)."""
    start = out.find("\n{") + 1 if not out.lstrip().startswith("{") else out.find("{")
    if start <= 0 and not out.lstrip().startswith("{"):
        raise ValueError("the CLI printed no JSON object")
    return json.loads(out[start:])


def sim_ready_summary(out: str) -> str:
    """`export --sim-ready`'s own summary line (tetrahedra, regions, tolerance, unmapped effects)."""
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    return next((ln for ln in lines if ln.startswith("sim-ready:")), lines[-1] if lines else "")


def _redraw(context) -> None:
    wm = context.window_manager
    for window in wm.windows if wm else []:
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "TIMELINE", "DOPESHEET_EDITOR", "GRAPH_EDITOR"):
                area.tag_redraw()


class PHYSINTERACT_OT_run(bpy.types.Operator):
    """Run physinteract-usd verbs on the capture, in order, then import the result"""

    bl_idname = "physinteract.run"
    bl_label = "Run physinteract-usd"
    bl_options = {"REGISTER"}

    steps: StringProperty(name="Steps", default="all",
                          description="Comma-separated: init, extract, fit, export, export_sim_ready, import, "
                                      "import_stage, simulate, report, diagnose, effect:NAME, version:N, or all")

    _timer = None

    @classmethod
    def poll(cls, context):
        return _JOB is None or _JOB.finished

    def _start(self, context):
        global _JOB
        settings = context.scene.physinteract
        settings.error = ""
        settings.note = ""
        settings.progress = -1.0
        try:
            _JOB = build_job(context, self.steps)
        except (UserError, runner.CliNotFound) as exc:
            settings.error = str(exc)
            settings.status = ""
            self.report({"ERROR"}, str(exc))
            return False
        settings.running = True
        settings.status = f"running {self.steps}"
        _JOB.start()
        return True

    def _finish(self, context):
        settings = context.scene.physinteract
        settings.running = False
        settings.progress = -1.0
        job = _JOB
        settings.note = "; ".join(job.notes)
        if job.state == "done":
            settings.status = f"{self.steps}: done in {_elapsed(job)}"
            self.report({"INFO"}, settings.status + (f" (note: {settings.note})" if settings.note else ""))
            return {"FINISHED"}
        settings.error = job.error
        settings.status = f"{self.steps}: {job.state}"
        self.report({"ERROR"}, job.error)
        return {"CANCELLED"}

    def execute(self, context):
        """Blocking: background mode, scripts and tests (`bpy.ops.physinteract.run(steps=...)`)."""
        if not self._start(context):
            return {"CANCELLED"}
        _JOB.wait()
        return self._finish(context)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        if not self._start(context):
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.25, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        state = _JOB.poll()
        settings = context.scene.physinteract
        if state == "running":
            text, frac = _JOB.progress_info()
            settings.status = text
            settings.progress = -1.0 if frac is None else frac
            _redraw(context)
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        self._timer = None
        result = self._finish(context)
        _redraw(context)
        return result

    def cancel(self, context):
        if _JOB is not None:
            _JOB.kill()
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
        context.scene.physinteract.running = False


def _elapsed(job) -> str:
    import time

    return f"{time.monotonic() - job.started:.1f} s"


class PHYSINTERACT_OT_cancel(bpy.types.Operator):
    """Stop the running physinteract-usd step: first its own clean stop (a fit keeps its best
    iterate), a second click forces it"""

    bl_idname = "physinteract.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return _JOB is not None and not _JOB.finished

    def execute(self, context):
        _JOB.cancel()  # graceful first; again: forced. The modal operator sees the end on a tick
        s = context.scene.physinteract
        s.status = _JOB.progress() or s.status
        return {"FINISHED"}


# ------------------------------------------------------------------------------- viewport ops
def _particles_for_selection(context):
    s = context.scene.physinteract
    obj = context.active_object
    if obj is not None and obj.type == "POINTCLOUD" and not viewport.is_particles(obj):
        raise UserError(f"'{obj.name}' is not the SimParticles cloud (the splat cloud's points are Gaussians, "
                        "not particles): select points of SimParticles")
    obj = obj if viewport.is_particles(obj) else viewport.particles_in(s.last_collection)
    if obj is None:
        raise UserError("import the stage first, then select points of its SimParticles cloud (Edit Mode)")
    idx = viewport.selected_points(obj)
    if not idx:
        raise UserError(f"no point of '{obj.name}' is selected (Edit Mode)")
    return idx


def _stage_camera(context):
    """The video's camera: the one imported with the stage (not whatever camera renders the scene)."""
    coll = bpy.data.collections.get(context.scene.physinteract.last_collection or "")
    cams = [o for o in coll.all_objects if o.type == "CAMERA"] if coll is not None else []
    return cams[0] if cams else context.scene.camera


def _video_size(context):
    s = context.scene.physinteract
    try:
        size = (json.loads(s.info_json or "{}").get("frames") or {}).get("size")
    except ValueError:
        size = None
    r = context.scene.render
    return tuple(size) if size else (r.resolution_x, r.resolution_y)


class PHYSINTERACT_OT_hint(bpy.types.Operator):
    """Set an extraction hint from the viewport"""

    bl_idname = "physinteract.hint"
    bl_label = "Set hint"
    bl_options = {"REGISTER", "UNDO"}

    action: EnumProperty(items=[
        ("CONTACT_POINTS", "Contact from selected points", "The selected SimParticles points are the contact"),
        ("CONTACT_CURSOR", "Contact from 3D cursor", "The hand touches where the 3D cursor is, at this frame"),
        ("SUPPORT_POINTS", "Supports from selected points", "The selected points are held still"),
        ("SUPPORT_CURSOR", "Support from 3D cursor", "The object is held still where the 3D cursor is, at this frame"),
        ("GRASP", "Grasp here", "A 'grasp' marker at this frame"),
        ("RELEASE", "Release here", "A 'release' marker at this frame"),
        ("CLEAR", "Clear", "Clear the hint fields (markers stay)")])

    def execute(self, context):
        s = context.scene.physinteract
        scene = context.scene
        try:
            if self.action == "CONTACT_POINTS":
                s.hint_contact_particles = viewport.compact_indices(_particles_for_selection(context))
                s.hint_contact_pixel = ""
            elif self.action == "SUPPORT_POINTS":
                s.hint_support_particles = viewport.compact_indices(_particles_for_selection(context))
            elif self.action in ("CONTACT_CURSOR", "SUPPORT_CURSOR"):
                k = scene.frame_current
                uv = viewport.cursor_pixel(scene, _stage_camera(context), scene.cursor.location, k,
                                           _video_size(context))
                px = viewport.hint_pixel(k, uv)
                if self.action == "CONTACT_CURSOR":
                    s.hint_contact_pixel, s.hint_contact_particles = px, ""
                else:
                    s.hint_support_pixels = ";".join([p for p in s.hint_support_pixels.split(";") if p.strip()] + [px])
            elif self.action in ("GRASP", "RELEASE"):
                viewport.set_marker(scene, self.action.lower(), scene.frame_current)
            else:
                s.hint_contact_particles = s.hint_contact_pixel = ""
                s.hint_support_particles = s.hint_support_pixels = ""
                s.hint_type = "AUTO"
                s.hint_grasp_radius = 0.0
        except (UserError, viewport.ViewportError) as exc:
            s.error = str(exc)
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        s.error = ""
        return {"FINISHED"}


class PHYSINTERACT_OT_suggested(bpy.types.Operator):
    """Fill init's settings from the capture's README ('Suggested:' init command line)"""

    bl_idname = "physinteract.suggested"
    bl_label = "Use the capture's suggested settings"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        s = context.scene.physinteract
        try:
            readme = Path(_abs(s.capture_dir, "capture folder")) / "README.txt"
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        found = runner.suggested_init(readme.read_text(errors="replace")) if readme.is_file() else {}
        if not found:
            s.error = f"{readme}: no suggested init settings there"
            self.report({"ERROR"}, s.error)
            return {"CANCELLED"}
        apply_init_settings(s, found)
        s.error = ""
        s.status = "init settings: " + ", ".join(f"{k} {v}" for k, v in found.items())
        return {"FINISHED"}


def apply_init_settings(s, found: dict) -> None:
    for key, value in found.items():
        if key == "youngs_range":
            s.youngs_min, s.youngs_max = value
        elif key == "model":
            s.model = value if value in ("fixedCorotated", "neoHookean") else "DEFAULT"
        elif key == "preload":
            s.preload = value
        elif key in ("grid", "padding", "poisson", "max_poisson", "density"):
            setattr(s, key, value)


class PHYSINTERACT_OT_add_empty(bpy.types.Operator):
    """Add an Empty at the 3D cursor to drive a resimulation (keyframe its location)"""

    bl_idname = "physinteract.add_empty"
    bl_label = "Add interaction Empty"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        s = context.scene.physinteract
        e = bpy.data.objects.new("Drag", None)
        e.empty_display_type = "SPHERE"
        e.empty_display_size = 0.03
        e.location = context.scene.cursor.location
        context.collection.objects.link(e)
        s.resim_empty = e
        return {"FINISHED"}


# ------------------------------------------------------------------------------------- panel
def _cli(context):
    try:
        return runner.resolve_cli(cli_setting(context))
    except runner.CliNotFound:
        return None


_PROBING: set = set()


def _caps(context, verb: str, flag: str | None = None):
    """True / False, or None while unknown (a background probe is started): never blocks draw()."""
    cli = _cli(context)
    if cli is None:
        return False
    verbs = clicaps.cached(cli)
    if verbs is None or (flag and verb in verbs and clicaps.cached(cli, verb) is None):
        key = tuple(cli)
        if key not in _PROBING:
            _PROBING.add(key)
            clicaps.probe_in_background(cli)
        return None
    return verb in verbs and (flag is None or flag in (clicaps.cached(cli, verb) or set()))


def _missing(layout, what: str, known) -> None:
    layout.label(text=f"{what}: checking the CLI…" if known is None else
                 f"{what}: not in this physinteract-usd (update it)", icon="INFO")


class PHYSINTERACT_PT_fit(bpy.types.Panel):
    bl_idname = "PHYSINTERACT_PT_fit"
    bl_label = "Fit material from video"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "PhysInteract"

    def draw(self, context):
        s = context.scene.physinteract
        layout = self.layout
        col = layout.column(align=True)
        col.prop(s, "capture_dir")
        box = layout.box()
        box.label(text="Overrides (optional)")
        box.prop(s, "video")
        box.prop(s, "camera")
        box.prop(s, "masks")
        box.prop(s, "masks_amodal")
        layout.prop(s, "object_source", expand=True)
        if s.object_source == "SELECTED":
            obj = context.active_object
            ok = obj is not None and obj.type == "MESH"
            layout.label(text=f"Object: {obj.name}" if ok else "Select a mesh object",
                         icon="MESH_DATA" if ok else "ERROR")
        col = layout.column(align=True)
        col.prop(s, "stage_path")
        col.prop(s, "export_path")
        col.prop(s, "sim_ready_path")
        row = layout.row(align=True)
        row.prop(s, "grid")
        row.prop(s, "fps")
        row = layout.row(align=True)
        row.prop(s, "force")
        if s.force and _caps(context, "init", "--discard-fits"):
            row.prop(s, "discard_fits")

        busy = _JOB is not None and not _JOB.finished
        col = layout.column(align=True)
        col.enabled = not busy
        row = col.row(align=True)
        row.operator("physinteract.run", text="Init").steps = "init"
        row.operator("physinteract.run", text="Extract").steps = "extract"
        row = col.row(align=True)
        row.operator("physinteract.run", text="Fit").steps = "fit"
        row.operator("physinteract.run", text="Export").steps = "export"
        known = _caps(context, "export", "--sim-ready")
        if known:
            col.operator("physinteract.run", text="Simulation-ready export", icon="MESH_ICOSPHERE").steps = \
                "export_sim_ready"
        else:
            _missing(col, "export --sim-ready", known)
        col.operator("physinteract.run", text="Run all and import", icon="PLAY").steps = "all"
        row = col.row(align=True)
        row.operator("physinteract.run", text="Import twin", icon="IMPORT").steps = "import"
        row.operator("physinteract.run", text="Import stage").steps = "import_stage"
        layout.prop(s, "replace_import")
        draw_status(layout, s, busy)


def draw_status(layout, s, busy) -> None:
    if busy:
        if s.progress >= 0:
            layout.progress(factor=s.progress, type="BAR", text=f"{100 * s.progress:.0f}%")
        layout.label(text=s.status or "running", icon="SORTTIME")
        stopping = _JOB is not None and _JOB.stopping
        layout.operator("physinteract.cancel", text="Force stop" if stopping else "Cancel", icon="CANCEL")
    elif s.error:
        layout.label(text=s.error, icon="ERROR")
    elif s.status:
        layout.label(text=s.status, icon="CHECKMARK")
    if not busy and s.note:
        layout.label(text=f"note: {s.note}", icon="INFO")
    if not busy and s.sim_ready_summary:
        layout.label(text=s.sim_ready_summary, icon="MESH_ICOSPHERE")


class _Sub:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "PhysInteract"
    bl_parent_id = "PHYSINTERACT_PT_fit"
    bl_options = {"DEFAULT_CLOSED"}


class PHYSINTERACT_PT_settings(_Sub, bpy.types.Panel):
    bl_idname = "PHYSINTERACT_PT_settings"
    bl_label = "Init and fit settings"

    def draw(self, context):
        s = context.scene.physinteract
        layout = self.layout
        layout.operator("physinteract.suggested", icon="IMPORT")
        layout.label(text="0 keeps the CLI's default")
        col = layout.column(align=True)
        col.prop(s, "padding")
        row = col.row(align=True)
        row.prop(s, "youngs_min")
        row.prop(s, "youngs_max")
        col.prop(s, "poisson")
        col.prop(s, "max_poisson")
        col.prop(s, "density")
        col.prop(s, "model")
        if _caps(context, "init", "--preload"):
            col.prop(s, "preload")
        if _caps(context, "init", "--yes"):
            layout.prop(s, "accept_slow")
        layout.prop(s, "fit_iterations")


class PHYSINTERACT_PT_hints(_Sub, bpy.types.Panel):
    bl_idname = "PHYSINTERACT_PT_hints"
    bl_label = "Hints for extract"

    def draw(self, context):
        s = context.scene.physinteract
        layout = self.layout
        layout.prop(s, "hint_type")
        col = layout.column(align=True)
        row = col.row(align=True)
        row.operator("physinteract.hint", text="Contact: selected points").action = "CONTACT_POINTS"
        row.operator("physinteract.hint", text="Contact: 3D cursor").action = "CONTACT_CURSOR"
        col.prop(s, "hint_contact_particles")
        col.prop(s, "hint_contact_pixel")
        col = layout.column(align=True)
        row = col.row(align=True)
        row.operator("physinteract.hint", text="Supports: selected points").action = "SUPPORT_POINTS"
        row.operator("physinteract.hint", text="Support: 3D cursor").action = "SUPPORT_CURSOR"
        col.prop(s, "hint_support_particles")
        col.prop(s, "hint_support_pixels")
        layout.prop(s, "hint_grasp_radius")
        row = layout.row(align=True)
        row.operator("physinteract.hint", text="Grasp here", icon="MARKER").action = "GRASP"
        row.operator("physinteract.hint", text="Release here", icon="MARKER").action = "RELEASE"
        layout.prop(s, "use_markers")
        scene = context.scene
        g, r = viewport.marker_frame(scene, "grasp"), viewport.marker_frame(scene, "release")
        if g is not None or r is not None:
            layout.label(text=f"markers: grasp {g if g is not None else '-'}, release {r if r is not None else '-'}")
            known = _caps(context, "extract", "--grasp-frame")
            if not known:
                _missing(layout, "extract --grasp-frame", known)
        layout.operator("physinteract.hint", text="Clear hints").action = "CLEAR"
        try:
            contacts = json.loads(s.contacts_json or "[]")
        except ValueError:
            contacts = []
        if contacts:
            box = layout.box()
            box.label(text="On the stage:")
            for c in contacts:
                box.label(text=viewport.describe_contact(c), icon="HAND" if c["source"] == "user" else "DOT")


class PHYSINTERACT_PT_resimulate(_Sub, bpy.types.Panel):
    bl_idname = "PHYSINTERACT_PT_resimulate"
    bl_label = "Resimulate"

    def draw(self, context):
        s = context.scene.physinteract
        layout = self.layout
        row = layout.row(align=True)
        row.prop(s, "resim_empty")
        row.operator("physinteract.add_empty", text="", icon="ADD")
        layout.prop(s, "resim_kind", expand=True)
        if s.resim_kind == "drag":
            layout.prop(s, "resim_contact")
        if s.resim_kind == "push":
            layout.prop(s, "resim_friction")
        col = layout.column(align=True)
        col.prop(s, "resim_release")
        col.prop(s, "resim_frames")
        col.prop(s, "resim_keep_supports")
        col.prop(s, "resim_name")
        busy = _JOB is not None and not _JOB.finished
        row = layout.row()
        row.enabled = not busy
        row.operator("physinteract.run", text="Resimulate and import", icon="PHYSICS").steps = "simulate"
        if s.resim_empty is not None:
            layout.label(text=f"radius {s.resim_empty.empty_display_size:.3g} (the Empty's display size)")


class PHYSINTERACT_PT_look(_Sub, bpy.types.Panel):
    bl_idname = "PHYSINTERACT_PT_look"
    bl_label = "Look"

    def draw(self, context):
        s = context.scene.physinteract
        layout = self.layout
        layout.prop(s, "colour_by")
        if s.colour_by == "RESIDUAL":
            known = _caps(context, "report")
            if not known:
                _missing(layout, "report (per-particle residual)", known)
        layout.prop(s, "splat_look")
        layout.prop(s, "splat_size")
        layout.prop(s, "render_particles")
        if s.look_note:
            layout.label(text=s.look_note, icon="INFO")


class PHYSINTERACT_PT_report(_Sub, bpy.types.Panel):
    bl_idname = "PHYSINTERACT_PT_report"
    bl_label = "Report and diagnosis"

    def draw(self, context):
        s = context.scene.physinteract
        layout = self.layout
        busy = _JOB is not None and not _JOB.finished
        row = layout.row(align=True)
        row.enabled = not busy
        row.operator("physinteract.run", text="Report", icon="GRAPH").steps = "report"
        has_diag = _caps(context, "diagnose")
        sub = row.row(align=True)
        sub.enabled = bool(has_diag)
        sub.operator("physinteract.run", text="Diagnose", icon="VIEWZOOM").steps = "diagnose"
        known = _caps(context, "report")
        if not known:
            _missing(layout, "report (stage's fit report used)", known)
        if not has_diag:
            _missing(layout, "diagnose", has_diag)
        draw_report(layout, s, context.scene.frame_current)
        draw_diagnosis(layout, s, _caps(context, "effects"), busy)
        draw_versions(layout, s, _caps(context, "versions"), busy)


def draw_report(layout, s, frame) -> None:
    try:
        rep = json.loads(s.report_json) if s.report_json else None
    except ValueError:
        rep = None
    if not rep:
        return
    box = layout.box()
    if rep.get("verdict"):
        box.label(text=f"verdict: {rep['verdict']}", icon="CHECKMARK" if rep["verdict"] == "adequate" else "ERROR")
    for line in _wrap(rep.get("headline") or "", 70):
        box.label(text=line)
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    box.label(text=f"PSNR {fmt(rep.get('psnr'), '.2f')} dB (masked {fmt(rep.get('psnr_masked'), '.2f')}), "
                   f"SSIM {fmt(rep.get('ssim'), '.3f')}, IoU {fmt(rep.get('iou'), '.3f')}")
    if rep.get("track_error_px") is not None:
        box.label(text=f"track error {rep['track_error_px']:.2f} px")
    frames = [f for f in rep.get("frames") or [] if f.get("psnr") is not None]
    now = report_at(rep, frame)
    if now:
        box.label(text=f"frame {frame}: PSNR {fmt(now.get('psnr'), '.2f')}, SSIM {fmt(now.get('ssim'), '.3f')}, "
                       f"IoU {fmt(now.get('iou'), '.3f')}" + (f" ({now['phase']})" if now.get("phase") else ""))
    if frames:
        vals = [f["psnr"] for f in frames]
        lo, hi = min(vals), max(vals)
        col = box.column(align=True)
        col.label(text=f"per-frame PSNR {lo:.1f}..{hi:.1f} dB (keyed as 'Frame PSNR' for the Graph Editor)")
        step = max(1, (len(frames) + 23) // 24)
        for f in frames[::step]:
            fac = 0.05 + 0.95 * ((f["psnr"] - lo) / (hi - lo) if hi > lo else 1.0)
            col.progress(factor=fac, type="BAR", text=f"{f['frame']}: {f['psnr']:.1f} dB")
    if rep.get("source") == "stage":
        box.label(text="(from the stage's fit report)")


def draw_diagnosis(layout, s, has_effects, busy) -> None:
    try:
        diag = json.loads(s.diagnose_json) if s.diagnose_json else None
    except ValueError:
        diag = None
    if not diag:
        return
    box = layout.box()
    box.label(text=f"verdict: {diag.get('verdict', '?')}")
    if diag.get("reason"):
        box.label(text=str(diag["reason"])[:160])
    for c in diag.get("candidates") or []:
        eff = str(c.get("effect", "?"))
        drop = c.get("predicted_loss_drop")
        col = box.column(align=True)
        col.label(text=f"{eff}: score {c.get('score', 0):.3g}" + (f", predicted loss drop {drop:.3g}" if
                                                                  isinstance(drop, (int, float)) else ""))
        ev = c.get("evidence")
        if ev:
            col.label(text=("  " + (ev if isinstance(ev, str) else json.dumps(ev)))[:160])
        if eff in EFFECTS:
            row = col.row()
            row.enabled = bool(has_effects) and not busy
            row.operator("physinteract.run", text=f"Add {eff} and refit", icon="ADD").steps = f"effect:{eff}"
    if not has_effects:
        _missing(box, "effects add", has_effects)


def _wrap(text: str, width: int) -> list:
    words, lines, cur = text.split(), [], ""
    for w in words:
        if cur and len(cur) + 1 + len(w) > width:
            lines.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}".strip()
    return lines + ([cur] if cur else [])


def draw_versions(layout, s, has_versions, busy) -> None:
    """The fit versions: `versions list --json` when the CLI has it (with the current one), else
    `info --json`'s fits."""
    try:
        listed = json.loads(s.versions_json) if s.versions_json else None
        fits = (listed or {}).get("versions") or (json.loads(s.info_json or "{}").get("fits")) or []
    except ValueError:
        fits = []
    if not fits:
        return
    current = (listed or {}).get("current")
    box = layout.box()
    box.label(text="Fit versions:")
    for f in fits:
        row = box.row()
        psnr = f.get("psnr")
        status = f.get("status")
        row.label(text=f"v{f.get('version')}: {', '.join(f.get('effects') or []) or 'base'}"
                       + (f", PSNR {psnr:.2f}" if isinstance(psnr, (int, float)) else "")
                       + (f" ({status})" if status and status != "complete" else ""),
                  icon="RADIOBUT_ON" if f.get("version") == current else "RADIOBUT_OFF")
        if has_versions and f.get("version") != current:
            sub = row.row()
            sub.enabled = not busy
            sub.operator("physinteract.run", text="Use").steps = f"version:{f.get('version')}"


CLASSES = (PHYSINTERACT_AP_preferences, PHYSINTERACT_PG_settings, PHYSINTERACT_OT_run,
           PHYSINTERACT_OT_cancel, PHYSINTERACT_OT_hint, PHYSINTERACT_OT_suggested, PHYSINTERACT_OT_add_empty,
           PHYSINTERACT_PT_fit, PHYSINTERACT_PT_settings, PHYSINTERACT_PT_hints, PHYSINTERACT_PT_resimulate,
           PHYSINTERACT_PT_look, PHYSINTERACT_PT_report)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.physinteract = PointerProperty(type=PHYSINTERACT_PG_settings)


def unregister():
    global _JOB
    if _JOB is not None and not _JOB.finished:
        _JOB.kill()
    _JOB = None
    del bpy.types.Scene.physinteract
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
