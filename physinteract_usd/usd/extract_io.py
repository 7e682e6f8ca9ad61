"""What `extract` writes: contact sets, their initial trajectories (T0) and the hand masks, into the
stage's fit layer (stronger than init, weaker than the user's root), keeping whatever else that
layer holds (fit reports, a fitted material, animation).

- contact sets and `<contact>_initial` trajectories through the contact codec (`usd.contacts`);
- `physinteract:handMasks` on /World/PhysInteract: PNGs in `<stem>.extract/hand_masks/`, next to the
  stage, as relative asset paths; and `<stem>.extract/preview.png`.

Contact sets that an earlier `extract` or `fit` put in the fit layer are replaced (with the
trajectories that move them); the user's own sets (authored in the root layer) win and are left
alone. The layer and the mask folder are written atomically (temp + rename).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd

from .contacts import authored_contact_names, remove_contacts, write_contact, write_trajectory
from .layout import SCENE, LayerPaths, check_our_root, mark_layer, open_fit_layer, save_layer


def extract_dir(stage_path) -> Path:
    """`<stem>.extract/` next to the stage: hand masks and the preview."""
    return LayerPaths.of(stage_path).sibling(".extract")


def user_contact_names(stage_path) -> list[str]:
    """Names of the contact sets the user authored in the stage's root layer (these win: extraction
    does not replace them)."""
    return authored_contact_names(Sdf.Layer.FindOrOpen(str(LayerPaths.of(stage_path).root)), SCENE)


def write_extraction(stage_path, scene, contacts, hand_masks, *, trajectories_for=None,
                     preview_png: np.ndarray | None = None) -> dict:
    """Write extracted contacts (`contacts.ContactSet`s) and hand masks into the stage's fit layer
    and `<stem>.extract/`.

    Every contact set in the fit layer that the user does not also author in the root layer is
    replaced by `contacts`; trajectories_for: {user contact name: (T, 3)} initial trajectories
    for the user's contacts that had none; preview_png: a BGR uint8 image. Returns {"layer",
    "hand_masks", "preview", "contacts", "removed"}."""
    from ..frames import write_mask

    lp = LayerPaths.of(stage_path)
    check_our_root(lp.root)
    layer = open_fit_layer(lp, scene.fps, scene.n_frames)
    user = set(user_contact_names(stage_path))
    removed = remove_contacts(layer, SCENE, keep=user)
    stage = Usd.Stage.Open(layer)
    scene_prim = stage.OverridePrim(SCENE)
    written = []
    for c in contacts:
        if c.name in user:
            continue  # the user's own set of that name wins
        write_contact(stage, SCENE, c, scene.particles_positions, scene.fps)
        written.append(c.name)
    for name, traj in (trajectories_for or {}).items():
        write_trajectory(stage, SCENE, name, traj, "initial", scene.fps)
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
        mark_layer(layer, layer="fit", extracted=True)
        save_layer(layer, lp.fit)
        if out_dir.exists():
            os.replace(out_dir, old_dir)
        os.replace(tmp_dir, out_dir)
        shutil.rmtree(old_dir, ignore_errors=True)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
    return {"layer": str(lp.fit), "hand_masks": str(out_dir / "hand_masks"),
            "preview": str(out_dir / "preview.png") if preview_png is not None else None,
            "contacts": written, "removed": removed}
