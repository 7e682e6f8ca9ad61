"""Interaction extraction from the video (the design's `extract` verb).

    from physinteract_usd.extract import extract, Hint
    result = extract("scene.usda")                         # detect, write scene.fit.usdc
    result = extract("scene.usda", interaction_type="pointNonAdherent",
                     hint=Hint(frame=5, pixel=(61.5, 40.5)))  # the user's word wins

`extract_interaction(scene, frames, masks, ...)` is the algorithm on plain arrays (no USD); the
stage I/O is `physinteract_usd.usd.extract_io`. Classical computer vision by default; learned
models plug in through `models.Models` (docs/extract.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .interaction import classify_interaction, extract_interaction
from .models import Models
from .result import INTERACTION_TYPES, ExtractedContact, ExtractionResult, Hint

__all__ = ["extract", "extract_interaction", "parse_hint", "Hint", "Models", "ExtractionResult",
           "ExtractedContact", "INTERACTION_TYPES", "classify_interaction"]


def _parse_pixel(text: str, flag: str) -> tuple[int, tuple[float, float]]:
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise InputError(flag, f"expected K,U,V (frame, column, row), got {text!r}")
    try:
        k = int(parts[0])
        u, v = float(parts[1]), float(parts[2])
    except ValueError:
        raise InputError(flag, f"expected an integer frame and two numbers, got {text!r}") from None
    if not (np.isfinite(u) and np.isfinite(v)):
        raise InputError(flag, f"pixel coordinates must be finite, got {text!r}")
    return k, (u + 0.5, v + 0.5)


def _parse_indices(text: str, flag: str) -> np.ndarray:
    try:
        idx = [int(p) for p in str(text).replace(" ", "").split(",") if p != ""]
    except ValueError:
        raise InputError(flag, f"expected comma-separated particle indices, got {text!r}") from None
    if not idx:
        raise InputError(flag, "no particle index given")
    return np.asarray(idx, np.int64)


def parse_hint(pixel: str | None = None, particles: str | None = None, support_pixels=None,
               support_particles: str | None = None, grasp_radius: float | None = None) -> Hint | None:
    """The CLI's hint flags: `--hint-pixel K,U,V` (frame K, pixel column U and row V as an image
    viewer shows them, 0-based; the pixel's centre is used), `--hint-particles I,J,...`
    (SimParticles indices), `--support-pixel K,U,V` (a list: where the object is held) and
    `--support-particles I,J,...`, `--grasp-radius R` (metres). None when none is given; InputError
    naming the flag otherwise."""
    if isinstance(support_pixels, str):
        support_pixels = [support_pixels]
    if (pixel is None and particles is None and not support_pixels and support_particles is None
            and grasp_radius is None):
        return None
    hint = Hint()
    if grasp_radius is not None:
        r = float(grasp_radius)
        if not np.isfinite(r) or r <= 0:
            raise InputError("--grasp-radius", f"must be a positive length in metres, got {grasp_radius}")
        hint.grasp_radius = r
    if pixel is not None:
        hint.frame, hint.pixel = _parse_pixel(pixel, "--hint-pixel")
    if particles is not None:
        hint.particles = _parse_indices(particles, "--hint-particles")
    if support_pixels:
        hint.support_pixels = [_parse_pixel(t, "--support-pixel") for t in support_pixels]
    if support_particles is not None:
        hint.support_particles = _parse_indices(support_particles, "--support-particles")
    return hint


def extract(stage_path, *, hint: Hint | None = None, interaction_type: str | None = None, log=print,
            preview: bool = True, models: Models | None = None, device: str = "cpu") -> ExtractionResult:
    """Extract the interaction from the stage's video and write it into the stage.

    Writes contact sets, initial trajectories (T0) and hand masks into `<stem>.fit.usdc` and
    `<stem>.extract/` (hand_masks/, preview.png). Contact sets the user authored in the root layer
    win: an interaction contact of theirs is kept (extraction only adds its T0 if it has none),
    fixed sets of theirs replace the detected supports. `hint` (a pixel in a frame, or particle
    indices, for the contact and / or the supports) and `interaction_type` win over detection. Returns the `ExtractionResult` (its
    `summary()` is what `extract --json` prints; `outputs` says what was written). `device`: where
    the object at rest is rendered (cpu or cuda)."""
    from ..api import load_observations
    from ..usd.extract_io import user_contact_names, write_extraction
    from ..usd.stage import read_stage
    from .preview import preview_image

    stage_path = Path(stage_path)
    sd = read_stage(stage_path)
    obs = load_observations(sd)
    user_names = set(user_contact_names(stage_path))
    user_sets = [c for c in sd.contacts if c.name in user_names]
    user_inter = [c for c in user_sets if c.contact_type != "fixed"]
    user_fixed = [c for c in user_sets if c.contact_type == "fixed"]
    notes = []
    trajectories_for = {}
    if user_inter:
        u = user_inter[0]
        if (hint is not None and not hint.is_empty) or interaction_type is not None:
            notes.append(f"the stage's own contact set {u.name} wins over the hint / --type given")
        interaction_type = u.contact_type
        support_hint = {} if hint is None else {"support_pixels": hint.support_pixels,
                                                 "support_particles": hint.support_particles,
                                                 "grasp_radius": hint.grasp_radius}
        hint = Hint(particles=np.asarray(u.particle_indices, np.int64), **support_hint) if len(u.particle_indices) else None
        if hint is None and np.any(u.contact_point):
            uv, _ = sd.camera.at(0).project(np.asarray(u.contact_point, float)[None])
            if np.isfinite(uv).all() and 0 <= uv[0, 0] < sd.camera.width and 0 <= uv[0, 1] < sd.camera.height:
                hint = Hint(frame=0, pixel=(float(uv[0, 0]), float(uv[0, 1])), **support_hint)
        if hint is None and support_hint:
            hint = Hint(**support_hint)
    log(f"extracting the interaction from {sd.n_frames} frames ({sd.image_size[0]}x{sd.image_size[1]})")
    result = extract_interaction(sd, obs.frames, obs.masks, masks_amodal=sd.masks_amodal, hint=hint,
                                 interaction_type=interaction_type, models=models, log=log, device=device)
    result.notes = notes + result.notes
    contacts = list(result.contacts)
    if user_inter:
        u = user_inter[0]
        has_traj = any(t.contact_set == u.name and t.stage in ("initial", "user", "groundTruth")
                       for t in sd.trajectories)
        mine = result.interaction[0]
        if not has_traj and mine.trajectory is not None:
            traj = mine.trajectory
            if len(u.particle_indices):
                traj = traj - traj[0] + sd.particles_positions[u.particle_indices].mean(0)
            trajectories_for[u.name] = traj
            result.notes.append(f"added an initial trajectory for your contact set {u.name}")
        contacts = [c for c in contacts if c.type == "fixed"]
        result.type_source = "stage"
    if user_fixed:
        contacts = [c for c in contacts if c.type != "fixed"]
        result.notes.append("your fixed contact sets replace the detected supports")
    # the simulator wants every particle in at most one adherent / fixed set
    taken = set()
    for c in user_sets:
        taken.update(int(i) for i in c.particle_indices)
    for c in contacts:
        if c.type in ("pointAdherent", "fixed") and taken:
            c.indices = np.array([i for i in c.indices if int(i) not in taken], np.int64)
        taken.update(int(i) for i in c.indices)
    contacts = [c for c in contacts if c.type != "fixed" or len(c.indices)]
    img = preview_image(result, sd) if preview else None
    out = write_extraction(stage_path, sd, contacts, result.loss_masks, trajectories_for=trajectories_for,
                           preview_png=img)
    result.outputs = out
    for c in result.contacts:
        if c.type == "fixed":
            continue
        rel = "end" if c.release_frame is None else c.release_frame
        log(f"contact {c.name}: {c.type} ({result.type_source}), {len(c.indices)} particles, "
            f"frames {c.grasp_frame}..{rel}")
    n_sup = [len(c.indices) for c in contacts if c.type == "fixed"]
    log(f"supports: {len(n_sup)} fixed set(s) of {', '.join(map(str, n_sup)) or 'no'} particles")
    for n in result.notes:
        log(f"note: {n}")
    log(f"wrote {out['layer']} and {Path(out['hand_masks']).parent}")
    return result
