"""What fits and re-simulations write: a fit version's material field, animation, contacts and
report (`write_fit_layer`, through the versions of usd/versions.py), a re-simulation's own layer
(`write_simulation_layer`), and the animation a stage shows (`read_splat_animation`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdVol, Vt

from ..gaussians import scales_quats_from_covariance
from ..scene import SceneData
from .contacts import write_contact, write_trajectory
from .layout import (GENERATOR, PARTICLES, SCENE, SPLATS, LayerPaths, atomic_outputs, check_owned,
                     set_stage_metadata)
from .reports import json_default, write_report
from .stage import open_stage
from .versions import commit_version, now_utc


def _splat_samples(covs: np.ndarray):
    covs = np.asarray(covs)
    T, N = covs.shape[:2]
    s, q = scales_quats_from_covariance(covs.reshape(-1, 3, 3))
    return s.reshape(T, N, 3), q.reshape(T, N, 4)


def _quatf_array(quats: np.ndarray) -> Vt.QuatfArray:
    return Vt.QuatfArray([Gf.Quatf(float(q[0]), Gf.Vec3f(*map(float, q[1:]))) for q in quats])


def author_animation(stage: Usd.Stage, positions, gaussian_means, gaussian_covs) -> None:
    """Time-sampled SimParticles points (and extent) and Splats positions / orientations / scales,
    frame k at time code k."""
    pts = stage.OverridePrim(PARTICLES)
    pattr = pts.CreateAttribute("points", Sdf.ValueTypeNames.Point3fArray)
    ext = pts.CreateAttribute("extent", Sdf.ValueTypeNames.Float3Array)
    for k in range(len(positions)):
        p = np.asarray(positions[k], np.float32)
        pattr.Set(Vt.Vec3fArray.FromNumpy(p), Usd.TimeCode(k))
        ext.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, p.min(0))), Gf.Vec3f(*map(float, p.max(0)))]), Usd.TimeCode(k))
    spl = stage.OverridePrim(SPLATS)
    scales, quats = _splat_samples(gaussian_covs)
    a_pos = spl.CreateAttribute("positions", Sdf.ValueTypeNames.Point3fArray)
    a_rot = spl.CreateAttribute("orientations", Sdf.ValueTypeNames.QuatfArray)
    a_scl = spl.CreateAttribute("scales", Sdf.ValueTypeNames.Float3Array)
    for k in range(len(gaussian_means)):
        tc = Usd.TimeCode(k)
        a_pos.Set(Vt.Vec3fArray.FromNumpy(np.asarray(gaussian_means[k], np.float32)), tc)
        a_rot.Set(_quatf_array(quats[k]), tc)
        a_scl.Set(Vt.Vec3fArray.FromNumpy(scales[k].astype(np.float32)), tc)


def author_fit_content(stage: Usd.Stage, scene: SceneData, result, contacts, *,
                       confidence=None) -> None:
    """A fit's content, authored as overs on `stage`: the material field (primvars on SimParticles
    and, per Gaussian, on Splats), the confidence, the simulated animation, the contacts used
    (`contacts.ContactSet`s, with their T0) and the fitted trajectories. `confidence`: (per
    particle, per Gaussian) to write instead of the result's (a stopped fit's zeros)."""
    f32 = lambda a: Vt.FloatArray.FromNumpy(np.asarray(a, np.float32))  # noqa: E731
    conf_p, conf_g = confidence if confidence is not None else (result.confidence, result.confidence_gaussian)
    for path, vals in ((PARTICLES, (result.youngs, result.poisson, conf_p)),
                       (SPLATS, (result.youngs_gaussian, result.poisson_gaussian, conf_g))):
        pv = UsdGeom.PrimvarsAPI(stage.OverridePrim(path))
        for name, v in zip(("youngsModulus", "poissonRatio", "confidence"), vals):
            pv.CreatePrimvar(f"physinteract:{name}", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(f32(v))
    author_animation(stage, result.positions, result.gaussian_means, result.gaussian_covs)
    scene_prim = stage.OverridePrim(SCENE)
    chosen = (getattr(result, "settings", None) or {}).get("preload")
    if isinstance(chosen, dict):     # the fit decided whether the scan carries its weight (fit/preload_choice.py)
        scene_prim.CreateAttribute("physinteract:preload", Sdf.ValueTypeNames.Bool).Set(bool(chosen["preload"]))
    for c in contacts:
        write_contact(stage, SCENE, c, scene.particles_positions, scene.fps)
        fitted = result.trajectories.get(c.name)
        if fitted is not None:
            write_trajectory(stage, SCENE, c.name, fitted, "fitted", scene.fps)


def write_fit_layer(stage_path, scene: SceneData, result, contacts, *, effect_parameters: dict | None = None,
                    keep_best: bool = True, confidence_estimated: bool = True, resumed_from: str = "") -> dict:
    """Write a fit as a new version (usd/versions.py): its full snapshot in
    `<stem>.versions/v<N>.usdc`, its PhysInteractFitReport in scene.fit.usdc beside every earlier
    version's, and its content (`author_fit_content`) into scene.fit.usdc when it becomes current:
    with `keep_best`, when its loss is lower than the current version's; an interrupted fit never
    replaces a complete one. What extraction wrote besides contacts (hand masks) stays.
    Returns {"version", "layer", "snapshot", "current", "made_current", "reason"}."""
    status = "interrupted" if result.interrupted else "complete"
    conf = None
    if not confidence_estimated:  # not estimated: claim nothing (0), and say so in the report
        conf = (np.zeros_like(result.confidence), np.zeros_like(result.confidence_gaussian))

    def author(stage, version):
        author_fit_content(stage, scene, result, contacts, confidence=conf)
        write_report(stage, SCENE, version, result, effect_parameters, status=status, created=now_utc(),
                     confidence_estimated=confidence_estimated, resumed_from=resumed_from)

    return commit_version(stage_path, scene, author, status=status, final_loss=float(result.final_loss),
                          keep_best=keep_best)


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


def write_simulation_layer(stage_path, scene: SceneData, name: str, positions, gaussian_means,
                           gaussian_covs, fps: float, spec: dict) -> dict:
    """A re-simulation under a new interaction as its own time-sampled layer
    `<stem>.sim.<name>.usdc`, and a small stage `<stem>.sim.<name>.usda` that puts it over the
    fitted stage (your root layer is not touched). Returns the two paths."""
    lp = LayerPaths.of(stage_path)
    layer_path, view_path = lp.sibling(f".sim.{name}.usdc"), lp.sibling(f".sim.{name}.usda")
    check_owned(layer_path, "simulation")      # an earlier simulate's files are replaced; nobody else's
    check_owned(view_path, "simulationView")
    n = len(positions)
    layer = Sdf.Layer.CreateAnonymous("sim.usdc")
    set_stage_metadata(layer, fps, 0, n - 1)
    author_animation(Usd.Stage.Open(layer), positions, gaussian_means, gaussian_covs)
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "simulation", "name": name,
                                              "interaction": json.dumps(spec, default=json_default)}}
    view = Sdf.Layer.CreateAnonymous("view.usda")
    set_stage_metadata(view, fps, 0, n - 1)
    view.subLayerPaths.append(f"./{layer_path.name}")
    view.subLayerPaths.append(f"./{Path(lp.root).name}")
    view.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "simulationView", "name": name}}
    with atomic_outputs(layer_path, view_path) as (t1, t2):
        if not layer.Export(str(t1)) or not view.Export(str(t2)):
            raise OSError(f"{layer_path}: could not write the simulation layer")
    return {"layer": str(layer_path), "stage": str(view_path)}
