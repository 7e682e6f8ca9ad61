"""`extract`: where the hand touches the object, how it moves, and what holds the object still,
from the stage's video (the algorithm is `extract.extract_interaction`, on plain arrays); written
into the stage's fit layer with the hand masks and a preview.

The user's word wins: contact sets they authored in the root layer (an interaction contact of
theirs is kept, extraction only adds its T0 if it has none; fixed sets of theirs replace the
detected supports), hints and `--type`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..extract import ExtractionResult, Hint, Models, extract_interaction
from ..usd.extract_io import user_contact_names, write_extraction
from .adapters import load_observations, read_scene


def _user_hint(u, hint: Hint | None, sd) -> Hint | None:
    """The hint that the user's own interaction contact set `u` amounts to (its particles, else its
    contact point's pixel at frame 0), keeping the support, grasp-size and timing hints given."""
    support_hint = {} if hint is None else {"support_pixels": hint.support_pixels,
                                             "support_particles": hint.support_particles,
                                             "grasp_radius": hint.grasp_radius, "grasp_frame": hint.grasp_frame,
                                             "release_frame": hint.release_frame}
    if len(u.indices):
        return Hint(particles=np.asarray(u.indices, np.int64), **support_hint)
    if u.contact_point is not None and np.any(u.contact_point):
        uv, _ = sd.camera.at(0).project(np.asarray(u.contact_point, float)[None])
        if np.isfinite(uv).all() and 0 <= uv[0, 0] < sd.camera.width and 0 <= uv[0, 1] < sd.camera.height:
            return Hint(frame=0, pixel=(float(uv[0, 0]), float(uv[0, 1])), **support_hint)
    return Hint(**support_hint) if support_hint else None


def timing_said(result: ExtractionResult) -> str:
    """' (grasp and release as given)' where the user's flags set them."""
    src = result.evidence.get("timing_source", {})
    yours = [k for k in ("grasp", "release") if src.get(k) == "user"]
    return f" ({' and '.join(yours)} as given)" if yours else ""


def extract(stage_path, *, hint: Hint | None = None, interaction_type: str | None = None, log=print,
            preview: bool = True, models: Models | None = None, device: str = "cpu") -> ExtractionResult:
    """Extract the interaction from the stage's video and write it into the stage.

    Writes contact sets, initial trajectories (T0) and hand masks into `<stem>.fit.usdc` and
    `<stem>.extract/` (hand_masks/, preview.png). `hint` (a pixel in a frame, or particle indices,
    for the contact and / or the supports) and `interaction_type` win over detection. Returns the
    `ExtractionResult` (its `summary()` is what `extract --json` prints; `outputs` says what was
    written). `device`: where the object at rest is rendered (cpu or cuda)."""
    from ..extract.preview import preview_image

    stage_path = Path(stage_path)
    sd = read_scene(stage_path)
    obs = load_observations(sd, with_hand_masks=False)
    user_names = set(user_contact_names(stage_path))
    user_sets = [c for c in sd.contacts if c.name in user_names]
    user_inter = [c for c in user_sets if c.type != "fixed"]
    user_fixed = [c for c in user_sets if c.type == "fixed"]
    notes = []
    trajectories_for = {}
    if user_inter:
        u = user_inter[0]
        if (hint is not None and not hint.is_empty) or interaction_type is not None:
            notes.append(f"the stage's own contact set {u.name} wins over the hint / --type given")
        interaction_type = u.type
        hint = _user_hint(u, hint, sd)
    log(f"extracting the interaction from {sd.n_frames} frames ({sd.image_size[0]}x{sd.image_size[1]})")
    result = extract_interaction(sd, obs.frames, obs.masks, masks_amodal=sd.masks_amodal, hint=hint,
                                 interaction_type=interaction_type, models=models, log=log, device=device)
    result.notes = notes + result.notes
    contacts = list(result.contacts)
    if user_inter:
        u = user_inter[0]
        mine = result.interaction[0]
        if u.trajectory is None and mine.trajectory is not None:
            traj = mine.trajectory
            if len(u.indices):
                traj = traj - traj[0] + sd.particles_positions[u.indices].mean(0)
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
        taken.update(int(i) for i in c.indices)
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
            f"frames {c.grasp_frame}..{rel}{timing_said(result)}")
    n_sup = [len(c.indices) for c in contacts if c.type == "fixed"]
    log(f"supports: {len(n_sup)} fixed set(s) of {', '.join(map(str, n_sup)) or 'no'} particles")
    for n in result.notes:
        log(f"note: {n}")
    log(f"wrote {out['layer']} and {Path(out['hand_masks']).parent}")
    return result
