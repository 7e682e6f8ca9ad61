"""`export`: the composed stage flattened into one file."""

from __future__ import annotations

import os
from pathlib import Path

from pxr import Sdf

from ..errors import InputError
from .layout import GENERATOR, SCENE, LayerPaths, atomic_outputs
from .stage import open_stage


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
