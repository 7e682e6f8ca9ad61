"""Writing and reading physinteract-usd stages (the design's layout and layers).

```
scene.usda            the user's thin root: stage metadata, their choices (effects, overrides),
                      subLayers = [./scene.fit.usdc, ./scene.init.usdc]
scene.init.usdc       written by `init`: object, particles, camera, PhysInteractScene
scene.fit.usdc        written by `fit` / `extract` / `simulate` (empty after `init`)
```
Files are written atomically (temp file + rename); nothing the user authored is overwritten.
"""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdVol, Vt

from .. import __version__
from ..camera import Camera
from ..errors import InputError
from ..gaussians import Gaussians
from ..scene import ContactSet, SceneData, SimSettings, Trajectory
from . import EFFECT_APIS

GENERATOR = f"physinteract-usd {__version__}"
WORLD = Sdf.Path("/World")
OBJECT = Sdf.Path("/World/Object")
SPLATS = Sdf.Path("/World/Object/Splats")
PARTICLES = Sdf.Path("/World/Object/SimParticles")
MESH = Sdf.Path("/World/Object/Mesh")
CAMERA = Sdf.Path("/World/Camera")
SCENE = Sdf.Path("/World/PhysInteract")
HORIZONTAL_APERTURE = 0.36  # film back width: 36 mm in tenths of a scene unit (metres); only the ratio to focalLength matters for projection

PRIMVAR_E = "primvars:physinteract:youngsModulus"
PRIMVAR_NU = "primvars:physinteract:poissonRatio"
PRIMVAR_CONF = "primvars:physinteract:confidence"
PRIMVAR_VOLUME = "primvars:physinteract:volume"
PRIMVAR_BINDING = "primvars:physinteract:particleIndex"
PRIMVAR_SURFACE = "primvars:physinteract:isSurface"


# ------------------------------------------------------------------------------------ layer paths
@dataclass(frozen=True)
class LayerPaths:
    root: Path
    init: Path
    fit: Path

    @staticmethod
    def of(root) -> "LayerPaths":
        root = Path(root)
        stem = root.name[: -len(root.suffix)] if root.suffix else root.name
        return LayerPaths(root, root.with_name(f"{stem}.init.usdc"), root.with_name(f"{stem}.fit.usdc"))


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")


@contextlib.contextmanager
def atomic_outputs(*paths: Path):
    """Yield temp paths for `paths`; on success rename them all into place, on error remove them."""
    tmps = [_tmp_name(Path(p)) for p in paths]
    try:
        yield tmps
        for t, p in zip(tmps, paths):
            os.replace(t, p)
    finally:
        for t in tmps:
            with contextlib.suppress(FileNotFoundError):
                t.unlink()


def _set_stage_metadata(layer: Sdf.Layer, fps: float, start: int, end: int) -> None:
    layer.defaultPrim = "World"
    layer.timeCodesPerSecond = fps
    layer.framesPerSecond = fps
    layer.startTimeCode = start
    layer.endTimeCode = end
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)


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
def write_init_stage(path, capture, particles, settings: SimSettings, *, force: bool = False) -> LayerPaths:
    """Write scene.usda (if absent), scene.init.usdc and an empty scene.fit.usdc, atomically.

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
    _set_stage_metadata(init, fps, 0, n - 1)
    stage = Usd.Stage.Open(init)
    world = UsdGeom.Xform.Define(stage, WORLD)
    Usd.ModelAPI(world).SetKind("assembly")
    obj = UsdGeom.Xform.Define(stage, OBJECT)
    Usd.ModelAPI(obj).SetKind("component")
    g = capture.object.gaussians
    splats = author_splats(stage, g)
    UsdGeom.PrimvarsAPI(splats.GetPrim()).CreatePrimvar(
        "physinteract:particleIndex", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
        Vt.IntArray.FromNumpy(particles.binding.astype(np.int32)))
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

    fit = Sdf.Layer.CreateAnonymous("fit.usdc")
    _set_stage_metadata(fit, fps, 0, n - 1)
    fit.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "fit"}}

    outputs = [lp.init, lp.fit] + ([] if root_exists else [lp.root])
    with atomic_outputs(*outputs) as tmps:
        if not init.Export(str(tmps[0])) or not fit.Export(str(tmps[1])):
            raise OSError(f"{lp.init}: could not write the stage layers")
        if not root_exists:
            root = Sdf.Layer.CreateAnonymous("root.usda")
            _set_stage_metadata(root, fps, 0, n - 1)
            root.subLayerPaths.append(f"./{lp.fit.name}")
            root.subLayerPaths.append(f"./{lp.init.name}")
            root.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "root"}}
            root.documentation = ("physinteract-usd stage. Your layer: effects and overrides you author "
                                  "here win over the generated sublayers.")
            if not root.Export(str(tmps[2])):
                raise OSError(f"{lp.root}: could not write the root layer")
    return lp


def check_our_root(path: Path) -> Sdf.Layer:
    layer = Sdf.Layer.FindOrOpen(str(path))
    if layer is None:
        raise InputError(path, "cannot be opened as a USD layer")
    data = dict(layer.customLayerData).get("physinteract")
    subs = [Path(s).name for s in layer.subLayerPaths]
    lp = LayerPaths.of(path)
    if data is None and lp.init.name not in subs:
        raise InputError(path, "not a physinteract-usd stage (no physinteract layer data and no "
                         f"{lp.init.name} sublayer): written by another tool")
    return layer


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
    w, h = ga("imageResolution")
    start, end = int(ga("startFrame")), int(ga("endFrame"))
    cam = read_camera(stage, int(w), int(h), n_frames=end + 1)
    g = read_splats(stage)
    pprim = stage.GetPrimAtPath(PARTICLES)
    if not pprim:
        raise InputError(path, f"no simulation particles at {PARTICLES}")
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
        constitutive_model=str(pprim.GetAttribute("physinteract:constitutiveModel").Get()))
    splats = stage.GetPrimAtPath(SPLATS)
    binding = pv(splats, PRIMVAR_BINDING)
    if binding is None or len(binding) != len(g):
        raise InputError(path, "the splats' primvars:physinteract:particleIndex binding is missing or "
                         "has the wrong length")
    effects = {}
    for name, api in EFFECT_APIS.items():
        if scene.HasAPI(api):
            params = {}
            for prop in scene.GetPrimDefinition().GetPropertyNames():
                if prop.startswith(f"physinteract:{name}:"):
                    params[prop.split(":")[-1]] = scene.GetAttribute(prop).Get()
            effects[name] = params
    contacts, trajectories, reports = [], [], []
    for child in scene.GetChildren():
        t = child.GetTypeName()
        if t == "PhysInteractContactSet":
            ca = lambda n: child.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
            idx = ca("particleIndices")
            contacts.append(ContactSet(child.GetName(), np.array(idx if idx is not None else [], dtype=np.int64),
                                       str(ca("contactType")), float(ca("graspTime")), float(ca("releaseTime")),
                                       str(ca("source")), float(ca("colliderRadius")), np.array(ca("contactPoint")),
                                       tuple(float(x) for x in ca("contactNormal")), float(ca("friction")),
                                       bool(ca("extentGuessed"))))
        elif t == "PhysInteractTrajectory":
            pos_attr = child.GetAttribute("physinteract:position")
            times = pos_attr.GetTimeSamples()
            pos = np.array([pos_attr.Get(tc) for tc in times], dtype=np.float64).reshape(-1, 3)
            vel_attr = child.GetAttribute("physinteract:velocity")
            vel = (np.array([vel_attr.Get(tc) for tc in times], dtype=np.float64).reshape(-1, 3)
                   if vel_attr.GetNumTimeSamples() == len(times) and times else None)
            targets = child.GetRelationship("physinteract:contactSet").GetTargets()
            trajectories.append(Trajectory(child.GetName(), targets[0].name if targets else "",
                                           np.array(times, dtype=np.float64), pos, vel,
                                           str(child.GetAttribute("physinteract:stage").Get())))
        elif t == "PhysInteractFitReport":
            reports.append(_read_report(child))
    reports.sort(key=lambda r: r["version"])
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
        binding=binding.astype(np.int64),
        youngs_modulus=e if e is not None else np.full(len(pts), np.sqrt(settings.youngs_min * settings.youngs_max)),
        poisson_ratio=nu if nu is not None else np.full(len(pts), settings.poisson_default),
        confidence=pv(pprim, PRIMVAR_CONF), settings=settings,
        frame_assets=[_resolve(path, a) for a in frames], video_asset=_resolve(path, video.path) if video and video.path else None,
        mask_assets=[_resolve(path, a) for a in masks], masks_amodal=bool(ga("masksAmodal")),
        hand_mask_assets=[_resolve(path, a.path) for a in (ga("handMasks") or [])],
        effects=effects, contacts=contacts, trajectories=trajectories, reports=reports,
        generator=str(ga("generator")), object_kind="mesh" if stage.GetPrimAtPath(MESH) else "gaussians")


def _resolve(stage_path: Path, asset: str) -> str:
    p = Path(asset)
    return str(p if p.is_absolute() else (stage_path.parent / p).resolve())


def _read_report(prim) -> dict:
    g = lambda n: prim.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
    arr = lambda n: list(g(n) or [])  # noqa: E731
    settings = g("settings") or ""
    params = g("effectParameters") or ""
    return {"name": prim.GetName(), "version": int(g("version")), "effects": [str(x) for x in arr("effects")],
            "frames": [int(x) for x in arr("frameIndices")], "psnr": arr("framePsnr"),
            "psnr_masked": arr("framePsnrMasked"), "ssim": arr("frameSsim"), "iou": arr("frameIou"),
            "loss_history": arr("lossHistory"), "final_loss": float(g("finalLoss")),
            "runtime_s": float(g("runtimeSeconds")), "device": str(g("device")),
            "settings": json.loads(settings) if settings else {},
            "effect_parameters": json.loads(params) if params else {}}


# ---------------------------------------------------------------------------------- write: fit
REPORT_PREFIX = "FitReport_v"


def _open_or_new_fit_layer(lp: LayerPaths, fps: float, n: int):
    """A fresh anonymous fit layer carrying over the previous FitReport prims (one per version)."""
    new = Sdf.Layer.CreateAnonymous("fit.usdc")
    _set_stage_metadata(new, fps, 0, n - 1)
    versions = []
    if lp.fit.exists():
        old = Sdf.Layer.FindOrOpen(str(lp.fit))
        if old is not None:
            scene_spec = old.GetPrimAtPath(SCENE)
            if scene_spec is not None:
                for child in scene_spec.nameChildren:
                    if child.typeName == "PhysInteractFitReport":
                        Sdf.CreatePrimInLayer(new, child.path)
                        Sdf.CopySpec(old, child.path, new, child.path)
                        attr = child.attributes.get("physinteract:version")
                        versions.append(int(attr.default) if attr is not None and attr.default is not None else 1)
                # what extraction found besides contacts (the hand's pixels per frame) stays
                hm = scene_spec.attributes.get("physinteract:handMasks")
                if hm is not None and hm.default is not None:
                    spec = new.GetPrimAtPath(SCENE) or Sdf.CreatePrimInLayer(new, SCENE)
                    a = Sdf.AttributeSpec(spec, "physinteract:handMasks", Sdf.ValueTypeNames.AssetArray)
                    a.default = hm.default
    return new, versions


def _splat_samples(covs: np.ndarray):
    from ..render.deform import scales_quats_from_covariance

    T, N = covs.shape[:2]
    s, q = scales_quats_from_covariance(covs.reshape(-1, 3, 3))
    return s.reshape(T, N, 3), q.reshape(T, N, 4)


def write_fit_layer(stage_path, scene: SceneData, result, contacts, *, source: str = "extracted",
                    effect_parameters: dict | None = None) -> dict:
    """Write the fit into scene.fit.usdc (atomically), keeping earlier versions' reports.

    Authors: the material field (primvars on SimParticles and, per Gaussian, on Splats), the
    confidence, the contacts used and the fitted trajectories, the simulated animation
    (time-sampled SimParticles points and Splats positions / orientations / scales), and a
    PhysInteractFitReport for this model version. Returns {"version", "layer"}.
    """
    lp = LayerPaths.of(stage_path)
    n = scene.n_frames
    layer, versions = _open_or_new_fit_layer(lp, scene.fps, n)
    version = max(versions, default=0) + 1
    stage = Usd.Stage.Open(layer)
    f32 = lambda a: Vt.FloatArray.FromNumpy(np.asarray(a, np.float32))  # noqa: E731

    # material on particles, animated points
    pts = stage.OverridePrim(PARTICLES)
    pv = UsdGeom.PrimvarsAPI(pts)
    for name, vals in (("youngsModulus", result.youngs), ("poissonRatio", result.poisson),
                       ("confidence", result.confidence)):
        pv.CreatePrimvar(f"physinteract:{name}", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(f32(vals))
    pattr = pts.CreateAttribute("points", Sdf.ValueTypeNames.Point3fArray)
    for k in range(len(result.positions)):
        pattr.Set(Vt.Vec3fArray.FromNumpy(result.positions[k].astype(np.float32)), Usd.TimeCode(k))
    ext = pts.CreateAttribute("extent", Sdf.ValueTypeNames.Float3Array)
    for k in range(len(result.positions)):
        lo, hi = result.positions[k].min(0), result.positions[k].max(0)
        ext.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), Usd.TimeCode(k))

    # material per Gaussian (input PLY order), deformed splats
    spl = stage.OverridePrim(SPLATS)
    spv = UsdGeom.PrimvarsAPI(spl)
    for name, vals in (("youngsModulus", result.youngs_gaussian), ("poissonRatio", result.poisson_gaussian),
                       ("confidence", result.confidence_gaussian)):
        spv.CreatePrimvar(f"physinteract:{name}", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(f32(vals))
    scales, quats = _splat_samples(result.gaussian_covs)
    a_pos = spl.CreateAttribute("positions", Sdf.ValueTypeNames.Point3fArray)
    a_rot = spl.CreateAttribute("orientations", Sdf.ValueTypeNames.QuatfArray)
    a_scl = spl.CreateAttribute("scales", Sdf.ValueTypeNames.Float3Array)
    for k in range(len(result.gaussian_means)):
        tc = Usd.TimeCode(k)
        a_pos.Set(Vt.Vec3fArray.FromNumpy(result.gaussian_means[k].astype(np.float32)), tc)
        a_rot.Set(Vt.QuatfArray([Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))) for q in quats[k]]), tc)
        a_scl.Set(Vt.Vec3fArray.FromNumpy(scales[k].astype(np.float32)), tc)

    # contacts and trajectories
    scene_prim = stage.OverridePrim(SCENE)
    dt = 1.0 / scene.fps
    for c in contacts:
        cp = stage.DefinePrim(SCENE.AppendChild(c.name), "PhysInteractContactSet")
        cp.GetAttribute("physinteract:particleIndices").Set(Vt.IntArray.FromNumpy(np.asarray(c.indices, np.int32)))
        cp.GetAttribute("physinteract:contactType").Set(c.type)
        cp.GetAttribute("physinteract:graspTime").Set(float(c.grasp_frame))
        cp.GetAttribute("physinteract:releaseTime").Set(float(c.release_frame) if c.release_frame is not None else 1e9)
        # each contact keeps where it came from (a user's set stays the user's); a fit from the
        # ground truth marks all of them
        cp.GetAttribute("physinteract:source").Set(source if source != "extracted" else c.source)
        cp.GetAttribute("physinteract:colliderRadius").Set(float(c.radius))
        cp.GetAttribute("physinteract:contactNormal").Set(Gf.Vec3f(*map(float, c.normal)))
        cp.GetAttribute("physinteract:friction").Set(float(c.friction))
        if c.type == "fixed":
            cp.GetAttribute("physinteract:extentGuessed").Set(bool(c.guessed))
        if len(c.indices):
            cp.GetAttribute("physinteract:contactPoint").Set(Gf.Vec3f(*map(float, scene.particles_positions[c.indices].mean(0))))
        for stage_name, traj in (("initial", c.trajectory), ("fitted", result.trajectories.get(c.name))):
            if traj is None:
                continue
            tp = stage.DefinePrim(SCENE.AppendChild(f"{c.name}_{stage_name}"), "PhysInteractTrajectory")
            tp.GetAttribute("physinteract:stage").Set(stage_name)
            tp.GetRelationship("physinteract:contactSet").SetTargets([cp.GetPath()])
            traj = np.asarray(traj, np.float64)
            vel = np.vstack([np.diff(traj, axis=0) / dt, np.zeros((1, 3))])
            for k in range(len(traj)):
                tp.GetAttribute("physinteract:position").Set(Gf.Vec3f(*map(float, traj[k])), Usd.TimeCode(k))
                tp.GetAttribute("physinteract:velocity").Set(Gf.Vec3f(*map(float, vel[k])), Usd.TimeCode(k))

    # the report of this version
    rp = stage.DefinePrim(SCENE.AppendChild(f"{REPORT_PREFIX}{version}"), "PhysInteractFitReport")
    fm = result.frame_metrics
    ra = lambda name, v: rp.GetAttribute(f"physinteract:{name}").Set(v)  # noqa: E731
    ra("version", version)
    ra("effects", Vt.TokenArray(sorted(result.effects)))
    ra("frameIndices", Vt.IntArray([int(f["frame"]) for f in fm]))
    for key, attr in (("psnr", "framePsnr"), ("psnr_masked", "framePsnrMasked"), ("ssim", "frameSsim"),
                      ("iou", "frameIou")):
        ra(attr, f32([min(float(f[key]), 100.0) if np.isfinite(f[key]) else 100.0 for f in fm]))
    ra("lossHistory", f32(result.loss_history))
    ra("finalLoss", float(result.final_loss))
    ra("runtimeSeconds", float(result.runtime_s))
    ra("device", str(result.device))
    ra("settings", json.dumps(result.settings, default=_json_default))
    ra("effectParameters", json.dumps(effect_parameters or {}, default=_json_default))
    del scene_prim
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "fit", "version": version}}
    with atomic_outputs(lp.fit) as (tmp,):
        if not layer.Export(str(tmp)):
            raise OSError(f"{lp.fit}: could not write the fit layer")
    return {"version": version, "layer": str(lp.fit)}


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def read_splat_animation(path) -> dict:
    """The composed Splats per frame (positions, orientations, scales), their per-Gaussian
    primvars, and the time codes: what a fitted (or simulated) stage shows."""
    stage = open_stage(path)
    prim = stage.GetPrimAtPath(SPLATS)
    pos_a = UsdVol.ParticleFieldPositionAttributeAPI(prim).GetPositionsAttr()
    rot_a = UsdVol.ParticleFieldOrientationAttributeAPI(prim).GetOrientationsAttr()
    scl_a = UsdVol.ParticleFieldScaleAttributeAPI(prim).GetScalesAttr()
    times = pos_a.GetTimeSamples()
    out = {"times": list(times), "positions": [], "quats": [], "scales": []}
    for t in times:
        tc = Usd.TimeCode(t)
        out["positions"].append(np.array(pos_a.Get(tc), dtype=np.float64))
        out["quats"].append(np.array([[q.GetReal(), *q.GetImaginary()] for q in rot_a.Get(tc)], dtype=np.float64))
        out["scales"].append(np.array(scl_a.Get(tc), dtype=np.float64))
    for name in ("youngsModulus", "poissonRatio", "confidence"):
        a = prim.GetAttribute(f"primvars:physinteract:{name}")
        out[name] = np.array(a.Get(), dtype=np.float64) if a and a.HasValue() else None
    return out


# -------------------------------------------------------------------------------- write: simulate
def write_simulation_layer(stage_path, scene: SceneData, name: str, positions, gaussian_means,
                           gaussian_covs, fps: float, spec: dict) -> dict:
    """A re-simulation under a new interaction as its own time-sampled layer
    `<stem>.sim.<name>.usdc`, and a small stage `<stem>.sim.<name>.usda` that puts it over the
    fitted stage (your root layer is not touched). Returns the two paths."""
    lp = LayerPaths.of(stage_path)
    stem = lp.root.name[: -len(lp.root.suffix)] if lp.root.suffix else lp.root.name
    layer_path = lp.root.with_name(f"{stem}.sim.{name}.usdc")
    view_path = lp.root.with_name(f"{stem}.sim.{name}.usda")
    n = len(positions)
    layer = Sdf.Layer.CreateAnonymous("sim.usdc")
    _set_stage_metadata(layer, fps, 0, n - 1)
    stage = Usd.Stage.Open(layer)
    pts = stage.OverridePrim(PARTICLES)
    pattr = pts.CreateAttribute("points", Sdf.ValueTypeNames.Point3fArray)
    for k in range(n):
        pattr.Set(Vt.Vec3fArray.FromNumpy(np.asarray(positions[k], np.float32)), Usd.TimeCode(k))
    spl = stage.OverridePrim(SPLATS)
    scales, quats = _splat_samples(np.asarray(gaussian_covs))
    a_pos = spl.CreateAttribute("positions", Sdf.ValueTypeNames.Point3fArray)
    a_rot = spl.CreateAttribute("orientations", Sdf.ValueTypeNames.QuatfArray)
    a_scl = spl.CreateAttribute("scales", Sdf.ValueTypeNames.Float3Array)
    for k in range(n):
        tc = Usd.TimeCode(k)
        a_pos.Set(Vt.Vec3fArray.FromNumpy(np.asarray(gaussian_means[k], np.float32)), tc)
        a_rot.Set(Vt.QuatfArray([Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))) for q in quats[k]]), tc)
        a_scl.Set(Vt.Vec3fArray.FromNumpy(scales[k].astype(np.float32)), tc)
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "simulation", "name": name,
                                              "interaction": json.dumps(spec, default=_json_default)}}
    view = Sdf.Layer.CreateAnonymous("view.usda")
    _set_stage_metadata(view, fps, 0, n - 1)
    view.subLayerPaths.append(f"./{layer_path.name}")
    view.subLayerPaths.append(f"./{lp.root.name}")
    view.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "simulationView", "name": name}}
    with atomic_outputs(layer_path, view_path) as (t1, t2):
        if not layer.Export(str(t1)) or not view.Export(str(t2)):
            raise OSError(f"{layer_path}: could not write the simulation layer")
    return {"layer": str(layer_path), "stage": str(view_path)}


# ------------------------------------------------------------------------------------------ export
def export_stage(stage_path, out_path) -> str:
    """Flatten the composed stage into one self-contained file (.usd/.usdc/.usda or .usdz).

    Asset paths (frames, masks) are rewritten relative to the output; the animation, material
    primvars and every prim are kept. Blender imports the result's SimParticles as an animated
    point cloud."""
    from pxr import UsdUtils

    out = Path(out_path)
    ext = out.suffix.lower()
    if ext not in (".usd", ".usdc", ".usda", ".usdz"):
        raise InputError(out, "the output must end in .usd, .usdc, .usda or .usdz")
    if not out.parent.exists():
        raise InputError(out.parent, "output folder does not exist")
    src = Path(stage_path).resolve()
    stage = open_stage(stage_path)
    # every layer the stage is made of (a simulation view's layer too), and the ones it will have
    own = {p.resolve() for p in (src, *LayerPaths.of(src).__dict__.values()) if isinstance(p, Path)}
    own |= {Path(lay.realPath).resolve() for lay in stage.GetUsedLayers() if lay.realPath}
    if out.resolve() in own:
        raise InputError(out, "would overwrite a layer of the stage itself")
    flat = stage.Flatten()
    src_dir = src.parent
    out_dir = out.resolve().parent

    def rebase(p: str) -> str:
        if not p or "://" in p or p.startswith("@"):
            return p
        ap = Path(p) if Path(p).is_absolute() else (src_dir / p).resolve()
        return os.path.relpath(ap, out_dir).replace(os.sep, "/")

    UsdUtils.ModifyAssetPaths(flat, rebase)
    flat.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "export", "source": str(src)}}
    if ext == ".usdz":
        import tempfile

        # a package holds what it references: the capture's frames and masks stay outside it
        spec = flat.GetPrimAtPath(SCENE)
        if spec is not None:
            for name in ("physinteract:frames", "physinteract:masks", "physinteract:handMasks", "physinteract:video"):
                if name in spec.attributes:
                    spec.RemoveProperty(spec.attributes[name])

        with tempfile.TemporaryDirectory() as td:
            inner = Path(td) / (out.stem + ".usdc")
            if not flat.Export(str(inner)):
                raise OSError(f"{out}: could not write")
            with atomic_outputs(out) as (tmp,):
                if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(inner)), str(tmp)):
                    raise OSError(f"{out}: could not write the usdz package")
        return str(out)
    with atomic_outputs(out) as (tmp,):
        if not flat.Export(str(tmp)):
            raise OSError(f"{out}: could not write")
    return str(out)
