"""What `report` writes on the stage: the per-particle residual map (overall and per phase) as
primvars on SimParticles, so Blender colours the point cloud by them, and the verdict in the fit
layer's metadata. Written into scene.fit.usdc through the one fit-layer opener; the user's root is
never touched.

    primvars:physinteract:residual          float[] per particle, RMS residual motion (m), all frames
    primvars:physinteract:residual_<phase>  the same over one phase's frames (load, hold, release, free)
"""

from __future__ import annotations

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from .layout import PARTICLES, LayerPaths, mark_layer, open_fit_layer, save_layer
from .stage import open_stage

RESIDUAL = "physinteract:residual"


def primvar_name(phase: str) -> str:
    """The primvar (without `primvars:`) of a phase's residual map; 'all' is the plain one."""
    return RESIDUAL if phase == "all" else f"{RESIDUAL}_{phase}"


def write_residuals(stage_path, fps: float, n_frames: int, maps: dict, *, summary: dict | None = None) -> str:
    """Author the residual maps {phase | 'all': (P,) metres} on SimParticles in the fit layer
    (replacing earlier ones: a phase that no longer occurs loses its primvar) and the report's
    summary in the layer's metadata. Returns the fit layer's path."""
    lp = LayerPaths.of(stage_path)
    layer = open_fit_layer(lp, fps, n_frames)
    spec = layer.GetPrimAtPath(PARTICLES)
    if spec is not None:
        for prop in list(spec.properties):
            if prop.name.startswith(f"primvars:{RESIDUAL}"):
                spec.RemoveProperty(prop)
    stage = Usd.Stage.Open(layer)
    pv = UsdGeom.PrimvarsAPI(stage.OverridePrim(PARTICLES))
    for phase, vals in maps.items():
        v = np.nan_to_num(np.asarray(vals, np.float32), nan=0.0)
        p = pv.CreatePrimvar(primvar_name(phase), Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
        p.Set(Vt.FloatArray.FromNumpy(v))
        p.GetAttr().SetCustomDataByKey("physinteract:unit", "m")
        p.GetAttr().SetCustomDataByKey("physinteract:phase", phase)
        p.GetAttr().SetDocumentation("RMS residual motion, video minus model, in the image plane (metres), "
                                     f"over the {'whole clip' if phase == 'all' else phase + ' frames'}")
    if summary is not None:
        mark_layer(layer, report={k: v for k, v in summary.items() if v is not None})
    save_layer(layer, lp.fit)
    return str(lp.fit)


def read_residuals(stage_path) -> dict:
    """{phase | 'all': (P,) float} the residual primvars the composed stage holds."""
    stage = open_stage(stage_path)
    prim = stage.GetPrimAtPath(PARTICLES)
    out = {}
    for p in UsdGeom.PrimvarsAPI(prim).GetPrimvars():
        name = p.GetPrimvarName()
        if name == RESIDUAL or name.startswith(RESIDUAL + "_"):
            phase = "all" if name == RESIDUAL else name[len(RESIDUAL) + 1:]
            out[phase] = np.asarray(p.Get(), np.float64)
    return out
