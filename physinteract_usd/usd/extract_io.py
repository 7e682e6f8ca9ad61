"""USD side of extraction: what the user authored, and writing the extraction into scene.fit.usdc.

Extraction writes, into the generated fit layer (stronger than init, weaker than the user's root),
keeping whatever else that layer holds (FitReport prims, a fitted material, animation):

- `PhysInteractContactSet` prims under /World/PhysInteract (particleIndices, contactType,
  graspTime, releaseTime, source = "extracted", colliderRadius, contactPoint; plus the custom
  attributes `physinteract:contactNormal` and `physinteract:friction` for colliders);
- `PhysInteractTrajectory` prims `<contact>_initial` (stage = "initial", time-sampled position and
  velocity per frame, rel contactSet);
- `physinteract:handMasks` on /World/PhysInteract: PNGs in `<stem>.extract/hand_masks/`, next to the
  stage, as relative asset paths; and `<stem>.extract/preview.png`.

Contact sets and trajectories that an earlier `extract` or `fit` put in the fit layer are replaced
(a fit's `_fitted` trajectories of replaced contacts go too). The layer and the mask folder are
written atomically (temp + rename).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, Vt

from ..errors import InputError
from .stage import GENERATOR, SCENE, LayerPaths, atomic_outputs, check_our_root

CONTACT_TYPE = "PhysInteractContactSet"
TRAJECTORY_TYPE = "PhysInteractTrajectory"


def extract_dir(stage_path) -> Path:
    """`<stem>.extract/` next to the stage: hand masks and the preview."""
    lp = LayerPaths.of(stage_path)
    stem = lp.root.name[: -len(lp.root.suffix)] if lp.root.suffix else lp.root.name
    return lp.root.with_name(f"{stem}.extract")


def user_contact_names(stage_path) -> list[str]:
    """Names of the contact sets the user authored in the stage's root layer (these win: extraction
    does not replace them)."""
    lp = LayerPaths.of(stage_path)
    layer = Sdf.Layer.FindOrOpen(str(lp.root))
    if layer is None:
        return []
    spec = layer.GetPrimAtPath(SCENE)
    if spec is None:
        return []
    names = []
    for child in spec.nameChildren:
        if child.typeName == CONTACT_TYPE or (child.specifier == Sdf.SpecifierOver and
                                              "physinteract:particleIndices" in child.attributes):
            names.append(child.name)
    return names


def read_contact_extras(stage_path) -> dict:
    """{contact name: {"normal": (3,), "friction": float}} from the custom attributes extraction
    writes on collider contact sets (the schema has no field for them yet)."""
    stage = Usd.Stage.Open(str(stage_path))
    out = {}
    scene = stage.GetPrimAtPath(SCENE)
    if not scene:
        return out
    for child in scene.GetChildren():
        if child.GetTypeName() != CONTACT_TYPE:
            continue
        d = {}
        a = child.GetAttribute("physinteract:contactNormal")
        if a and a.HasValue():
            d["normal"] = tuple(float(x) for x in a.Get())
        a = child.GetAttribute("physinteract:friction")
        if a and a.HasValue():
            d["friction"] = float(a.Get())
        if d:
            out[child.GetName()] = d
    return out


def _fresh_fit_layer(lp: LayerPaths, fps: float, n: int) -> Sdf.Layer:
    """An anonymous copy of the current fit layer (or a new one), to edit and export."""
    if lp.fit.exists():
        src = Sdf.Layer.OpenAsAnonymous(str(lp.fit))
        if src is None:
            raise InputError(lp.fit, "cannot be opened as a USD layer")
        return src
    layer = Sdf.Layer.CreateAnonymous("fit.usdc")
    layer.defaultPrim = "World"
    layer.timeCodesPerSecond = fps
    layer.framesPerSecond = fps
    layer.startTimeCode = 0
    layer.endTimeCode = n - 1
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "fit"}}
    return layer


def _remove_old(layer: Sdf.Layer, replace: set[str], keep: set[str]) -> list[str]:
    """Remove contact sets (and the trajectories that move them) from the layer: those named in
    `replace`, or, with `replace` empty, all but `keep`. Returns the names removed."""
    spec = layer.GetPrimAtPath(SCENE)
    if spec is None:
        return []
    removed = []
    contacts = [c.name for c in spec.nameChildren if c.typeName == CONTACT_TYPE and c.name not in keep]
    if replace:
        contacts = [c for c in contacts if c in replace]
    gone = set(contacts)
    for child in list(spec.nameChildren):
        if child.name in gone:
            removed.append(child.name)
            del spec.nameChildren[child.name]
        elif child.typeName == TRAJECTORY_TYPE:
            rel = child.relationships.get("physinteract:contactSet")
            targets = [t.name for t in rel.targetPathList.GetAddedOrExplicitItems()] if rel is not None else []
            base = child.name.rsplit("_", 1)[0]
            if (targets and targets[0] in gone) or (not targets and base in gone):
                del spec.nameChildren[child.name]
    return removed


def write_extraction(stage_path, scene, contacts, hand_masks, *, trajectories_for=None,
                     preview_png: np.ndarray | None = None) -> dict:
    """Write extracted contacts (`ExtractedContact`s) and hand masks into the stage's fit layer
    and `<stem>.extract/`.

    Every contact set in the fit layer that the user does not also author in the root layer is
    replaced by `contacts`; trajectories_for: {user contact name: (T, 3)} initial trajectories
    for the user's contacts that had none; preview_png: a BGR uint8 image. Returns {"layer",
    "hand_masks", "preview", "contacts", "removed"}."""
    from ..frames import write_mask

    lp = LayerPaths.of(stage_path)
    check_our_root(lp.root)
    n = scene.n_frames
    layer = _fresh_fit_layer(lp, scene.fps, n)
    user = set(user_contact_names(stage_path))
    removed = _remove_old(layer, set(), keep=user)
    stage = Usd.Stage.Open(layer)
    scene_prim = stage.OverridePrim(SCENE)
    dt = 1.0 / scene.fps
    written = []

    def author_trajectory(name: str, contact_path, traj):
        tp = stage.DefinePrim(SCENE.AppendChild(f"{name}_initial"), TRAJECTORY_TYPE)
        tp.GetAttribute("physinteract:stage").Set("initial")
        tp.GetRelationship("physinteract:contactSet").SetTargets([contact_path])
        traj = np.asarray(traj, np.float64)
        vel = np.vstack([np.diff(traj, axis=0) / dt, np.zeros((1, 3))])
        pa, va = tp.GetAttribute("physinteract:position"), tp.GetAttribute("physinteract:velocity")
        for k in range(len(traj)):
            pa.Set(Gf.Vec3f(*map(float, traj[k])), Usd.TimeCode(k))
            va.Set(Gf.Vec3f(*map(float, vel[k])), Usd.TimeCode(k))

    for c in contacts:
        if c.name in user:
            continue  # the user's own set of that name wins
        cp = stage.DefinePrim(SCENE.AppendChild(c.name), CONTACT_TYPE)
        ca = lambda n, v, p=cp: p.GetAttribute(f"physinteract:{n}").Set(v)  # noqa: E731
        ca("particleIndices", Vt.IntArray.FromNumpy(np.asarray(c.indices, np.int32)))
        ca("contactType", c.type)
        ca("graspTime", float(c.grasp_frame))
        ca("releaseTime", float(c.release_frame) if c.release_frame is not None else 1e9)
        ca("source", "user" if c.source == "hint" else "extracted")  # a hinted set is the user's choice
        ca("colliderRadius", float(c.radius))
        if c.type == "fixed":
            ca("extentGuessed", bool(c.guessed))
        ca("contactPoint", Gf.Vec3f(*map(float, c.contact_point)))
        if c.type in ("pointNonAdherent", "surfaceNonAdherent"):
            ca("contactNormal", Gf.Vec3f(*map(float, c.normal)))
            ca("friction", float(c.friction))
        if c.trajectory is not None:
            author_trajectory(c.name, cp.GetPath(), c.trajectory)
        written.append(c.name)
    for name, traj in (trajectories_for or {}).items():
        author_trajectory(name, SCENE.AppendChild(name), traj)
        written.append(f"{name}_initial")

    # hand masks and the preview into <stem>.extract/ (a temp folder renamed into place)
    out_dir = extract_dir(stage_path)
    tmp_dir = out_dir.with_name(f".{out_dir.name}.tmp{os.getpid()}")
    old_dir = out_dir.with_name(f".{out_dir.name}.old{os.getpid()}")
    shutil.rmtree(tmp_dir, ignore_errors=True)
    (tmp_dir / "hand_masks").mkdir(parents=True)
    assets = []
    try:
        for k, m in enumerate(hand_masks):
            write_mask(tmp_dir / "hand_masks" / f"{k:06d}.png", m)
            assets.append(Sdf.AssetPath(f"./{out_dir.name}/hand_masks/{k:06d}.png"))
        if preview_png is not None:
            import cv2

            if not cv2.imwrite(str(tmp_dir / "preview.png"), preview_png):
                raise OSError(f"{out_dir / 'preview.png'}: could not write")
        scene_prim.CreateAttribute("physinteract:handMasks", Sdf.ValueTypeNames.AssetArray, custom=False).Set(
            Sdf.AssetPathArray(assets))
        data = dict(layer.customLayerData)
        phys = dict(data.get("physinteract", {}))
        phys.update({"generator": GENERATOR, "layer": "fit", "extracted": True})
        data["physinteract"] = phys
        layer.customLayerData = data
        with atomic_outputs(lp.fit) as (tmp,):
            if not layer.Export(str(tmp)):
                raise OSError(f"{lp.fit}: could not write the fit layer")
            if out_dir.exists():
                os.replace(out_dir, old_dir)
            os.replace(tmp_dir, out_dir)
        shutil.rmtree(old_dir, ignore_errors=True)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
    # a cached copy of the fit layer would hide the new file from the next read
    cached = Sdf.Layer.Find(str(lp.fit))
    if cached is not None:
        cached.Reload(force=True)
    return {"layer": str(lp.fit), "hand_masks": str(out_dir / "hand_masks"),
            "preview": str(out_dir / "preview.png") if preview_png is not None else None,
            "contacts": written, "removed": removed}
