"""PhysInteract USD for Blender: "Fit material from video" in the 3D viewport's sidebar.

A thin client: it runs the `physinteract-usd` command line (init, extract, fit, export) as
subprocesses, never blocking the interface (a modal operator polls them on a timer), and imports
the resulting USD with Blender's own importer as an animated point cloud. No physics here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import runner

bl_info = {  # legacy add-on install; as an extension, blender_manifest.toml is used instead
    "name": "PhysInteract USD",
    "author": "physinteract-usd",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "3D Viewport > Sidebar > PhysInteract",
    "description": "Fit a soft object's material from a video of a hand handling it, import the "
                   "digital twin as an animated point cloud",
    "category": "Physics",
}

ADDON_ID = __package__ or __name__
PRIMVAR_E = "physinteract:youngsModulus"
STEP_LABELS = {"init": "init", "extract": "extract", "fit": "fit", "export": "export"}

_JOB: runner.Job | None = None


class UserError(Exception):
    """A setting the user must fix: shown as one line, nothing run."""


# ------------------------------------------------------------------------------- preferences
class PHYSINTERACT_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    cli_path: StringProperty(
        name="physinteract-usd", subtype="FILE_PATH", default="",
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
    replace_import: BoolProperty(name="Replace previous import", default=True,
                                 description="Remove the objects of the previous import first")
    # state shown in the panel
    running: BoolProperty(default=False, options={"SKIP_SAVE"})
    status: StringProperty(default="", options={"SKIP_SAVE"})
    error: StringProperty(default="", options={"SKIP_SAVE"})
    last_collection: StringProperty(default="")


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
    return {"capture": capture, "stage": stage, "export": export,
            "video": _abs(settings.video, "video"), "camera": _abs(settings.camera, "camera"),
            "masks": _abs(settings.masks, "masks")}


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
def import_result(context, path: str, info: dict | None = None, replace: bool = True) -> list:
    """Import a stage or exported asset with Blender's USD importer; returns the new objects.

    Time-sampled SimParticles become an animated POINTCLOUD (a Mesh Sequence Cache modifier
    reading the USD file), primvars become attributes; the camera comes along. Gaussian splats
    (UsdVol.ParticleField, USD >= 26.x) and the PhysInteract prims are skipped by Blender.
    """
    if not os.path.exists(path):
        raise RuntimeError(f"{path}: file not found")
    settings = context.scene.physinteract
    if replace and settings.last_collection:
        _remove_collection(settings.last_collection)
    before = set(bpy.data.objects)
    colls_before = set(bpy.data.collections)
    result = bpy.ops.wm.usd_import(filepath=path, import_cameras=True, import_points=True,
                                   import_meshes=True, set_frame_range=True, create_collection=True)
    if "FINISHED" not in result:
        raise RuntimeError(f"{path}: Blender's USD import failed")
    new = [o for o in bpy.data.objects if o not in before]
    new_colls = [c for c in bpy.data.collections if c not in colls_before]
    settings.last_collection = new_colls[0].name if new_colls else ""
    scene = context.scene
    cams = [o for o in new if o.type == "CAMERA"]
    if cams:
        scene.camera = cams[0]
    if info:
        size = (info.get("frames") or {}).get("size")
        if size:
            scene.render.resolution_x, scene.render.resolution_y = int(size[0]), int(size[1])
            scene.render.resolution_percentage = 100
    e_range = ((info or {}).get("simulation") or {}).get("youngs_range_pa")
    for o in new:
        if o.type == "POINTCLOUD" and PRIMVAR_E in o.data.attributes:
            o.data.materials.clear()
            o.data.materials.append(youngs_material(o.data, e_range))
    return new


def _remove_collection(name: str) -> None:
    coll = bpy.data.collections.get(name)
    if coll is None:
        return
    for o in list(coll.all_objects):
        bpy.data.objects.remove(o, do_unlink=True)
    for child in list(coll.children_recursive):
        bpy.data.collections.remove(child)
    bpy.data.collections.remove(coll)


def youngs_material(pointcloud, e_range=None) -> bpy.types.Material:
    """Colour by log10 of Young's modulus over the fit's allowed range (blue soft, red stiff)."""
    if not e_range:
        import numpy as np

        vals = np.empty(len(pointcloud.points), np.float32)
        pointcloud.attributes[PRIMVAR_E].data.foreach_get("value", vals)
        lo, hi = float(vals.min()), float(vals.max())
        e_range = (lo, hi if hi > lo else lo * 10.0)
    lo, hi = (max(float(x), 1e-6) for x in e_range)
    import math

    mat = bpy.data.materials.get("PhysInteract Young's modulus") or bpy.data.materials.new(
        "PhysInteract Young's modulus")
    if mat.node_tree is None:
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = PRIMVAR_E
    log = nt.nodes.new("ShaderNodeMath")
    log.operation = "LOGARITHM"
    log.inputs[1].default_value = 10.0
    rng = nt.nodes.new("ShaderNodeMapRange")
    rng.inputs["From Min"].default_value = math.log10(lo)
    rng.inputs["From Max"].default_value = math.log10(hi)
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.1, 0.2, 0.9, 1.0)
    ramp.color_ramp.elements[1].color = (0.9, 0.15, 0.1, 1.0)
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(attr.outputs["Fac"], log.inputs[0])
    nt.links.new(log.outputs[0], rng.inputs["Value"])
    nt.links.new(rng.outputs["Result"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    for i, n in enumerate((attr, log, rng, ramp, bsdf, out)):
        n.location = (i * 220.0, 0.0)
    return mat


# ------------------------------------------------------------------------------------- jobs
STEP_CHOICES = ("init", "extract", "fit", "export", "import", "import_stage", "all")


def build_job(context, steps: str) -> runner.Job:
    """The steps as a runner.Job. Raises UserError / runner.CliNotFound before anything runs."""
    settings = context.scene.physinteract
    names = [s.strip() for s in steps.split(",") if s.strip()]
    bad = [s for s in names if s not in STEP_CHOICES]
    if bad or not names:
        raise UserError(f"unknown step(s) {', '.join(bad) or '(none)'}: expected {', '.join(STEP_CHOICES)}")
    p = resolved_paths(settings)
    cli = runner.resolve_cli(cli_setting(context))
    if "all" in names:
        names = (["init"] if settings.force or not os.path.exists(p["stage"]) else []) + \
            ["extract", "fit", "export", "import"]
    info: dict = {}
    job_steps = []
    for name in names:
        if name == "init":
            if not p["capture"] and not (p["video"] and p["camera"]):
                raise UserError("set the capture folder (or both the video and the camera)")
            obj = None
            if settings.object_source == "SELECTED":
                obj = export_selected_mesh(context, str(Path(p["stage"]).with_name(
                    Path(p["stage"]).stem + ".object.obj")))
            os.makedirs(os.path.dirname(p["stage"]) or ".", exist_ok=True)
            job_steps.append(runner.CliStep("init", runner.init_argv(
                cli, p["stage"], capture=p["capture"] or None, object=obj, video=p["video"] or None,
                camera=p["camera"] or None, masks=p["masks"] or None, masks_amodal=settings.masks_amodal,
                fps=settings.fps or None, grid=settings.grid, force=settings.force)))
        elif name in ("extract", "fit"):
            job_steps.append(runner.CliStep(name, runner.verb_argv(cli, name, p["stage"])))
        elif name == "export":
            job_steps.append(runner.CliStep("export", runner.verb_argv(cli, "export", p["stage"], p["export"])))
        elif name in ("import", "import_stage"):
            target = p["stage"] if name == "import_stage" else p["export"]
            job_steps.append(runner.CliStep("info", runner.verb_argv(cli, "info", p["stage"], "--json"),
                                            on_done=lambda out, info=info: info.update(parse_json(out))))
            job_steps.append(runner.PyStep(
                "import", lambda target=target, info=info: import_result(
                    bpy.context, target, info, bpy.context.scene.physinteract.replace_import)))
    return runner.Job(job_steps)


def parse_json(out: str) -> dict:
    """The JSON object a `--json` verb prints, skipping any banner lines before it (Warp prints
    one to stdout when it initialises)."""
    start = out.find("\n{") + 1 if not out.lstrip().startswith("{") else out.find("{")
    if start <= 0 and not out.lstrip().startswith("{"):
        raise ValueError("info --json printed no JSON object")
    return json.loads(out[start:])


def _redraw(context) -> None:
    wm = context.window_manager
    for window in wm.windows if wm else []:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


class PHYSINTERACT_OT_run(bpy.types.Operator):
    """Run physinteract-usd verbs on the capture, in order, then import the result"""

    bl_idname = "physinteract.run"
    bl_label = "Run physinteract-usd"
    bl_options = {"REGISTER"}

    steps: StringProperty(name="Steps", default="all",
                          description="Comma-separated: init, extract, fit, export, import, "
                                      "import_stage, or all")

    _timer = None

    @classmethod
    def poll(cls, context):
        return _JOB is None or _JOB.finished

    def _start(self, context):
        global _JOB
        settings = context.scene.physinteract
        settings.error = ""
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
        job = _JOB
        if job.state == "done":
            settings.status = f"{self.steps}: done in {_elapsed(job)}"
            self.report({"INFO"}, settings.status)
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
            settings.status = _JOB.progress()
            _redraw(context)
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        self._timer = None
        result = self._finish(context)
        _redraw(context)
        return result

    def cancel(self, context):
        if _JOB is not None:
            _JOB.cancel()
        if self._timer is not None:
            context.window_manager.event_timer_remove(self._timer)
        context.scene.physinteract.running = False


def _elapsed(job) -> str:
    import time

    return f"{time.monotonic() - job.started:.1f} s"


class PHYSINTERACT_OT_cancel(bpy.types.Operator):
    """Stop the running physinteract-usd step"""

    bl_idname = "physinteract.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return _JOB is not None and not _JOB.finished

    def execute(self, context):
        _JOB.cancel()  # the modal operator sees the state on its next tick
        return {"FINISHED"}


# ------------------------------------------------------------------------------------- panel
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
        row = layout.row(align=True)
        row.prop(s, "grid")
        row.prop(s, "fps")
        layout.prop(s, "force")

        busy = _JOB is not None and not _JOB.finished
        col = layout.column(align=True)
        col.enabled = not busy
        row = col.row(align=True)
        row.operator("physinteract.run", text="Init").steps = "init"
        row.operator("physinteract.run", text="Extract").steps = "extract"
        row = col.row(align=True)
        row.operator("physinteract.run", text="Fit").steps = "fit"
        row.operator("physinteract.run", text="Export").steps = "export"
        col.operator("physinteract.run", text="Run all and import", icon="PLAY").steps = "all"
        row = col.row(align=True)
        row.operator("physinteract.run", text="Import twin", icon="IMPORT").steps = "import"
        row.operator("physinteract.run", text="Import stage").steps = "import_stage"
        layout.prop(s, "replace_import")
        if busy:
            layout.label(text=s.status or "running", icon="SORTTIME")
            layout.operator("physinteract.cancel", icon="CANCEL")
        elif s.error:
            layout.label(text=s.error, icon="ERROR")
        elif s.status:
            layout.label(text=s.status, icon="CHECKMARK")


CLASSES = (PHYSINTERACT_AP_preferences, PHYSINTERACT_PG_settings, PHYSINTERACT_OT_run,
           PHYSINTERACT_OT_cancel, PHYSINTERACT_PT_fit)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.physinteract = PointerProperty(type=PHYSINTERACT_PG_settings)


def unregister():
    global _JOB
    if _JOB is not None and not _JOB.finished:
        _JOB.cancel()
    _JOB = None
    del bpy.types.Scene.physinteract
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
