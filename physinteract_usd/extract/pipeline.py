"""Interaction extraction from a video: where the hand touches the object, when it grasps and lets
go, how (interaction type), how it moves (the initial trajectory T0), and what holds the object
still (supports). numpy / OpenCV / scipy only; no USD (the stage I/O is `usd.extract_io`).

The method (docs/extract.md has the full account), one module per question:

1. render the object at rest through the camera (silhouette, depth, particle visibility)
   (`analysis.Analysis`, `geometry.render_rest`);
2. segment the hand in every frame (`models.segmenter`, default `segmentation.ColourMotionSegmenter`)
   and compute optical flow (`models.tracker`, default `track.DenseFlowTracker`) (`analysis.Analysis`);
3. per frame, the contact region = hand pixels over the object at rest or next to its visible
   silhouette (`contact.find_contact`); per frame pair, the hand's and the object's velocities
   near it (`timing.velocities`, `timing.coupling`);
4. timing (`timing.find_timing`): the contact period = the longest run of frames in which the hand
   touches the object; the grasp is where the hand comes to (near) rest on the object before its
   main motion; the release is the hand's slowest frame before the object stops following it;
5. type (`interaction_type.classify`, rules in `interaction_type.classify_interaction`): a contact
   whose first main motion moves the object away from the hand's body is a push (non-adherent),
   unless the hand went back the way it came in (a pull in depth); an object pressed in that never
   follows the toucher out past its rest surface (read against the silhouette's normal or the
   toucher's approach) is pushed; a toucher whose front is at least 6 cm wide (else, unmeasured, a
   long straight hand-object interface) is a surface (a palm); else adherent. All read while the
   toucher acts: up to its first pair at over 3x its acting pace (`interaction_type.acting_end`:
   its departure, whose flow leaks into the object next to it);
6. contact particles (`contact.contact_at_grasp`, `contact.contact_particles`): the contact pixels
   at the grasp frame back-projected with the rendered depth (X = T_c^-1 pi^-1(x, d)) and mapped
   to the particles within a radius;
7. T0 (`lifting.track_hand`, `lifting.lift_trajectory`): the hand's velocity at the contact
   integrated from the grasp, lifted to 3D (at the contact's depth for a pull, along the push
   direction for a collider: its first main motion while it acts);
8. supports (`supports.support_contacts`, `supports.find_supports`): particles that do not move
   while the rest does (tracked, interpolated to the ones the camera does not see), grouped into
   connected regions; gravity says a still object that would otherwise fall is held somewhere, so
   the stillest particles are taken when no region is.

The user's hints (`hints.parse_hint`, checked by `hints.check_hint`) and `interaction_type` win
over detection.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from .analysis import Analysis
from .contact import contact_at_grasp, contact_particles, find_contact, pushing_edge
from .hints import check_hint
from .interaction_type import classify
from .lifting import lift_trajectory, track_hand
from .models import Models
from .result import INTERACTION_TYPES, ExtractionResult, Hint
from .supports import above_floor, support_contacts, toucher_acting, toucher_low, unpin
from . import timing as _timing
from .timing import (apply_overrides, collider_back_out, collider_release, collider_start, find_timing, ramp_start,
                     timing_confidence)


def extract_interaction(scene, frames, masks=None, *, masks_amodal: bool = False, hint: Hint | None = None,
                        interaction_type: str | None = None, models: Models | None = None,
                        log=print, device: str = "cpu") -> ExtractionResult:
    """Extract the interaction from a video of the stage's object.

    scene: a `SceneData` (read_stage); frames (T, H, W, 3) float in [0, 1]; masks (T, H, W) bool
    object silhouettes or None. `hint` and `interaction_type` win over detection. Returns an
    `ExtractionResult` (contacts with the fit's fields, hand masks, evidence). `device` (cpu or
    cuda) is where the object at rest is rendered for depth; the rest runs on the CPU."""
    models = models or Models()
    frames = check_inputs(scene, frames, interaction_type)
    hint = check_hint(hint, scene, len(frames))
    notes = []
    an = Analysis(scene, frames, masks, masks_amodal, models, device)                       # 1, 2
    if not an.static_camera:
        notes.append("the camera moves: image-space motion cues (timing, supports) assume a static camera "
                     "and are unreliable")
    evidence = {"spacing_px": an.spacing_px, "object_size_px": an.obj_size_px, "radius_px": an.R,
                "hand_pixels": int(an.hand.sum()), "models": models.describe()}

    seen = find_contact(an, hint, evidence)                                                 # 3: where
    timing = find_timing(an, seen, evidence)                                                # 4: when
    timing = apply_overrides(timing, hint, evidence, notes)                                 # the user's word
    g = timing.grasp
    grasp = contact_at_grasp(an, seen, g)
    hand = track_hand(timing, grasp.uv)
    itype, conf, tsource = classify(an, timing, grasp.uv, hand, evidence, models,           # 5: how
                                    interaction_type, frames)
    rules = timing_method() != "model"    # the model reads every toucher alike: no collider rules
    if rules and itype != "pointAdherent" and evidence.get("timing_source", {}).get("grasp") != "user":
        g2 = collider_start(timing, an.eps)
        if g2 != g:   # a collider acts from when the object starts to give
            timing.grasp = g = g2
            evidence["grasp_frame"] = g
            grasp = contact_at_grasp(an, seen, g)
            hand = track_hand(timing, grasp.uv)
    if rules and evidence.get("timing_source", {}).get("grasp") != "user":
        g2 = ramp_start(timing, an.eps)
        if g2 != g:   # the toucher began to act at the foot of its speed ramp (a motion from rest)
            evidence["grasp_ramp"] = [g, g2]
            timing.grasp = g = g2
            evidence["grasp_frame"] = g
            grasp = contact_at_grasp(an, seen, g)
            hand = track_hand(timing, grasp.uv)
    if rules and itype != "pointAdherent" and evidence.get("timing_source", {}).get("release") != "user":
        r2 = collider_release(timing, hand.first_move, an.eps)
        if r2 != timing.release:   # a collider moving on into the object has not let go of it
            timing.release = r2
            evidence["release_frame"] = r2
            hand = track_hand(timing, grasp.uv)
    if not rules and itype != "pointAdherent" and evidence.get("timing_source", {}).get("release") != "user":
        r2 = collider_back_out(g, timing.release, timing.hand_velocity, timing.near)
        if r2 != timing.release:   # a collider touches until it is back out where it first touched
            timing.release = r2
            evidence["release_frame"] = r2
            hand = track_hand(timing, grasp.uv)
    timing_confidence(timing, an.eps, evidence, notes)
    if itype == "pointNonAdherent" and seen.hint_uv is None and seen.hint_particles is None:
        grasp = pushing_edge(an, grasp, hand.first_move, g)
    c3d = contact_particles(an, hint, itype, seen, grasp, g, evidence, notes)               # 6: where, in 3D
    lift_hand = hand
    if itype != "pointAdherent" and evidence.get("acting_end") is not None and \
            (timing.release is None or evidence["acting_end"] < timing.release):
        # a collider pushes the way it moved while it acted, not the way it left at a transit's pace
        # (#23: dev_0213's palm, pressing down, lifted along its 44 px departure up, its plane 7 cm
        # above the block): the same track, its first main motion read up to `acting_end`
        lift_hand = track_hand(replace(timing, release=evidence["acting_end"]), grasp.uv)
    lifted = lift_trajectory(an, hint, itype, timing, grasp, lift_hand, c3d, evidence)      # 7: T0
    held = c3d.particles if itype == "pointAdherent" else np.zeros(0, np.int64)
    low = None
    if lifted.contact.trajectory is not None:
        # (c) of the floor's test: the toucher only where it acts on the object
        acting = toucher_acting(np.asarray(lifted.contact.trajectory), itype, lifted.contact.radius, an.x0,
                                an.spacing, g, lifted.release)
        low = toucher_low(lifted.contact.trajectory, lifted.trajectory_flat, lifted.contact.radius, itype,
                          float(an.x0[:, 1].min()), acting, evidence)
        evidence["toucher_acting_frames"] = int(acting.sum())
    supports, motion_p = support_contacts(an, hint, held, acting_motion(hand, g, lifted.release, itype),  # 8: supports
                                          lifted.push_dir, evidence, notes, lowest_contact_y=low)
    contact = lifted.contact
    if not (hint is not None and hint.has_support):
        supports = unpin(an.x0, an.spacing, contact, supports, notes, evidence)
    contact = above_floor(an.x0, contact, evidence.get("floor"), notes, evidence, an.scene.camera)  # not through it
    return ExtractionResult(contacts=[contact] + supports, hand_masks=an.hand, interaction_type=itype,
                            type_source=tsource,
                            grasp_frame=int(contact.grasp_frame) if itype == "pointAdherent" else g,
                            release_frame=lifted.release, evidence=evidence, notes=notes, frames=frames,
                            object_masks=an.obj, support_motion=motion_p, track_uv=lifted.track_uv,
                            contact_pixels=c3d.pixels, type_confidence=conf)


def timing_method() -> str:
    """"model" (the ninth pass's `timing.held_window`), "rules" (the passes' cascade) or "hybrid"
    (the model's grasp, the rules' release)."""
    return _timing.METHOD


def acting_motion(hand, g: int, r: int | None, itype: str) -> float:
    """The scale against which the supports' stillness is judged: the hand's largest image
    displacement from the grasp over the contact period; a collider's (a fingertip's, a palm's)
    only while it acts, to its release: its retreat moves nothing (dev_0009: a palm lifted off a
    sheet 26 px after pressing it by 1-2 px made the whole still sheet 'held' at a 2 px
    threshold). (A grasp's is kept over the period: on the dev split, cutting it at the release
    lost dev_0006's hanging support and invented one on dev_0004.)"""
    if itype == "pointAdherent" or r is None or r <= g:
        return float(hand.motion)
    d = hand.uv[g:r + 1] - hand.uv[g]
    return float(np.linalg.norm(d, axis=1).max())


def check_inputs(scene, frames, interaction_type: str | None) -> np.ndarray:
    """The frames as (T, H, W, 3) float32, checked against the camera (at least 3 of them), and
    the type the user gave; InputError otherwise."""
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise InputError(scene.path, "frames must be (T, H, W, 3)")
    T = len(frames)
    if T < 3:
        raise InputError(scene.path, f"extraction needs at least 3 frames, the stage has {T}")
    if (frames.shape[2], frames.shape[1]) != (scene.camera.width, scene.camera.height):
        raise InputError(scene.path, f"frames are {frames.shape[2]}x{frames.shape[1]}, the camera "
                         f"{scene.camera.width}x{scene.camera.height}")
    if interaction_type is not None and interaction_type not in INTERACTION_TYPES:
        raise InputError("--type", f"must be one of {', '.join(INTERACTION_TYPES)}, not {interaction_type!r}")
    return frames
