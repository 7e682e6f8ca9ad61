"""Writing and reading physinteract-usd stages: `init`'s layer (object, particles, camera, scene
settings) and `read_stage`, which composes a stage into plain `SceneData` (the core modules' input).
Layer paths and prim paths: `usd.layout`; contacts: `usd.contacts`; the fit layer: `usd.fit_io`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdVol, Vt

from ..camera import Camera
from ..errors import InputError
from ..gaussians import Gaussians
from ..scene import SceneData, SimSettings
from . import EFFECT_APIS
from .contacts import read_contacts
from . import validate as V
from .reports import REPORT_TYPE, read_report
from .versions import CURRENT_ATTR, list_versions
from .layout import (CAMERA, GENERATOR, MESH, OBJECT, PARTICLES, PRIMVAR_CONF, PRIMVAR_E, PRIMVAR_NU,
                     PRIMVAR_SURFACE, PRIMVAR_VOLUME, SCENE, SPLATS, WORLD, LayerPaths, atomic_outputs,
                     check_our_root, set_stage_metadata)

HORIZONTAL_APERTURE = 0.36  # film back width: 36 mm in tenths of a scene unit (metres); only the ratio to focalLength matters for projection


# ------------------------------------------------------------------------------------- camera I/O
def author_camera(stage: Usd.Stage, cam: Camera, path: Sdf.Path = CAMERA) -> UsdGeom.Camera:
    """A UsdGeom.Camera whose projection equals the pinhole camera (and cv2.projectPoints)."""
    ucam = UsdGeom.Camera.Define(stage, path)
    px = HORIZONTAL_APERTURE / cam.width           # film units per pixel, horizontally
    focal = cam.fx * px
    py = focal / cam.fy                             # film units per pixel, vertically
    ucam.CreateFocalLengthAttr(float(focal))
    ucam.CreateHorizontalApertureAttr(float(cam.width * px))
    ucam.CreateVerticalApertureAttr(float(cam.height * py))
    # the offsets move the film window: a principal point left of centre is a window shifted right
    ucam.CreateHorizontalApertureOffsetAttr(float((cam.width / 2.0 - cam.cx) * px))
    ucam.CreateVerticalApertureOffsetAttr(float((cam.cy - cam.height / 2.0) * py))
    ucam.CreateClippingRangeAttr(Gf.Vec2f(float(cam.near), float(cam.far)))
    ucam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    op = ucam.AddTransformOp()
    if cam.is_static:
        op.Set(Gf.Matrix4d(cam.c2w.T.tolist()))
    else:
        for k, m in enumerate(cam.c2w):
            op.Set(Gf.Matrix4d(m.T.tolist()), Usd.TimeCode(k))
    return ucam


def read_camera(stage: Usd.Stage, width: int, height: int, path: Sdf.Path = CAMERA,
                n_frames: int | None = None) -> Camera:
    prim = stage.GetPrimAtPath(path)
    if not prim or not prim.IsA(UsdGeom.Camera):
        raise InputError(stage.GetRootLayer().realPath, f"no camera at {path}")
    ucam = UsdGeom.Camera(prim)
    focal = ucam.GetFocalLengthAttr().Get()
    hap, vap = ucam.GetHorizontalApertureAttr().Get(), ucam.GetVerticalApertureAttr().Get()
    hoff, voff = ucam.GetHorizontalApertureOffsetAttr().Get(), ucam.GetVerticalApertureOffsetAttr().Get()
    px, py = hap / width, vap / height
    fx, fy = focal / px, focal / py
    cx, cy = width / 2.0 - hoff / px, height / 2.0 + voff / py
    xf = UsdGeom.Xformable(prim)
    near, far = ucam.GetClippingRangeAttr().Get()
    if xf.TransformMightBeTimeVarying():
        n = n_frames or 1
        poses = np.stack([np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode(k))).T for k in range(n)])
    else:
        poses = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
    return Camera(fx, fy, cx, cy, width, height, poses, near, far)


def project_with_usd_camera(stage: Usd.Stage, points: np.ndarray, width: int, height: int,
                            time=Usd.TimeCode.Default(), path: Sdf.Path = CAMERA) -> np.ndarray:
    """Project world points through USD's own camera model (Gf.Frustum): the independent check."""
    gcam = UsdGeom.Camera(stage.GetPrimAtPath(path)).GetCamera(time)
    fr = gcam.frustum
    m = fr.ComputeViewMatrix() * fr.ComputeProjectionMatrix()
    out = np.empty((len(points), 2))
    for i, p in enumerate(points):
        q = m.Transform(Gf.Vec3d(*map(float, p)))
        out[i] = ((q[0] + 1.0) * 0.5 * width, (1.0 - q[1]) * 0.5 * height)
    return out


# -------------------------------------------------------------------------------- Gaussians I/O
def author_splats(stage: Usd.Stage, g: Gaussians, path: Sdf.Path = SPLATS, time=None):
    splats = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
    prim = splats.GetPrim()
    tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    UsdVol.ParticleFieldPositionAttributeAPI(prim).CreatePositionsAttr().Set(
        Vt.Vec3fArray.FromNumpy(g.means.astype(np.float32)), tc)
    quats = Vt.QuatfArray([Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))) for q in g.quats])
    UsdVol.ParticleFieldOrientationAttributeAPI(prim).CreateOrientationsAttr().Set(quats, tc)
    UsdVol.ParticleFieldScaleAttributeAPI(prim).CreateScalesAttr().Set(
        Vt.Vec3fArray.FromNumpy(g.scales.astype(np.float32)), tc)
    UsdVol.ParticleFieldOpacityAttributeAPI(prim).CreateOpacitiesAttr().Set(
        Vt.FloatArray.FromNumpy(g.opacities.astype(np.float32)), tc)
    sh_api = UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI(prim)
    sh_api.CreateRadianceSphericalHarmonicsDegreeAttr().Set(int(g.sh_degree))
    sh_api.CreateRadianceSphericalHarmonicsCoefficientsAttr().Set(
        Vt.Vec3fArray.FromNumpy(g.sh.reshape(-1, 3).astype(np.float32)), tc)
    lo, hi = g.means.min(0) - 3 * g.scales.max(), g.means.max(0) + 3 * g.scales.max()
    UsdGeom.Boundable(prim).CreateExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]))
    UsdGeom.PrimvarsAPI(prim).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                            UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(g.colors.astype(np.float32)))
    return splats


def read_splats(stage: Usd.Stage, path: Sdf.Path = SPLATS) -> Gaussians:
    prim = stage.GetPrimAtPath(path)
    if not prim:
        raise InputError(stage.GetRootLayer().realPath, f"no Gaussian splats at {path}")
    means = np.array(UsdVol.ParticleFieldPositionAttributeAPI(prim).GetPositionsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
    q = UsdVol.ParticleFieldOrientationAttributeAPI(prim).GetOrientationsAttr().Get(Usd.TimeCode.Default())
    quats = np.array([[x.GetReal(), *x.GetImaginary()] for x in q], dtype=np.float64)
    scales = np.array(UsdVol.ParticleFieldScaleAttributeAPI(prim).GetScalesAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
    opac = np.array(UsdVol.ParticleFieldOpacityAttributeAPI(prim).GetOpacitiesAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
    sh_api = UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI(prim)
    deg = sh_api.GetRadianceSphericalHarmonicsDegreeAttr().Get()
    sh = np.array(sh_api.GetRadianceSphericalHarmonicsCoefficientsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
    sh = sh.reshape(len(means), (deg + 1) ** 2, 3)
    return Gaussians(means, scales, quats, opac, sh)


def author_mesh(stage: Usd.Stage, mesh, path: Sdf.Path = MESH) -> UsdGeom.Mesh:
    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(mesh.vertices, dtype=np.float32)))
    faces = np.asarray(mesh.faces, dtype=np.int32)
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*mesh.bounds[0]), Gf.Vec3f(*mesh.bounds[1])]))
    return m


# --------------------------------------------------------------------------------- write: init
def write_init_stage(path, capture, particles, settings: SimSettings, *, force: bool = False,
                     grid_choice: dict | None = None) -> LayerPaths:
    """Write scene.usda (if absent), scene.init.usdc and an empty scene.fit.usdc, atomically.
    `grid_choice`: how init chose the grid (app.init.GridChoice.to_dict()), kept in the init
    layer's customLayerData (physinteract.gridChoice) beside the other init provenance.

    An existing root layer is the user's: without `force` it is an error; with `force` the root is
    kept as is (their choices survive) and only the generated layers are replaced.
    """
    lp = LayerPaths.of(path)
    if lp.root.suffix.lower() not in (".usda", ".usd"):
        raise InputError(lp.root, "the stage's root layer must be a .usda (or .usd) file")
    if not lp.root.parent.exists():
        raise InputError(lp.root.parent, "output folder does not exist")
    root_exists = lp.root.exists()
    if root_exists:
        if not force:
            raise InputError(lp.root, "already exists: `init --force` replaces the generated layers "
                             "(scene.init.usdc) and keeps your root layer")
        check_our_root(lp.root)
    n = capture.n_frames
    fps = float(capture.fps)

    init = Sdf.Layer.CreateAnonymous("init.usdc")
    set_stage_metadata(init, fps, 0, n - 1)
    stage = Usd.Stage.Open(init)
    world = UsdGeom.Xform.Define(stage, WORLD)
    Usd.ModelAPI(world).SetKind("assembly")
    obj = UsdGeom.Xform.Define(stage, OBJECT)
    Usd.ModelAPI(obj).SetKind("component")
    g = capture.object.gaussians
    author_splats(stage, g)
    if capture.object.mesh is not None:
        author_mesh(stage, capture.object.mesh)
    pts = UsdGeom.Points.Define(stage, PARTICLES)
    pts.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(particles.positions.astype(np.float32)))
    pts.CreateWidthsAttr(Vt.FloatArray.FromNumpy(np.full(len(particles), particles.spacing, np.float32)))
    pts.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    lo, hi = particles.positions.min(0), particles.positions.max(0)
    pts.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]))
    pprim = pts.GetPrim()
    pprim.ApplyAPI("PhysInteractMaterialFieldAPI")
    pprim.GetAttribute("physinteract:constitutiveModel").Set(settings.constitutive_model)
    pprim.GetAttribute("physinteract:density").Set(float(settings.density))
    pv = UsdGeom.PrimvarsAPI(pprim)
    e0 = np.full(len(particles), np.sqrt(settings.youngs_min * settings.youngs_max), np.float32)
    pv.CreatePrimvar("physinteract:youngsModulus", Sdf.ValueTypeNames.FloatArray,
                     UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(e0))
    pv.CreatePrimvar("physinteract:poissonRatio", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
        Vt.FloatArray.FromNumpy(np.full(len(particles), settings.poisson_default, np.float32)))
    pv.CreatePrimvar("physinteract:volume", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
        Vt.FloatArray.FromNumpy(particles.volumes.astype(np.float32)))
    pv.CreatePrimvar("physinteract:isSurface", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
        Vt.IntArray.FromNumpy(particles.is_surface.astype(np.int32)))
    pv.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.constant).Set(
        Vt.Vec3fArray([Gf.Vec3f(0.8, 0.6, 0.3)]))

    author_camera(stage, capture.camera)
    scene = stage.DefinePrim(SCENE, "PhysInteractScene")
    root_dir = lp.root.parent.resolve()
    sa = lambda name, value: scene.GetAttribute(f"physinteract:{name}").Set(value)  # noqa: E731
    sa("generator", GENERATOR)
    sa("startFrame", 0)
    sa("endFrame", n - 1)
    sa("fps", fps)
    sa("imageResolution", Gf.Vec2i(capture.camera.width, capture.camera.height))
    sa("domainMin", Gf.Vec3f(*map(float, settings.domain_min)))
    sa("domainMax", Gf.Vec3f(*map(float, settings.domain_max)))
    sa("gridResolution", Gf.Vec3i(*map(int, settings.grid_resolution)))
    sa("cellSize", float(settings.cell_size))
    sa("particleSpacing", float(settings.particle_spacing))
    sa("substeps", int(settings.substeps))
    sa("transferTau", float(settings.transfer_tau))
    if getattr(settings, "preload", False) is not None:     # None: left unauthored, the fit decides
        sa("preload", bool(settings.preload))
    sa("youngsModulusMin", float(settings.youngs_min))
    sa("youngsModulusMax", float(settings.youngs_max))
    sa("poissonRatioDefault", float(settings.poisson_default))
    sa("poissonRatioMax", float(settings.poisson_max))
    sa("gravity", Gf.Vec3f(*settings.gravity))
    from ..frames import VideoFile

    if isinstance(capture.frames, VideoFile):
        sa("video", Sdf.AssetPath(_rel(capture.frames.path, root_dir)))
    else:
        sa("frames", Sdf.AssetPathArray([Sdf.AssetPath(_rel(p, root_dir)) for p in capture.frames.paths]))
    if capture.masks:
        sa("masks", Sdf.AssetPathArray([Sdf.AssetPath(_rel(p, root_dir)) for p in capture.masks]))
    sa("masksAmodal", bool(capture.masks_amodal))
    scene.GetRelationship("physinteract:object").SetTargets([OBJECT])
    scene.GetRelationship("physinteract:particles").SetTargets([PARTICLES])
    scene.GetRelationship("physinteract:camera").SetTargets([CAMERA])
    init.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "init",
                                             "objectFile": _rel(capture.object.path, root_dir),
                                             "fpsSource": str(capture.fps_source)}}
    if grid_choice:
        d = dict(init.customLayerData)
        d["physinteract"] = {**d["physinteract"], "gridChoice": dict(grid_choice)}
        init.customLayerData = d

    fit = Sdf.Layer.CreateAnonymous("fit.usdc")
    set_stage_metadata(fit, fps, 0, n - 1)
    fit.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "fit"}}

    outputs = [lp.init, lp.fit] + ([] if root_exists else [lp.root])
    with atomic_outputs(*outputs) as tmps:
        if not init.Export(str(tmps[0])) or not fit.Export(str(tmps[1])):
            raise OSError(f"{lp.init}: could not write the stage layers")
        if not root_exists:
            root = Sdf.Layer.CreateAnonymous("root.usda")
            set_stage_metadata(root, fps, 0, n - 1)
            root.subLayerPaths.append(f"./{lp.fit.name}")
            root.subLayerPaths.append(f"./{lp.init.name}")
            root.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "root"}}
            root.documentation = ("physinteract-usd stage. Your layer: effects and overrides you author "
                                  "here win over the generated sublayers.")
            if not root.Export(str(tmps[2])):
                raise OSError(f"{lp.root}: could not write the root layer")
    return lp


def _rel(p, root_dir: Path) -> str:
    p = Path(p).resolve()
    try:
        return "./" + p.relative_to(root_dir).as_posix()
    except ValueError:
        return os.path.relpath(p, root_dir).replace(os.sep, "/")


# ----------------------------------------------------------------------------------------- read
def _usd_error_text(exc) -> str:
    """The first message of a USD (Tf) error, without its C++ location: "x.usda:2:3: Expected ) ..."."""
    for line in str(exc).splitlines():
        line = line.strip()
        if not line:
            continue
        if " : '" in line:
            line = line.split(" : '", 1)[1].rstrip("'").strip()
        return line
    return type(exc).__name__


def open_stage(path) -> Usd.Stage:
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    # USD skips a sublayer it cannot read with a warning: a corrupt layer would read as missing data
    try:
        root = Sdf.Layer.FindOrOpen(str(path))
    except Exception:  # noqa: BLE001  (the stage's own open below says what is wrong)
        root = None
    for sub in root.subLayerPaths if root is not None else ():
        sub_path = Path(root.ComputeAbsolutePath(sub))
        if sub_path.exists():
            try:
                ok = Sdf.Layer.FindOrOpen(str(sub_path)) is not None
            except Exception:  # noqa: BLE001
                ok = False
            if not ok:
                raise InputError(sub_path, f"cannot be read as a USD layer (a sublayer of {path.name})")
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as exc:  # Tf errors surface as RuntimeError-ish
        raise InputError(path, f"cannot be opened as a USD stage ({_usd_error_text(exc)})") from None
    if stage is None:
        raise InputError(path, "cannot be opened as a USD stage")
    prim = stage.GetPrimAtPath(SCENE)
    if not prim or prim.GetTypeName() != "PhysInteractScene":
        raise InputError(path, "not a physinteract-usd stage (no PhysInteractScene prim at "
                         "/World/PhysInteract): run `physinteract-usd init` to make one")
    return stage


def read_stage(path) -> SceneData:
    """Read a physinteract-usd stage into a SceneData."""
    path = Path(path)
    stage = open_stage(path)
    scene = stage.GetPrimAtPath(SCENE)
    ga = lambda name: scene.GetAttribute(f"physinteract:{name}").Get()  # noqa: E731
    root_file = str(path)
    V.check_scene_prim(scene, root_file)   # every authored value is checked before it is used
    w, h = ga("imageResolution")
    start, end = int(ga("startFrame")), int(ga("endFrame"))
    cam_prim = stage.GetPrimAtPath(CAMERA)
    if cam_prim and cam_prim.IsA(UsdGeom.Camera):
        V.check_camera_pose(cam_prim, root_file, end + 1)
    cam = read_camera(stage, int(w), int(h), n_frames=end + 1)
    pprim = stage.GetPrimAtPath(PARTICLES)
    if not pprim:
        raise InputError(path, f"no simulation particles at {PARTICLES}")
    e_range = (float(ga("youngsModulusMin")), float(ga("youngsModulusMax")))
    n_particles = V.check_particles(pprim, root_file, e_range, float(ga("poissonRatioMax")))
    sprim = stage.GetPrimAtPath(SPLATS)
    if sprim:
        V.check_splats(sprim, root_file, e_range, float(ga("poissonRatioMax")))
    V.check_contact_indices(scene, root_file, n_particles)
    g = read_splats(stage)
    pts = np.array(UsdGeom.Points(pprim).GetPointsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)

    def pv(prim, name, default=None):
        attr = prim.GetAttribute(name)
        v = attr.Get(Usd.TimeCode.Default()) if attr and attr.HasValue() else None
        return default if v is None else np.array(v)

    settings = SimSettings(
        domain_min=np.array(ga("domainMin"), dtype=np.float64), domain_max=np.array(ga("domainMax"), dtype=np.float64),
        grid_resolution=tuple(int(x) for x in ga("gridResolution")), cell_size=float(ga("cellSize")),
        particle_spacing=float(ga("particleSpacing")), substeps=int(ga("substeps")),
        youngs_min=float(ga("youngsModulusMin")), youngs_max=float(ga("youngsModulusMax")),
        poisson_default=float(ga("poissonRatioDefault")), poisson_max=float(ga("poissonRatioMax")),
        density=float(pprim.GetAttribute("physinteract:density").Get()),
        gravity=tuple(float(x) for x in ga("gravity")),
        constitutive_model=str(pprim.GetAttribute("physinteract:constitutiveModel").Get()),
        transfer_tau=float(ga("transferTau") or 0.0), preload=_authored_bool(scene, "physinteract:preload"))
    effects = {}
    for name, api in EFFECT_APIS.items():
        if scene.HasAPI(api):
            params = {}
            for prop in scene.GetPrimDefinition().GetPropertyNames():
                if prop.startswith(f"physinteract:{name}:"):
                    params[prop.split(":")[-1]] = scene.GetAttribute(prop).Get()
            effects[name] = params
    contacts, trajectories = read_contacts(scene)
    reports, current = stage_versions(path, stage)
    frames = [a.path for a in (ga("frames") or [])]
    masks = [a.path for a in (ga("masks") or [])]
    video = ga("video")
    e = pv(pprim, PRIMVAR_E)
    nu = pv(pprim, PRIMVAR_NU)
    return SceneData(
        path=path, fps=float(ga("fps")), start_frame=start, end_frame=end, image_size=(int(w), int(h)),
        camera=cam, gaussians=g, particles_positions=pts,
        particles_volumes=pv(pprim, PRIMVAR_VOLUME, np.full(len(pts), settings.particle_spacing ** 3)),
        particles_surface=pv(pprim, PRIMVAR_SURFACE, np.zeros(len(pts), int)).astype(bool),
        youngs_modulus=e if e is not None else np.full(len(pts), np.sqrt(settings.youngs_min * settings.youngs_max)),
        poisson_ratio=nu if nu is not None else np.full(len(pts), settings.poisson_default),
        confidence=pv(pprim, PRIMVAR_CONF), settings=settings,
        frame_assets=[_resolve(path, a) for a in frames], video_asset=_resolve(path, video.path) if video and video.path else None,
        mask_assets=[_resolve(path, a) for a in masks], masks_amodal=bool(ga("masksAmodal")),
        hand_mask_assets=[_resolve(path, a.path) for a in (ga("handMasks") or [])],
        effects=effects, contacts=contacts, trajectories=trajectories, reports=reports,
        generator=str(ga("generator")), object_kind="mesh" if stage.GetPrimAtPath(MESH) else "gaussians",
        current_version=current)


def _authored_bool(prim, name: str) -> bool | None:
    """A bool attribute's authored value, None where no layer authors it (the schema's fallback not taken)."""
    attr = prim.GetAttribute(name)
    return bool(attr.Get()) if attr and attr.HasAuthoredValue() else None


def _resolve(stage_path: Path, asset: str) -> str:
    p = Path(asset)
    return str(p if p.is_absolute() else (stage_path.parent / p).resolve())


def read_grid_choice(stage_path) -> dict | None:
    """How init chose the grid (its init layer's customLayerData physinteract.gridChoice), None for
    a stage written before init recorded it."""
    lp = LayerPaths.of(Path(stage_path))
    layer = Sdf.Layer.FindOrOpen(str(lp.init)) if lp.init.exists() else None
    if layer is None:
        return None
    d = dict(layer.customLayerData).get("physinteract") or {}
    g = d.get("gridChoice")
    return dict(g) if g else None


# ------------------------------------------------------------------------------------- versions
def frame_range(stage_path) -> tuple[float, int]:
    """(fps, frame count) of a stage, read without checking the rest of it."""
    stage = open_stage(stage_path)
    scene = stage.GetPrimAtPath(SCENE)
    g = lambda n: scene.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
    fps, start, end = g("fps"), g("startFrame"), g("endFrame")
    return float(fps or 24.0), int((end or 0) - (start or 0) + 1)


def stage_versions(stage_path, stage: Usd.Stage | None = None) -> tuple[list[dict], int | None]:
    """(every version as `list_versions` gives it, the current version) from the composed stage
    (`stage`: already open), without checking the rest of it."""
    stage = stage or open_stage(stage_path)
    scene = stage.GetPrimAtPath(SCENE)
    reports = [read_report(ch) for ch in scene.GetChildren() if ch.GetTypeName() == REPORT_TYPE]
    cur_attr = scene.GetAttribute(CURRENT_ATTR)
    if cur_attr and cur_attr.HasAuthoredValue():
        current = int(cur_attr.Get()) or None
    else:  # a stage fitted before versions existed shows its newest fit
        current = max((r["version"] for r in reports), default=None)
    return list_versions(stage_path, reports, current), current
