"""From a stage to the core's inputs: the observations (frames, silhouettes, hand masks), the
contacts, the effects and the starting point of a resumed fit. The verbs use these; so may
benchmarks and experiments that need the pieces of a verb."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..fit.problem import Observations
from ..scene import SceneData
from ..usd.stage import read_stage


def read_scene(stage_path) -> SceneData:
    """The composed stage as plain Python objects (InputError for a missing or foreign file)."""
    return read_stage(stage_path)


def hand_masks(sd: SceneData, n: int | None = None) -> np.ndarray | None:
    """(n, H, W) bool: the hand's pixels per frame (left out of every image term), from extraction."""
    from ..frames import read_mask

    if not sd.hand_mask_assets:
        return None
    n = sd.n_frames if n is None else n
    return np.stack([read_mask(p) for p in sd.hand_mask_assets[:n]])


def load_observations(sd: SceneData, *, with_hand_masks: bool = True) -> Observations:
    """Frames and masks a stage refers to, as arrays (the fit's observations); the hand masks
    extraction wrote, unless `with_hand_masks` is False."""
    from ..frames import ImageSequence, VideoFile, read_mask

    if sd.frame_assets:
        src = ImageSequence([Path(p) for p in sd.frame_assets])
    elif sd.video_asset:
        src = VideoFile(sd.video_asset)
    else:
        raise InputError(sd.path, "the stage names no frames and no video")
    if len(src) < sd.n_frames:
        raise InputError(src.path, f"{len(src)} frames but the stage expects {sd.n_frames}")
    frames = np.stack([src.read(k) for k in range(sd.n_frames)]).astype(np.float32)
    masks = None
    if sd.mask_assets:
        masks = np.stack([read_mask(p) for p in sd.mask_assets[: sd.n_frames]])
    return Observations(frames=frames, masks=masks,
                        hand_masks=hand_masks(sd, sd.n_frames) if with_hand_masks else None)


def stage_contacts(sd: SceneData) -> list:
    """The contact sets the stage holds (user, extracted or an earlier fit's), checked: each
    interaction has an initial trajectory of one sample per frame."""
    for c in sd.contacts:
        if c.trajectory is not None and len(c.trajectory) != sd.n_frames:
            raise InputError(sd.path, f"trajectory of {c.name} has {len(c.trajectory)} samples for {sd.n_frames} frames")
        if c.type != "fixed" and c.trajectory is None:
            raise InputError(sd.path, f"contact set {c.name} ({c.type}) has no initial trajectory")
    return list(sd.contacts)


def true_contacts(sd: SceneData, gt_dir) -> list:
    """Contacts, supports and T0 from a synthetic capture's ground truth (`fit --contact-from`)."""
    from ..synth.gt import read_gt_contacts

    return read_gt_contacts(gt_dir, sd.particles_positions, sd.n_frames)


def true_hand_masks(gt_dir, n: int) -> np.ndarray | None:
    """The synthetic ground truth's hand masks (None when it has none)."""
    from ..frames import read_mask

    hm = Path(gt_dir) / "hand_masks"
    if not hm.is_dir():
        return None
    return np.stack([read_mask(hm / f"{k:06d}.png") for k in range(n)])


def stage_effects(sd: SceneData) -> dict:
    """{effect: {parameter: value}} the stage switches on (without the schema's `fit` flags)."""
    return {name: {k: v for k, v in params.items() if k != "fit"} for name, params in sd.effects.items()}


def effects_with_fitted(sd: SceneData) -> dict:
    """The stage's effects with the values its current fit version found for them."""
    effects = stage_effects(sd)
    rep = sd.current_report
    if rep is not None:
        for e, p in rep.get("effect_parameters", {}).items():
            effects.setdefault(e, {}).update(p)
    return effects
