"""`export`: the composed stage flattened into one file."""

from __future__ import annotations

from pathlib import Path

from pxr import Sdf

from ..errors import InputError
from .layout import GENERATOR, SCENE, LayerPaths, atomic_outputs
from .stage import open_stage


CAPTURE_ASSETS = ("physinteract:frames", "physinteract:masks", "physinteract:handMasks", "physinteract:video")


def stage_layer_files(stage_path) -> set[Path]:
    """Every file the stage is made of (a simulation view's layers too) and the ones it will have."""
    src = Path(stage_path).resolve()
    stage = open_stage(stage_path)
    own = {p.resolve() for p in (src, *LayerPaths.of(src).__dict__.values()) if isinstance(p, Path)}
    own |= {Path(lay.realPath).resolve() for lay in stage.GetUsedLayers() if lay.realPath}
    return own


def export_stage(stage_path, out_path, *, capture_paths: str = "drop") -> str:
    """Flatten the composed stage into one self-contained file (.usd/.usdc/.usda or .usdz).

    The animation, material primvars, contacts, reports and every prim are kept. The capture's
    frames, masks, video and hand masks are the capture's, not the asset's: `capture_paths="drop"`
    (default) leaves them out, so the file depends on nothing else; "absolute" keeps them as
    absolute paths (valid on this machine only; a .usdz always drops them). Blender imports the
    result's SimParticles as an animated point cloud."""
    from pxr import UsdUtils

    out = Path(out_path)
    ext = out.suffix.lower()
    if capture_paths not in ("drop", "absolute"):
        raise InputError("--capture-paths", f"must be drop or absolute, not {capture_paths!r}")
    if ext not in (".usd", ".usdc", ".usda", ".usdz"):
        raise InputError(out, "the output must end in .usd, .usdc, .usda or .usdz")
    if not out.parent.exists():
        raise InputError(out.parent, "output folder does not exist")
    src = Path(stage_path).resolve()
    stage = open_stage(stage_path)
    if out.resolve() in stage_layer_files(stage_path):
        raise InputError(out, "would overwrite a layer of the stage itself")
    flat = stage.Flatten()
    src_dir = src.parent
    spec = flat.GetPrimAtPath(SCENE)
    if capture_paths == "drop" or ext == ".usdz":
        if spec is not None:
            for name in CAPTURE_ASSETS:
                if name in spec.attributes:
                    spec.RemoveProperty(spec.attributes[name])

    def absolute(p: str) -> str:
        if not p or "://" in p or p.startswith("@"):
            return p
        return str(Path(p) if Path(p).is_absolute() else (src_dir / p).resolve())

    UsdUtils.ModifyAssetPaths(flat, absolute)
    flat.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "export", "source": str(src),
                                             "capturePaths": "drop" if ext == ".usdz" else capture_paths}}
    if ext == ".usdz":
        import tempfile

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
