"""The Blender side of the add-on's data: from the viewport to the stage's frame (the Empty that
drives a resimulation, selected points, the 3D cursor through the stage's camera, timeline
markers), and back (the look of the imported twin, the stage's contacts shown as Empties and
markers).

Axes: Blender's USD import keeps the stage's coordinates inside the imported objects and puts the
Y-up -> Z-up rotation on their parent, so the imported SimParticles object's world matrix maps
stage coordinates into Blender's world; its inverse takes anything the artist placed back into
the stage's frame (and follows the artist moving the imported hierarchy). Without an import the
fixed conversion is used: stage (x, y, z) = Blender (x, z, -y).
"""

from __future__ import annotations

import math

import bpy
import numpy as np
from mathutils import Matrix, Vector

PRIMVAR_E = "physinteract:youngsModulus"
PRIMVAR_CONF = "physinteract:confidence"
PRIMVAR_RESIDUAL = "physinteract:residual"
STAGE_FROM_BLENDER = Matrix(((1, 0, 0, 0), (0, 0, 1, 0), (0, -1, 0, 0), (0, 0, 0, 1)))
MARKER_PREFIX = "PI "           # markers the add-on makes (shown-back contact timing)
OWNED = "physinteract_owned"    # custom property on objects the add-on made beside an import


class ViewportError(ValueError):
    """One line for the panel."""


# ------------------------------------------------------------------------ finding the twin
def is_particles(obj) -> bool:
    return obj is not None and obj.type == "POINTCLOUD" and PRIMVAR_E in obj.data.attributes


def particles_in(coll_name: str):
    """The imported SimParticles point cloud of a collection (None if none)."""
    coll = bpy.data.collections.get(coll_name or "")
    if coll is None:
        return None
    return next((o for o in coll.all_objects if is_particles(o)), None)


def stage_matrix(particles=None) -> Matrix:
    """Blender world -> the stage's frame."""
    if particles is not None:
        return particles.matrix_world.inverted_safe()
    return STAGE_FROM_BLENDER.copy()


def _mean_scale(m: Matrix) -> float:
    s = m.to_scale()
    return (abs(s[0]) + abs(s[1]) + abs(s[2])) / 3.0


# ---------------------------------------------------------------------------- the Empty
def keyframe_frames(obj) -> list[int]:
    """The frames of the object's own keyframes (Blender 5's layered actions), sorted."""
    ad = obj.animation_data
    if ad is None or ad.action is None:
        return []
    frames = set()
    try:
        from bpy_extras import anim_utils

        bag = anim_utils.animdata_get_channelbag_for_assigned_slot(ad)
        curves = bag.fcurves if bag is not None else []
    except (ImportError, AttributeError):
        curves = getattr(ad.action, "fcurves", [])
    for fc in curves:
        frames.update(int(round(k.co[0])) for k in fc.keyframe_points)
    return sorted(frames)


def sample_empty(scene, empty, n_frames: int, to_stage: Matrix) -> dict:
    """The Empty over frames 0..n-1 in the stage's frame: positions (n, 3), its radius (display
    size x its world scale) and its +Z axis (n, 3), evaluated with parents and constraints. The
    scene's current frame is restored."""
    current = scene.frame_current, scene.frame_subframe
    pos, axis = np.zeros((n_frames, 3)), np.zeros((n_frames, 3))
    radius = 0.0
    rot = to_stage.to_3x3()
    try:
        for k in range(n_frames):
            scene.frame_set(k)
            mw = empty.matrix_world
            pos[k] = tuple(to_stage @ mw.translation)
            z = rot @ (mw.to_3x3() @ Vector((0.0, 0.0, 1.0)))
            axis[k] = tuple(z.normalized()) if z.length > 0 else (0.0, 0.0, 0.0)
            if k == 0:
                radius = float(empty.empty_display_size) * _mean_scale(mw) * _mean_scale(to_stage)
    finally:
        scene.frame_set(current[0], subframe=current[1])
    return {"positions": pos, "axis": axis, "radius": radius}


# ------------------------------------------------------------------------- selected points
def selected_points(obj) -> list[int]:
    """Indices of the selected points of a point cloud (edit mode's `.selection`)."""
    if obj is None or obj.type != "POINTCLOUD":
        raise ViewportError("select points of the imported SimParticles point cloud (Edit Mode) first")
    if obj.mode == "EDIT":
        obj.update_from_editmode()
    attr = obj.data.attributes.get(".selection")
    n = len(obj.data.points)
    if attr is None or n == 0:
        return []
    vals = np.zeros(n, np.float32 if attr.data_type == "FLOAT" else bool)
    attr.data.foreach_get("value", vals)
    return np.flatnonzero(vals > 0.5 if vals.dtype != bool else vals).tolist()


def compact_indices(idx) -> str:
    return ",".join(str(int(i)) for i in idx)


def parse_indices(text: str) -> list[int]:
    out = []
    for part in (text or "").replace(" ", "").split(","):
        if part:
            if not part.lstrip("-").isdigit():
                raise ViewportError(f"'{part}' is not a particle index")
            out.append(int(part))
    return out


# ------------------------------------------------------------------------- the 3D cursor
def cursor_pixel(scene, camera, co_world, frame: int, size) -> tuple[float, float]:
    """Where a world point lies in the video's frame `frame`, through the (imported) stage camera:
    continuous pixel coordinates, pixel (i, j)'s centre at (i + 0.5, j + 0.5), row down."""
    from bpy_extras.object_utils import world_to_camera_view

    if camera is None or camera.type != "CAMERA":
        raise ViewportError("the scene has no camera: import the stage first (its camera is the video's)")
    current = scene.frame_current
    try:
        scene.frame_set(frame)
        ndc = world_to_camera_view(scene, camera, Vector(co_world))
    finally:
        scene.frame_set(current)
    w, h = size
    if ndc.z <= 0:
        raise ViewportError("the 3D cursor is behind the camera")
    u, v = ndc.x * w, (1.0 - ndc.y) * h
    if not (0 <= u < w and 0 <= v < h):
        raise ViewportError(f"the 3D cursor is outside the video's frame (pixel {u:.0f}, {v:.0f} of {w}x{h})")
    return u, v


def hint_pixel(frame: int, uv) -> str:
    """The CLI's K,U,V (frame, column, row as an image viewer shows them: the pixel centre - 0.5)."""
    return f"{int(frame)},{uv[0] - 0.5:.2f},{uv[1] - 0.5:.2f}"


# --------------------------------------------------------------------------- the timeline
def marker_frame(scene, name: str):
    """The frame of the timeline marker called `name` (any case), None if none."""
    hits = [m.frame for m in scene.timeline_markers if m.name.strip().lower() == name]
    return min(hits) if hits else None


def set_marker(scene, name: str, frame: int):
    """Move the marker called `name` to `frame`, or add one (one per name)."""
    for m in scene.timeline_markers:
        if m.name.strip().lower() == name:
            m.frame = frame
            return m
    return scene.timeline_markers.new(name, frame=frame)


def remove_own_markers(scene) -> None:
    for m in list(scene.timeline_markers):
        if m.name.startswith(MARKER_PREFIX):
            scene.timeline_markers.remove(m)


# ------------------------------------------------------------------------ shown back
def show_contacts(scene, particles, contacts: list, collection) -> list:
    """The stage's contact sets in the viewport: one Empty per set at its contact point (a sphere
    of its collider radius or grasp size for the hand, a cube for a support), parented to the
    imported point cloud, with the set's facts as custom properties; and timeline markers
    `PI <name> grasp` / `PI <name> release`. Returns the Empties."""
    remove_own_markers(scene)
    made = []
    for c in contacts:
        fixed = c["type"] == "fixed"
        e = bpy.data.objects.new(f"{'support' if fixed else 'contact'}: {c['name']}", None)
        e.empty_display_type = "CUBE" if fixed else "SPHERE"
        e.empty_display_size = max(c.get("radius") or 0.0, 0.01 if fixed else 0.02)
        collection.objects.link(e)
        if particles is not None:
            e.parent = particles
            e.matrix_parent_inverse = Matrix.Identity(4)
            e.location = c["point"]
        else:
            e.matrix_world = STAGE_FROM_BLENDER.inverted() @ Matrix.Translation(c["point"])
        e[OWNED] = "contact"
        for k in ("name", "type", "source", "grasp"):
            e[f"physinteract_{k}"] = c[k]
        e["physinteract_release"] = -1 if c["release"] is None else c["release"]
        e["physinteract_particles"] = len(c["indices"])
        e.hide_render = True
        made.append(e)
        if not fixed:
            scene.timeline_markers.new(f"{MARKER_PREFIX}{c['name']} grasp", frame=int(c["grasp"]))
            if c["release"] is not None:
                scene.timeline_markers.new(f"{MARKER_PREFIX}{c['name']} release", frame=int(c["release"]))
    return made


def describe_contact(c: dict) -> str:
    rel = "end" if c["release"] is None else c["release"]
    who = {"user": "your hint", "extracted": "from the video"}.get(c["source"], c["source"])
    kind = "support" if c["type"] == "fixed" else c["type"]
    return f"{c['name']}: {kind}, {len(c['indices'])} particles, frames {c['grasp']}..{rel} ({who})"


# ------------------------------------------------------------------------------- the look
def _attr_values(pc, name) -> np.ndarray:
    a = pc.attributes[name]
    vals = np.empty(len(pc.points), np.float32)
    a.data.foreach_get("value", vals)
    return vals


def ramp_material(name: str, attribute: str, lo: float, hi: float, *, log10: bool = False,
                  colours=((0.1, 0.2, 0.9, 1.0), (0.9, 0.15, 0.1, 1.0))) -> bpy.types.Material:
    """A material colouring a point attribute over [lo, hi] (log10 of it with log10=True)."""
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_type = "GEOMETRY"
    attr.attribute_name = attribute
    chain = [attr]
    src = attr.outputs["Fac"]
    if log10:
        lg = nt.nodes.new("ShaderNodeMath")
        lg.operation = "LOGARITHM"
        lg.inputs[1].default_value = 10.0
        nt.links.new(src, lg.inputs[0])
        src = lg.outputs[0]
        chain.append(lg)
        lo, hi = math.log10(max(lo, 1e-12)), math.log10(max(hi, 1e-12))
    rng = nt.nodes.new("ShaderNodeMapRange")
    rng.inputs["From Min"].default_value = lo
    rng.inputs["From Max"].default_value = hi if hi > lo else lo + 1.0
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = colours[0]
    ramp.color_ramp.elements[1].color = colours[1]
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(src, rng.inputs["Value"])
    nt.links.new(rng.outputs["Result"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    for i, n in enumerate(chain + [rng, ramp, bsdf, out]):
        n.location = (i * 220.0, 0.0)
    return mat


def youngs_material(pointcloud, e_range=None) -> bpy.types.Material:
    """Colour by log10 of Young's modulus over the fit's allowed range (blue soft, red stiff)."""
    if not e_range:
        vals = _attr_values(pointcloud, PRIMVAR_E)
        lo, hi = float(vals.min()), float(vals.max())
        e_range = (lo, hi if hi > lo else lo * 10.0)
    lo, hi = (max(float(x), 1e-6) for x in e_range)
    return ramp_material("PhysInteract Young's modulus", PRIMVAR_E, lo, hi, log10=True)


def colour_particles(obj, colour_by: str, e_range=None) -> str:
    """Give the imported SimParticles cloud its material: STIFFNESS (log10 E), CONFIDENCE (0..1,
    red low, green high) or RESIDUAL (the report's per-particle residual, 0..its 98th percentile,
    dark to bright red). Returns '' or one line saying why it could not."""
    pc = obj.data
    note = ""
    if colour_by == "RESIDUAL" and PRIMVAR_RESIDUAL in pc.attributes:
        v = _attr_values(pc, PRIMVAR_RESIDUAL)
        hi = float(np.percentile(v, 98)) if len(v) else 1.0
        mat = ramp_material("PhysInteract residual", PRIMVAR_RESIDUAL, 0.0, hi if hi > 0 else 1.0,
                            colours=((0.05, 0.05, 0.08, 1.0), (1.0, 0.1, 0.05, 1.0)))
    elif colour_by == "CONFIDENCE" and PRIMVAR_CONF in pc.attributes:
        mat = ramp_material("PhysInteract confidence", PRIMVAR_CONF, 0.0, 1.0,
                            colours=((0.9, 0.15, 0.1, 1.0), (0.1, 0.8, 0.2, 1.0)))
    else:
        if colour_by == "RESIDUAL":
            note = ("no per-particle residual on this stage (primvars:physinteract:residual, written by "
                    "`report`): coloured by stiffness")
        elif colour_by == "CONFIDENCE":
            note = "no confidence on this stage (not fitted yet): coloured by stiffness"
        mat = youngs_material(pc, e_range)
    pc.materials.clear()
    pc.materials.append(mat)
    return note


SPLAT_MATERIAL = "PhysInteract splat colour"
LOOK_GROUP = "PhysInteract splat look"


def splat_material() -> bpy.types.Material:
    """The splats' own colours: emission of the per-point `displayColor` (the captured colour,
    lighting baked in as in the video), mixed by a `Lit` value towards a Principled BSDF of the
    same colour (0: as captured, 1: lit by the scene), and by each point's `opacity` towards
    transparent. Same nodes in Eevee and Cycles."""
    mat = bpy.data.materials.get(SPLAT_MATERIAL)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(SPLAT_MATERIAL)
    if mat.node_tree is None:  # Blender < 5: materials start without nodes
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    col = nt.nodes.new("ShaderNodeAttribute")
    col.attribute_type = "GEOMETRY"
    col.attribute_name = "displayColor"
    opa = nt.nodes.new("ShaderNodeAttribute")
    opa.attribute_type = "GEOMETRY"
    opa.attribute_name = "opacity"
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Roughness"].default_value = 0.8
    lit = nt.nodes.new("ShaderNodeValue")
    lit.name = lit.label = "Lit"
    lit.outputs[0].default_value = 0.0
    mix = nt.nodes.new("ShaderNodeMixShader")
    transparent = nt.nodes.new("ShaderNodeBsdfTransparent")
    alpha = nt.nodes.new("ShaderNodeMixShader")
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(col.outputs["Color"], emit.inputs["Color"])
    nt.links.new(col.outputs["Color"], bsdf.inputs["Base Color"])
    nt.links.new(lit.outputs[0], mix.inputs["Fac"])
    nt.links.new(emit.outputs["Emission"], mix.inputs[1])
    nt.links.new(bsdf.outputs["BSDF"], mix.inputs[2])
    nt.links.new(opa.outputs["Fac"], alpha.inputs["Fac"])
    nt.links.new(transparent.outputs["BSDF"], alpha.inputs[1])
    nt.links.new(mix.outputs["Shader"], alpha.inputs[2])
    nt.links.new(alpha.outputs["Shader"], out.inputs["Surface"])
    for n, xy in ((col, (0, 200)), (opa, (0, 400)), (lit, (0, -150)), (emit, (250, 200)), (bsdf, (250, -50)),
                  (mix, (500, 100)), (transparent, (500, 300)), (alpha, (750, 200)), (out, (1000, 200))):
        n.location = xy
    return mat


def look_group() -> bpy.types.NodeTree:
    """Geometry nodes: each point's radius (the splat's size, from the USD widths) times `Size`,
    and the splat material."""
    ng = bpy.data.node_groups.get(LOOK_GROUP)
    if ng is not None:
        return ng
    ng = bpy.data.node_groups.new(LOOK_GROUP, "GeometryNodeTree")
    ng.interface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    size = ng.interface.new_socket(name="Size", in_out="INPUT", socket_type="NodeSocketFloat")
    size.default_value, size.min_value, size.max_value = 1.0, 0.0, 10.0
    ng.interface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    n = ng.nodes
    gin, gout = n.new("NodeGroupInput"), n.new("NodeGroupOutput")
    radius = n.new("GeometryNodeInputNamedAttribute")
    radius.data_type = "FLOAT"
    radius.inputs["Name"].default_value = "radius"
    mul = n.new("ShaderNodeMath")
    mul.operation = "MULTIPLY"
    set_r = n.new("GeometryNodeSetPointRadius")
    set_m = n.new("GeometryNodeSetMaterial")
    set_m.inputs["Material"].default_value = splat_material()
    ng.links.new(gin.outputs[0], set_r.inputs["Points"])
    ng.links.new(radius.outputs["Attribute"], mul.inputs[0])
    ng.links.new(gin.outputs[1], mul.inputs[1])
    ng.links.new(mul.outputs[0], set_r.inputs["Radius"])
    ng.links.new(set_r.outputs["Points"], set_m.inputs["Geometry"])
    ng.links.new(set_m.outputs["Geometry"], gout.inputs[0])
    for node, x in ((gin, 0), (radius, 200), (mul, 400), (set_r, 600), (set_m, 800), (gout, 1000)):
        node.location = (x, 0)
    return ng


def apply_splat_look(obj, size: float = 1.0) -> None:
    """The splat cloud's look: the material, and the geometry-nodes modifier after its cache."""
    obj.data.materials.clear()
    obj.data.materials.append(splat_material())
    mod = obj.modifiers.get("PhysInteract look") or obj.modifiers.new("PhysInteract look", "NODES")
    mod.node_group = look_group()
    set_look_size(obj, size)


def set_look_size(obj, size: float) -> None:
    mod = obj.modifiers.get("PhysInteract look")
    if mod is None or mod.node_group is None:
        return
    for item in mod.node_group.interface.items_tree:
        if getattr(item, "in_out", "") == "INPUT" and item.name == "Size":
            mod[item.identifier] = float(size)
    obj.update_tag()


def evaluated_points(obj, depsgraph=None) -> dict:
    """Positions (world), radius and colour of a point cloud as evaluated (modifiers applied)."""
    dg = depsgraph or bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    pc = ev.data
    n = len(pc.points)
    co = np.empty(n * 3, np.float32)
    pc.attributes["position"].data.foreach_get("vector", co)
    m = np.array(ev.matrix_world)
    out = {"position": co.reshape(n, 3) @ m[:3, :3].T + m[:3, 3]}
    if "radius" in pc.attributes:
        out["radius"] = _attr_values(pc, "radius")
    if "displayColor" in pc.attributes and pc.attributes["displayColor"].data_type == "FLOAT_COLOR":
        c = np.empty(n * 4, np.float32)
        pc.attributes["displayColor"].data.foreach_get("color", c)
        out["color"] = c.reshape(n, 4)[:, :3]
    return out
