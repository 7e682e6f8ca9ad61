"""The simulation-ready asset (`export --sim-ready`): the twin as a tetrahedral soft body with the
Alliance for OpenUSD deformable-physics schemas (the proposal Newton 1.8 imports), in one new,
self-contained file. Written from scratch (nothing of the source stage is referenced); read back by
`read_sim_ready` (the tests and the Newton cross-check use it).

```
/World                         default prim; metersPerUnit 1, kilogramsPerUnit 1, upAxis Y
  PhysicsScene                 UsdPhysics.Scene: gravity (0, -1, 0) x 9.81 m/s^2
  Twin                         Xform + PhysicsDeformableBodyAPI (one soft body)
    SimMesh                    TetMesh + PhysicsVolumeDeformableSimAPI + PhysicsCollisionAPI, bound
                               (purpose physics) to Materials/Body; per-tetrahedron primvars
                               (interpolation uniform): physinteract:youngsModulus [Pa],
                               physinteract:poissonRatio, physinteract:density [kg/m^3],
                               physinteract:region (index of the clustered material)
      Region_k                 GeomSubset (tetrahedron, family materialBind) bound to Materials/Region_k
    Splats                     the Gaussians at rest (ParticleField3DGaussianSplat) with
                               primvars:physinteract:tetIndex (int) and :tetWeights (float4,
                               barycentric): mean = sum_i w_i SimMesh.points[tet[i]]; covariance
                               deforms with that tetrahedron's F
    Materials/Body, Region_k   Material + PhysicsMaterialAPI + PhysicsVolumeDeformableMaterialAPI
                               (physics:youngsModulus, physics:poissonsRatio, physics:density)
  Attachments                  PhysicsAttachment per support (SimMesh points -> the world) and per
                               grasp (SimMesh points -> Interaction/<name>, enabled while grasped)
  Interaction/<name>           Xform, time-sampled translate: the fitted hand trajectory
  Ground                       (ground effect) Plane + PhysicsCollisionAPI, friction material
```
Effects with a schema equivalent are written there (ground -> a collider with
physics:dynamicFriction / staticFriction); those without (damping, plasticity,
viscoelasticity) are written as physinteract:<effect>:<parameter> on /World/Twin and listed in
the layer's customLayerData (physinteract.effects.unmapped).
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade, Vt

from ..errors import InputError
from ..gaussians import Gaussians
from .layout import GENERATOR, atomic_outputs
from .stage import author_splats

WORLD = "/World"
TWIN = "/World/Twin"
SIM_MESH = "/World/Twin/SimMesh"
SPLATS = "/World/Twin/Splats"
MATERIALS = "/World/Twin/Materials"
ATTACHMENTS = "/World/Attachments"
INTERACTION = "/World/Interaction"
GROUND = "/World/Ground"
PHYSICS_SCENE = "/World/PhysicsScene"

PV_E = "primvars:physinteract:youngsModulus"
PV_NU = "primvars:physinteract:poissonRatio"
PV_RHO = "primvars:physinteract:density"
PV_REGION = "primvars:physinteract:region"
PV_TET = "primvars:physinteract:tetIndex"
PV_WEIGHTS = "primvars:physinteract:tetWeights"

BODY_API = "PhysicsDeformableBodyAPI"
VOLUME_SIM_API = "PhysicsVolumeDeformableSimAPI"
VOLUME_MATERIAL_API = "PhysicsVolumeDeformableMaterialAPI"
COLLISION_API = "PhysicsCollisionAPI"
ATTACHMENT_TYPE = "PhysicsAttachment"

MAPPED = {"ground": "a static collider /World/Ground (Plane at y = height); physics:dynamicFriction and "
                    "physics:staticFriction = friction on its material and on the body's"}
UNMAPPED = {"damping": "no damping in the volume-deformable schemas: mass-proportional c [1/s] (v <- v exp(-c dt)) "
                       "as physinteract:damping:coefficient on /World/Twin",
            "plasticity": "no plasticity in the schemas: von Mises yield stress [Pa] on the Hencky strain",
            "viscoelasticity": "no viscoelasticity in the schemas: a Maxwell branch (modulus [Pa], relaxation time [s])"}


@dataclass
class Hold:
    """Mesh points held by a support (trajectory None: still) or a grasp (trajectory (T, 3) of the
    hand, grasp and release frames; release None = never)."""

    name: str
    vertices: np.ndarray
    trajectory: np.ndarray | None = None
    grasp_frame: int = 0
    release_frame: int | None = None


@dataclass
class SimReadyAsset:
    """Everything the file holds, as plain arrays (built by app.simready)."""

    points: np.ndarray            # (V, 3) rest positions [m]
    tets: np.ndarray              # (T, 4) positively oriented
    surface: np.ndarray           # (F, 3) outward boundary faces
    youngs: np.ndarray            # (T,) [Pa]
    poisson: np.ndarray           # (T,)
    density: np.ndarray           # (T,) [kg/m^3]
    region: np.ndarray            # (T,) index into regions
    regions: list                 # [{"youngs", "poisson", "volume", "count", "spread"}]
    body_youngs: float
    body_poisson: float
    body_density: float
    gaussians: Gaussians
    splat_tet: np.ndarray         # (N,) tetrahedron of each Gaussian
    splat_weights: np.ndarray     # (N, 4) barycentric weights
    supports: list                # [Hold]
    grasps: list                  # [Hold] with trajectories
    effects: dict                 # {effect: {parameter: value}} switched on (fitted values)
    fps: float
    n_frames: int
    info: dict = field(default_factory=dict)   # provenance and measured tolerances (customLayerData)


def _f32(a):
    return Vt.FloatArray.FromNumpy(np.ascontiguousarray(a, np.float32))


def _apply(prim: Usd.Prim, *schemas: str) -> None:
    """Apply API schemas by name (the deformable proposal's are not registered with usd-core yet:
    they go into the prim's apiSchemas list, which is where the proposal's readers look)."""
    for s in schemas:
        prim.AddAppliedSchema(s)


def _material(stage: Usd.Stage, path: str, youngs: float, poisson: float, density: float, doc: str) -> UsdShade.Material:
    mat = UsdShade.Material.Define(stage, path)
    prim = mat.GetPrim()
    api = UsdPhysics.MaterialAPI.Apply(prim)      # the base physics material (density, friction)
    api.CreateDensityAttr().Set(float(density))
    _apply(prim, VOLUME_MATERIAL_API)
    prim.CreateAttribute("physics:youngsModulus", Sdf.ValueTypeNames.Float).Set(float(youngs))
    prim.CreateAttribute("physics:poissonsRatio", Sdf.ValueTypeNames.Float).Set(float(poisson))
    prim.SetDocumentation(doc)
    return mat


def write_sim_ready(out_path, a: SimReadyAsset) -> str:
    """Write the asset to OUT (.usd, .usdc, .usda or .usdz), atomically."""
    out = Path(out_path)
    ext = out.suffix.lower()
    if ext not in (".usd", ".usdc", ".usda", ".usdz"):
        raise InputError(out, "the output must end in .usd, .usdc, .usda or .usdz")
    if not out.parent.exists():
        raise InputError(out.parent, "output folder does not exist")
    layer = Sdf.Layer.CreateAnonymous("simready.usda")
    stage = Usd.Stage.Open(layer)
    _author(stage, a)
    if ext == ".usdz":
        from pxr import UsdUtils

        with tempfile.TemporaryDirectory() as td:
            inner = Path(td) / (out.stem + ".usdc")
            if not layer.Export(str(inner)):
                raise OSError(f"{out}: could not write")
            with atomic_outputs(out) as (tmp,):
                if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(inner)), str(tmp)):
                    raise OSError(f"{out}: could not write the usdz package")
        return str(out)
    with atomic_outputs(out) as (tmp,):
        if not layer.Export(str(tmp)):
            raise OSError(f"{out}: could not write")
    return str(out)


def _author(stage: Usd.Stage, a: SimReadyAsset) -> None:
    layer = stage.GetRootLayer()
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    layer.timeCodesPerSecond = a.fps
    layer.framesPerSecond = a.fps
    layer.startTimeCode = 0
    layer.endTimeCode = max(a.n_frames - 1, 0)

    scene = UsdPhysics.Scene.Define(stage, PHYSICS_SCENE)
    scene.CreateGravityDirectionAttr().Set(Gf.Vec3f(0.0, -1.0, 0.0))
    scene.CreateGravityMagnitudeAttr().Set(9.81)

    twin = UsdGeom.Xform.Define(stage, TWIN)
    _apply(twin.GetPrim(), BODY_API)
    twin.GetPrim().SetDocumentation("the fitted digital twin: one volume-deformable body (AOUSD deformable proposal)")

    # the simulation mesh and its per-tetrahedron field
    tm = UsdGeom.TetMesh.Define(stage, SIM_MESH)
    prim = tm.GetPrim()
    tm.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a.points, np.float32)))
    tm.CreateTetVertexIndicesAttr().Set(Vt.Vec4iArray.FromNumpy(np.ascontiguousarray(a.tets, np.int32)))
    tm.CreateSurfaceFaceVertexIndicesAttr().Set(Vt.Vec3iArray.FromNumpy(np.ascontiguousarray(a.surface, np.int32)))
    tm.CreateOrientationAttr().Set(UsdGeom.Tokens.rightHanded)
    lo, hi = a.points.min(0), a.points.max(0)
    tm.CreateExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    _apply(prim, VOLUME_SIM_API, COLLISION_API)
    pv = UsdGeom.PrimvarsAPI(prim)
    for name, vals, doc in (
            ("physinteract:youngsModulus", a.youngs, "Young's modulus per tetrahedron [Pa] (the fitted field)"),
            ("physinteract:poissonRatio", a.poisson, "Poisson's ratio per tetrahedron (the fitted field)"),
            ("physinteract:density", a.density, "density per tetrahedron [kg/m^3]")):
        p = pv.CreatePrimvar(name, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.uniform)
        p.Set(_f32(vals))
        p.GetAttr().SetDocumentation(doc)
    pv.CreatePrimvar("physinteract:region", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(a.region, np.int32)))
    pv.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.constant).Set(
        Vt.Vec3fArray([Gf.Vec3f(0.8, 0.55, 0.3)]))

    body = _material(stage, f"{MATERIALS}/Body", a.body_youngs, a.body_poisson, a.body_density,
                     "the body's one material (volume-weighted geometric mean E, mean nu): what a simulator "
                     "that reads one material per body uses")
    binding = UsdShade.MaterialBindingAPI.Apply(prim)
    binding.Bind(body, UsdShade.Tokens.weakerThanDescendants, "physics")
    if len(a.regions) > 1:
        for k, r in enumerate(a.regions):
            mat = _material(stage, f"{MATERIALS}/Region_{k}", r["youngs"], r["poisson"], a.body_density,
                            f"clustered material region {k}: {r['count']} tetrahedra, E within "
                            f"{100 * r['spread']:.0f}% of this value")
            idx = Vt.IntArray.FromNumpy(np.flatnonzero(a.region == k).astype(np.int32))
            sub = binding.CreateMaterialBindSubset(f"Region_{k}", idx, UsdGeom.Tokens.tetrahedron)
            sapi = UsdShade.MaterialBindingAPI.Apply(sub.GetPrim())
            sapi.Bind(mat, UsdShade.Tokens.weakerThanDescendants, "physics")
        binding.SetMaterialBindSubsetsFamilyType(UsdGeom.Tokens.partition)

    # the splats, bound to the tetrahedra
    splats = author_splats(stage, a.gaussians, Sdf.Path(SPLATS))
    spv = UsdGeom.PrimvarsAPI(splats.GetPrim())
    spv.CreatePrimvar("physinteract:tetIndex", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(a.splat_tet, np.int32)))
    spv.CreatePrimvar("physinteract:tetWeights", Sdf.ValueTypeNames.Float4Array, UsdGeom.Tokens.vertex).Set(
        Vt.Vec4fArray.FromNumpy(np.ascontiguousarray(a.splat_weights, np.float32)))
    splats.GetPrim().SetDocumentation(
        "the Gaussians at rest, bound to /World/Twin/SimMesh: each mean is sum_i tetWeights[i] * "
        "points[tetVertexIndices[tetIndex][i]]; each covariance deforms with its tetrahedron's F")

    # supports and grasps
    UsdGeom.Scope.Define(stage, ATTACHMENTS)
    for h in a.supports:
        att = _attachment(stage, f"{ATTACHMENTS}/Support_{_name(h.name)}", h.vertices, a.points[h.vertices], None)
        att.SetDocumentation(f"support '{h.name}': these SimMesh points are held still (attached to the world)")
    if a.grasps:
        UsdGeom.Scope.Define(stage, INTERACTION)
    for h in a.grasps:
        hand_path = f"{INTERACTION}/{_name(h.name)}"
        hand = UsdGeom.Xform.Define(stage, hand_path)
        op = hand.AddTranslateOp()
        traj = np.asarray(h.trajectory, np.float64)
        for k, p in enumerate(traj):
            op.Set(Gf.Vec3d(*map(float, p)), Usd.TimeCode(k))
        hand.GetPrim().SetDocumentation(f"the fitted trajectory of '{h.name}' (the hand), one sample per frame")
        g = int(h.grasp_frame)
        anchor = traj[min(g, len(traj) - 1)]
        att = _attachment(stage, f"{ATTACHMENTS}/Grasp_{_name(h.name)}", h.vertices, a.points[h.vertices] - anchor,
                          hand_path)
        en = att.CreateAttribute("physics:attachmentEnabled", Sdf.ValueTypeNames.Bool)
        en.Set(g <= 0 and (h.release_frame is None or h.release_frame > 0))
        for k in sorted({0, g, *([h.release_frame] if h.release_frame is not None else [])}):
            if 0 <= k < a.n_frames:
                en.Set(bool(g <= k and (h.release_frame is None or k < h.release_frame)), Usd.TimeCode(k))
        att.SetDocumentation(f"grasp '{h.name}': these SimMesh points follow {hand_path} from frame {g}"
                             + ("" if h.release_frame is None else f" until frame {h.release_frame}"))

    # effects
    unmapped = {}
    for name, params in sorted(a.effects.items()):
        if name == "ground":
            mu = float(params.get("friction", 0.5))
            _ground(stage, float(params.get("height", 0.0)), mu)
            # the object's side of the contact too (simulators combine both materials' friction)
            bapi = UsdPhysics.MaterialAPI(body.GetPrim())
            bapi.CreateDynamicFrictionAttr().Set(mu)
            bapi.CreateStaticFrictionAttr().Set(mu)
            continue
        for p, v in params.items():
            twin.GetPrim().CreateAttribute(f"physinteract:{name}:{p}", Sdf.ValueTypeNames.Float).Set(float(v))
        unmapped[name] = {"parameters": {p: float(v) for p, v in params.items()}, "why": UNMAPPED.get(name, "")}
    mapped = {k: MAPPED[k] for k in a.effects if k in MAPPED}

    layer.customLayerData = {"physinteract": {
        "generator": GENERATOR, "layer": "simready",
        "units": "metres, kilograms, seconds (metersPerUnit 1, kilogramsPerUnit 1); Pa, kg/m^3",
        "effects": {"mapped": mapped, "unmapped": unmapped},
        "regions": json.dumps(a.regions),
        **{k: (json.dumps(v) if isinstance(v, (list, tuple, dict)) else v) for k, v in a.info.items()}}}


def _name(s: str) -> str:
    out = "".join(ch if ch.isalnum() or ch == "_" else "_" for ch in str(s)) or "contact"
    return out if not out[0].isdigit() else "_" + out


def _attachment(stage, path, vertices, coords1, target):
    """A proposal PhysicsAttachment (registered by name only: its typed schema is not in usd-core)
    from SimMesh points to an xform (`target`, or the world when None)."""
    prim = stage.DefinePrim(path, ATTACHMENT_TYPE)
    prim.CreateRelationship("physics:src0").SetTargets([Sdf.Path(SIM_MESH)])
    if target is not None:
        prim.CreateRelationship("physics:src1").SetTargets([Sdf.Path(target)])
    prim.CreateAttribute("physics:type0", Sdf.ValueTypeNames.Token).Set("point")
    prim.CreateAttribute("physics:type1", Sdf.ValueTypeNames.Token).Set("xform")
    prim.CreateAttribute("physics:indices0", Sdf.ValueTypeNames.IntArray).Set(
        Vt.IntArray.FromNumpy(np.ascontiguousarray(vertices, np.int32)))
    prim.CreateAttribute("physics:coords1", Sdf.ValueTypeNames.Vector3fArray).Set(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(coords1, np.float32)))
    return prim


def _ground(stage, height: float, friction: float) -> None:
    plane = UsdGeom.Plane.Define(stage, GROUND)
    plane.CreateAxisAttr().Set("Y")
    plane.AddTranslateOp().Set(Gf.Vec3d(0.0, height, 0.0))
    UsdPhysics.CollisionAPI.Apply(plane.GetPrim())
    mat = UsdShade.Material.Define(stage, f"{GROUND}/Material")
    api = UsdPhysics.MaterialAPI.Apply(mat.GetPrim())
    api.CreateDynamicFrictionAttr().Set(float(friction))
    api.CreateStaticFrictionAttr().Set(float(friction))
    UsdShade.MaterialBindingAPI.Apply(plane.GetPrim()).Bind(mat, UsdShade.Tokens.weakerThanDescendants,
                                                             "physics")
    plane.GetPrim().SetDocumentation("the fitted ground effect: a static plane with Coulomb friction")


# ------------------------------------------------------------------------------------ reading
def _decode(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, str) and v[:1] in "[{":
            try:
                v = json.loads(v)
            except ValueError:
                pass
        out[k] = _decode(dict(v)) if hasattr(v, "keys") else v
    return out


def read_sim_ready(path) -> dict:
    """The asset as arrays: {"points", "tets", "surface", "youngs", "poisson", "density", "region",
    "body": {"youngs", "poisson", "density"}, "splat_tet", "splat_weights", "gaussians",
    "supports": {name: vertices}, "grasps": {name: {"vertices", "offsets", "trajectory",
    "enabled" (per frame)}}, "fps", "n_frames", "meters_per_unit", "kilograms_per_unit", "info"}."""
    from .stage import read_splats

    p = Path(path)
    if not p.exists():
        raise InputError(p, "file not found")
    stage = Usd.Stage.Open(str(p))
    tm_prim = stage.GetPrimAtPath(SIM_MESH)
    if not tm_prim or not tm_prim.IsA(UsdGeom.TetMesh):
        raise InputError(p, f"not a sim-ready asset (no TetMesh at {SIM_MESH})")
    tm = UsdGeom.TetMesh(tm_prim)
    get = lambda prim, name: np.asarray(prim.GetAttribute(name).Get())  # noqa: E731
    body = UsdShade.MaterialBindingAPI(tm_prim).ComputeBoundMaterial("physics")[0].GetPrim()
    out = {
        "points": np.asarray(tm.GetPointsAttr().Get(), np.float64),
        "tets": np.asarray(tm.GetTetVertexIndicesAttr().Get(), np.int64).reshape(-1, 4),
        "surface": np.asarray(tm.GetSurfaceFaceVertexIndicesAttr().Get(), np.int64).reshape(-1, 3),
        "youngs": get(tm_prim, PV_E).astype(np.float64), "poisson": get(tm_prim, PV_NU).astype(np.float64),
        "density": get(tm_prim, PV_RHO).astype(np.float64), "region": get(tm_prim, PV_REGION).astype(np.int64),
        "body": {"youngs": float(body.GetAttribute("physics:youngsModulus").Get()),
                 "poisson": float(body.GetAttribute("physics:poissonsRatio").Get()),
                 "density": float(body.GetAttribute("physics:density").Get())},
        "fps": float(stage.GetTimeCodesPerSecond()), "n_frames": int(stage.GetEndTimeCode()) + 1,
        "meters_per_unit": float(UsdGeom.GetStageMetersPerUnit(stage)),
        "kilograms_per_unit": float(UsdPhysics.GetStageKilogramsPerUnit(stage)),
        "info": _decode(dict(stage.GetRootLayer().customLayerData.get("physinteract", {}))),
    }
    sp = stage.GetPrimAtPath(SPLATS)
    out["gaussians"] = read_splats(stage, Sdf.Path(SPLATS))
    out["splat_tet"] = get(sp, PV_TET).astype(np.int64)
    out["splat_weights"] = get(sp, PV_WEIGHTS).astype(np.float64)
    out["supports"], out["grasps"] = {}, {}
    att_root = stage.GetPrimAtPath(ATTACHMENTS)
    for att in (att_root.GetChildren() if att_root else []):
        if att.GetTypeName() != ATTACHMENT_TYPE:
            continue
        idx = get(att, "physics:indices0").astype(np.int64)
        coords = get(att, "physics:coords1").astype(np.float64)
        targets = att.GetRelationship("physics:src1").GetTargets() if att.GetRelationship("physics:src1") else []
        if not targets:
            out["supports"][att.GetName().removeprefix("Support_")] = idx
            continue
        hand = UsdGeom.Xformable(stage.GetPrimAtPath(targets[0]))
        n = out["n_frames"]
        traj = np.array([hand.ComputeLocalToWorldTransform(Usd.TimeCode(k)).ExtractTranslation() for k in range(n)])
        en = att.GetAttribute("physics:attachmentEnabled")
        enabled = np.array([bool(en.Get(Usd.TimeCode(k))) if en else True for k in range(n)])
        out["grasps"][att.GetName().removeprefix("Grasp_")] = {"vertices": idx, "offsets": coords,
                                                                "trajectory": traj, "enabled": enabled}
    return out
