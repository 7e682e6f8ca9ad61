"""The batch's catalogue stage: one prim per fitted asset, referencing its exported file.

```
catalogue.usda      defaultPrim /Catalogue (Y up, metres)
  /Catalogue/<name>   Xform, references = @./items/<name>/asset.usdc@ (its /World), translated onto a
                      grid so the assets stand side by side; customData physinteract:batch = the
                      item's numbers (status, version, PSNR, verdict, diagnosis, median E, source)
```
Assets that did not finish are not referenced (the summary lists them). The file is the batch's:
a file at its path written by another tool is left alone (InputError).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

from pxr import Gf, Sdf, Usd, UsdGeom

from .layout import GENERATOR, atomic_outputs, check_owned

ROOT = Sdf.Path("/Catalogue")


def prim_name(name: str) -> str:
    """A valid, unique-enough prim name for an item name."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return s if s and not s[0].isdigit() else f"_{s}"


def _extent(asset: Path) -> float:
    """The largest side of the asset's bounds over its frames (0 when it has none)."""
    stage = Usd.Stage.Open(str(asset), Usd.Stage.LoadAll)
    prim = stage.GetDefaultPrim() if stage.GetDefaultPrim() else stage.GetPseudoRoot()
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_, UsdGeom.Tokens.render])
    size = 0.0
    for t in (stage.GetStartTimeCode(), stage.GetEndTimeCode()):
        cache.SetTime(Usd.TimeCode(t))
        rng = cache.ComputeWorldBound(prim).ComputeAlignedRange()
        if not rng.IsEmpty():
            size = max(size, max(rng.GetSize()))
    return float(size)


def write_catalogue(path, entries: list[dict]) -> dict:
    """Write the catalogue stage at `path`: `entries` are {"name", "asset" (a path), "data" (a flat
    dict of numbers and strings)}. Returns {"path", "assets"}."""
    path = Path(path).resolve()
    check_owned(path, "catalogue")
    entries = [e for e in entries if e.get("asset") and Path(e["asset"]).exists()]
    with atomic_outputs(path) as (tmp,):
        # written at a temp path beside its final one: the relative references resolve while authoring
        layer = Sdf.Layer.CreateNew(str(tmp))
        _author(layer, path, entries)
        if not layer.Save():
            raise OSError(f"{path}: could not write the catalogue")
    cached = Sdf.Layer.Find(str(path))
    if cached is not None:
        cached.Reload(force=True)
    return {"path": str(path), "assets": len(entries)}


def _author(layer: Sdf.Layer, path: Path, entries: list[dict]) -> None:
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "catalogue"}}
    layer.defaultPrim = ROOT.name
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.Xform.Define(stage, ROOT)
    spacing = 1.5 * max([_extent(Path(e["asset"])) for e in entries] + [1e-3])
    cols = max(1, math.ceil(math.sqrt(len(entries))))
    clips = []   # (timeCodesPerSecond, endTimeCode) of each asset
    used = set()
    for i, e in enumerate(entries):
        name = prim_name(e["name"])
        while name in used:
            name += "_"
        used.add(name)
        asset = Path(e["asset"]).resolve()
        ref = os.path.relpath(asset, path.parent).replace(os.sep, "/")
        if not ref.startswith("."):
            ref = "./" + ref
        x = UsdGeom.Xform.Define(stage, ROOT.AppendChild(name))
        x.GetPrim().GetReferences().AddReference(ref)
        x.AddTranslateOp().Set(Gf.Vec3d(spacing * (i % cols), 0.0, -spacing * (i // cols)))
        data = {k: v for k, v in (e.get("data") or {}).items()
                if isinstance(v, (str, int, float, bool)) and not (isinstance(v, float) and not math.isfinite(v))}
        x.GetPrim().SetCustomDataByKey("physinteract:batch", data)
        sub = Sdf.Layer.FindOrOpen(str(asset))
        if sub is not None and sub.timeCodesPerSecond > 0:
            clips.append((sub.timeCodesPerSecond, sub.endTimeCode))
    if clips:   # a reference maps its time codes by the ratio of the layers' timeCodesPerSecond
        fps = clips[0][0]
        layer.timeCodesPerSecond = fps
        layer.framesPerSecond = fps
        layer.startTimeCode = 0
        layer.endTimeCode = max(e * fps / f for f, e in clips)
