"""The stage's layout: its layers (where each lives, how each is opened and written, atomically)
and the paths of its prims.

```
scene.usda            the user's thin root: stage metadata, their choices (effects, overrides),
                      subLayers = [./scene.fit.usdc, ./scene.init.usdc]
scene.init.usdc       written by `init`: object, particles, camera, PhysInteractScene
scene.fit.usdc        written by `extract`, `fit` (empty after `init`): every version's
                      PhysInteractFitReport and the current version's material, animation, contacts
scene.versions/       written by `fit`: v<N>.usdc, the full snapshot of fit version N (what it wrote
                      into the fit layer), and checkpoint.npz while a fit runs (`fit --resume`)
```
Every writer edits an anonymous copy and renames a temp file into place: nothing is half-written,
and nothing the user authored in the root layer is touched.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

from pxr import Sdf, Usd, UsdGeom

from .. import __version__
from ..errors import InputError

GENERATOR = f"physinteract-usd {__version__}"

WORLD = Sdf.Path("/World")
OBJECT = Sdf.Path("/World/Object")
SPLATS = Sdf.Path("/World/Object/Splats")
PARTICLES = Sdf.Path("/World/Object/SimParticles")
MESH = Sdf.Path("/World/Object/Mesh")
CAMERA = Sdf.Path("/World/Camera")
SCENE = Sdf.Path("/World/PhysInteract")

PRIMVAR_E = "primvars:physinteract:youngsModulus"
PRIMVAR_NU = "primvars:physinteract:poissonRatio"
PRIMVAR_CONF = "primvars:physinteract:confidence"
PRIMVAR_VOLUME = "primvars:physinteract:volume"
PRIMVAR_SURFACE = "primvars:physinteract:isSurface"


@dataclass(frozen=True)
class LayerPaths:
    root: Path
    init: Path
    fit: Path

    @staticmethod
    def of(root) -> "LayerPaths":
        root = Path(root)
        return LayerPaths(root, root.with_name(f"{stem(root)}.init.usdc"), root.with_name(f"{stem(root)}.fit.usdc"))

    @property
    def versions(self) -> Path:
        """`<stem>.versions/`: one snapshot layer per fit version, and a running fit's checkpoint."""
        return self.sibling(".versions")

    def version_layer(self, n: int) -> Path:
        return self.versions / f"v{int(n)}.usdc"

    @property
    def checkpoint(self) -> Path:
        return self.versions / "checkpoint.npz"

    def sibling(self, suffix: str) -> Path:
        """`<stem><suffix>` next to the root layer (e.g. ".extract", ".sim.pull.usdc")."""
        return self.root.with_name(f"{stem(self.root)}{suffix}")


def stem(path) -> str:
    path = Path(path)
    return path.name[: -len(path.suffix)] if path.suffix else path.name


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


def check_writable_dir(folder: Path) -> None:
    """InputError unless `folder` is an existing folder we may create files in (probed: a
    read-only mount or a folder that is not ours fails here, not halfway through a write)."""
    folder = Path(folder)
    if not folder.exists():
        raise InputError(folder, "output folder does not exist")
    if not folder.is_dir():
        raise InputError(folder, "is not a folder")
    probe = folder / f".physinteract-write-probe.{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except OSError as exc:
        raise InputError(folder, f"output folder is not writable ({exc.strerror or exc})") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def set_stage_metadata(layer: Sdf.Layer, fps: float, start: int, end: int) -> None:
    layer.defaultPrim = "World"
    layer.timeCodesPerSecond = fps
    layer.framesPerSecond = fps
    layer.startTimeCode = start
    layer.endTimeCode = end
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)


def check_our_root(path: Path) -> Sdf.Layer:
    """The root layer, if it is one of ours (InputError otherwise: we never write over another
    tool's file)."""
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


def layer_kind(path: Path) -> str | None:
    """The physinteract layer kind a file says it is ("root", "init", "fit", "version", ...), or
    None for a file that is not one of ours (or not a USD layer at all)."""
    try:
        layer = Sdf.Layer.FindOrOpen(str(path))
    except Exception:  # noqa: BLE001  (a Tf error: not a USD layer)
        return None
    if layer is None:
        return None
    data = dict(layer.customLayerData).get("physinteract")
    return str(data.get("layer", "")) if isinstance(data, dict) else None


def check_owned(path: Path, kind: str) -> None:
    """InputError unless the existing file at `path` is a physinteract `kind` layer: a file another
    tool wrote under our name is never written over."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, f"is a folder where the stage's {kind} layer belongs")
    if path.exists() and layer_kind(path) != kind:
        raise InputError(path, f"is not a physinteract-usd {kind} layer (written by another tool?): "
                         "it is left alone; move it away or choose another stage name")


def open_fit_layer(lp: LayerPaths, fps: float, n_frames: int) -> Sdf.Layer:
    """An anonymous, editable copy of the stage's fit layer (or a new one): the one way every verb
    that writes the fit layer opens it. Save it with `save_layer(layer, lp.fit)`."""
    if lp.fit.exists():
        check_owned(lp.fit, "fit")
        layer = Sdf.Layer.OpenAsAnonymous(str(lp.fit))
        if layer is None:
            raise InputError(lp.fit, "cannot be opened as a USD layer")
        return layer
    layer = Sdf.Layer.CreateAnonymous("fit.usdc")
    set_stage_metadata(layer, fps, 0, n_frames - 1)
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "fit"}}
    return layer


def mark_layer(target: Sdf.Layer, **data) -> None:
    """Merge `data` into the layer's customLayerData["physinteract"] (generator stamped)."""
    d = dict(target.customLayerData)
    phys = dict(d.get("physinteract", {}))
    phys.update({"generator": GENERATOR, **data})
    d["physinteract"] = phys
    target.customLayerData = d


def save_layer(layer: Sdf.Layer, path: Path) -> None:
    """Export `layer` to `path` atomically, and make a cached copy of that file re-read it."""
    path = Path(path)
    with atomic_outputs(path) as (tmp,):
        if not layer.Export(str(tmp)):
            raise OSError(f"{path}: could not write the layer")
    cached = Sdf.Layer.Find(str(path))
    if cached is not None:
        cached.Reload(force=True)


def remove_prim_spec(layer: Sdf.Layer, path) -> bool:
    """Remove the prim spec at `path` (and everything under it) from `layer`; False if absent."""
    path = Sdf.Path(str(path))
    spec = layer.GetPrimAtPath(path)
    if spec is None:
        return False
    parent = layer.GetPrimAtPath(path.GetParentPath()) if path.GetParentPath() != Sdf.Path.absoluteRootPath else None
    if parent is None:
        del layer.rootPrims[path.name]
    else:
        del parent.nameChildren[path.name]
    return True
