"""What `diagnose` writes on the stage: the diagnosis JSON (the verb's output) as
`physinteract:diagnosis` (string) on the report prim of the version it diagnosed
(`/World/PhysInteract/FitReport_v<N>`) in the fit layer, so `report` and Blender can show it later
without re-running it. Written through the one fit-layer opener; the user's root is never touched.
"""

from __future__ import annotations

import json

from pxr import Sdf, Usd

from .layout import SCENE, LayerPaths, open_fit_layer, save_layer
from .reports import REPORT_PREFIX
from .stage import open_stage

ATTR = "physinteract:diagnosis"


def write_diagnosis(stage_path, fps: float, n_frames: int, version: int, diagnosis: dict) -> str:
    """Author the diagnosis of fit version `version` (replacing an earlier one). Returns the fit
    layer's path."""
    lp = LayerPaths.of(stage_path)
    layer = open_fit_layer(lp, fps, n_frames)
    stage = Usd.Stage.Open(layer)
    prim = stage.OverridePrim(SCENE.AppendChild(f"{REPORT_PREFIX}{int(version)}"))
    a = prim.CreateAttribute(ATTR, Sdf.ValueTypeNames.String, custom=True)
    a.Set(json.dumps(diagnosis, allow_nan=False))
    a.SetDocumentation("the diagnosis of this fit version (`physinteract-usd diagnose --json`'s output)")
    save_layer(layer, lp.fit)
    return str(lp.fit)


def read_diagnosis(stage_path, version: int) -> dict | None:
    """The diagnosis stored for fit version `version` (None when there is none)."""
    stage = open_stage(stage_path)
    prim = stage.GetPrimAtPath(SCENE.AppendChild(f"{REPORT_PREFIX}{int(version)}"))
    if not prim:
        return None
    a = prim.GetAttribute(ATTR)
    if not a or not a.HasValue():
        return None
    try:
        return json.loads(a.Get())
    except ValueError:
        return None
