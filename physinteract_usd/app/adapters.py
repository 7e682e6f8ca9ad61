"""From a stage to the core's inputs: the observations (frames, silhouettes, hand masks), the
contacts, the effects and the starting point of a resumed fit. The verbs use these; so may
benchmarks and experiments that need the pieces of a verb."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from typing import TYPE_CHECKING

if TYPE_CHECKING:     # the fit (torch) loads only where observations are built: `info` and `export` need none
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
    from ..fit.problem import Observations

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


def nuisance_effects(rep: dict | None) -> set:
    """The effects a fit version fitted as nuisances, not the user's: a damping `fit --nuisance-damping`
    switched on for that fit (`FitSettings.nuisance_damping` is recorded True only when it did, #24)."""
    if not rep or not (rep.get("settings") or {}).get("nuisance_damping"):
        return set()
    return {"damping"} & set(rep.get("effects") or [])


def effects_with_fitted(sd: SceneData) -> dict:
    """The stage's effects with the values its current fit version found for them."""
    effects = stage_effects(sd)
    rep = sd.current_report
    if rep is not None:
        for e, p in rep.get("effect_parameters", {}).items():
            effects.setdefault(e, {}).update(p)
    return effects


def measured_tracks(sd: SceneData, obs: Observations, *, cache: bool = True, max_points: int = 3000,
                    device: str = "cpu", progress=None):
    """Point tracks measured on the stage's video (`extract.track.measure_tracks`: DIS flow, checked
    forward-backward) from the Gaussians it shows at frame 0 (the object at rest, rendered through
    the stage's camera: opaque, front surface, inside the silhouette, off the hand), and from
    textured static background (the tracker's noise; a static camera only), as a
    `compare.GaussianTracks`. Cached in `<stem>.report/tracks.npz` next to the stage, keyed by the
    frames, hand masks and start points."""
    import hashlib
    import os

    import torch

    from ..compare import GaussianTracks, ModelAnimation, background_points, render_frames, track_start
    from ..compare.noise import static_background
    from ..extract.track import DenseFlowTracker, measure_tracks
    from ..render import covariance_from_scales_quats
    from ..usd.layout import LayerPaths

    g = sd.gaussians
    covs = covariance_from_scales_quats(torch.as_tensor(g.scales, dtype=torch.float32),
                                        torch.as_tensor(g.quats, dtype=torch.float32)).numpy()
    rest = render_frames(ModelAnimation(g.means[None], covs[None], g.colors, g.opacities), sd.camera,
                         np.zeros(3, np.float32), device=device)
    sil0 = None if obs.masks is None else obs.masks[0]
    hand0 = None if obs.hand_masks is None else obs.hand_masks[0]
    ids, uv0 = track_start(g.means, rest["alpha"][0], rest["depth"][0], sd.camera, sd.settings.particle_spacing,
                           silhouette=sil0, hand=hand0, max_points=max_points)
    bg_pts = np.zeros((0, 2))
    if sd.camera.is_static:
        cover = rest["alpha"][0][None] > 0.05
        if obs.masks is not None:
            cover = cover | obs.masks
        if obs.hand_masks is not None:
            cover = cover | obs.hand_masks
        bg_pts = background_points(obs.frames[0], static_background(cover, obs.frames.shape[1:3]))
    tracker = DenseFlowTracker()
    key = hashlib.sha1()
    for a in (obs.frames, obs.hand_masks, ids, uv0, bg_pts):
        if a is not None:
            key.update(np.ascontiguousarray(a).tobytes())
    key.update(repr((tracker.name, tracker.min_width, tracker.fb_tolerance, tracker.appearance_tolerance, 1)).encode())
    key = key.hexdigest()[:16]
    path = LayerPaths.of(sd.path).sibling(".report") / "tracks.npz"
    if cache and path.exists():
        try:
            with np.load(path) as z:
                if str(z["key"]) == key:
                    n = len(ids)
                    return GaussianTracks(ids, z["uv"][:, :n], z["valid"][:, :n], z["fb"][:, :n],
                                          z["uv"][:, n:] if sd.camera.is_static else None,
                                          z["valid"][:, n:] if sd.camera.is_static else None)
        except (OSError, KeyError, ValueError):
            pass   # a stale or broken cache is measured again
    pts = np.concatenate([uv0, bg_pts])
    t = measure_tracks(obs.frames, pts, start=0, stop=obs.hand_masks, tracker=tracker, progress=progress)
    if cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".tracks.tmp{os.getpid()}.npz")
            np.savez_compressed(tmp, key=key, uv=t.uv.astype(np.float32), valid=t.valid, fb=t.fb_error.astype(np.float32))
            tmp.replace(path)
        except OSError:
            pass   # a read-only folder: no cache
    n = len(ids)
    return GaussianTracks(ids, t.uv[:, :n], t.valid[:, :n], t.fb_error[:, :n],
                          t.uv[:, n:] if sd.camera.is_static else None, t.valid[:, n:] if sd.camera.is_static else None)
