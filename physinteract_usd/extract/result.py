"""What extraction returns: plain Python objects (no USD), and the user's hint."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..contacts import DEFAULT_NAMES as CONTACT_NAMES
from ..contacts import INTERACTION_TYPES


@dataclass
class Hint:
    """A user's hint that wins over detection: a pixel (u, v) (continuous coordinates, pixel
    centres at +0.5) in frame `frame` where the hand touches the object, and/or the particles
    (indices into SimParticles) the hand holds or pushes. For the supports: `support_pixels`, a
    list of (frame, (u, v)) where the object is held (each keeps the detected still region there,
    or makes a support of the particles within SUPPORT_HINT_RADIUS_M of that point when none was
    detected there; detected regions elsewhere are dropped), or `support_particles`, the particles
    held still (exactly those). `grasp_radius` [m]: how much the hand holds, the particles within
    it of the contact (pointAdherent), or the fingertip's radius (pointNonAdherent): the video
    shows where a hand grasps but not how much material it holds. `grasp_frame` / `release_frame`:
    when the hand takes hold (or starts touching) and lets go (`release_frame` NEVER: held to the
    end), for a video that does not show it; they win over the detected timing."""

    frame: int | None = None
    pixel: tuple | None = None
    particles: np.ndarray | None = None
    support_pixels: list | None = None
    support_particles: np.ndarray | None = None
    grasp_radius: float | None = None
    grasp_frame: int | None = None
    release_frame: int | None = None       # NEVER (-1): the hand holds on to the end

    NEVER = -1

    @property
    def has_timing(self) -> bool:
        return self.grasp_frame is not None or self.release_frame is not None

    @property
    def is_empty(self) -> bool:
        """No hint on where the hand touches (support and grasp-size hints aside)."""
        return self.pixel is None and (self.particles is None or len(self.particles) == 0)

    @property
    def has_support(self) -> bool:
        return bool(self.support_pixels) or (self.support_particles is not None and len(self.support_particles) > 0)


@dataclass
class ExtractionResult:
    contacts: list                         # contacts.ContactSet: the interaction(s) first, then supports
    hand_masks: np.ndarray                 # (T, H, W) bool
    interaction_type: str
    type_source: str                       # detected | user | stage
    grasp_frame: int
    release_frame: int | None
    evidence: dict = field(default_factory=dict)   # the numbers the decisions were taken on
    notes: list = field(default_factory=list)
    frames: np.ndarray | None = None       # the frames (for the preview), not written
    object_masks: np.ndarray | None = None
    support_motion: np.ndarray | None = None  # (P,) per-particle motion measure [px]
    outputs: dict = field(default_factory=dict)   # what `extract` wrote (paths, contact names)
    # how the interaction contact was found (the preview draws them; not written to the stage)
    track_uv: np.ndarray | None = None     # (T, 2) the hand's 2D track the trajectory was lifted from
    contact_pixels: np.ndarray | None = None  # (N, 2) contact pixels (uv) in the grasp frame
    type_confidence: float = 1.0

    loss_margin_px: int = 1                # the written masks grow the hand by this much

    @property
    def loss_masks(self) -> np.ndarray:
        """The masks the loss leaves out (written to the stage): the hand grown by
        `loss_margin_px`, so that its anti-aliased rim (skin mixed into the object) is left out too."""
        from .segmentation import dilate

        return np.stack([dilate(m, self.loss_margin_px) for m in self.hand_masks])

    @property
    def interaction(self) -> list:
        return [c for c in self.contacts if c.type != "fixed"]

    @property
    def supports(self) -> list:
        return [c for c in self.contacts if c.type == "fixed"]

    def summary(self) -> dict:
        """A JSON-able summary (what `extract --json` prints)."""
        out = {"interaction_type": self.interaction_type, "type_source": self.type_source,
               "grasp_frame": int(self.grasp_frame),
               "release_frame": None if self.release_frame is None else int(self.release_frame),
               "contacts": [], "hand_pixels_per_frame": [int(m.sum()) for m in self.hand_masks],
               "evidence": _jsonable(self.evidence), "notes": list(self.notes),
               "outputs": _jsonable(self.outputs)}
        for c in self.contacts:
            d = {"name": c.name, "type": c.type, "particles": int(len(c.indices)), "source": c.source,
                 "grasp_frame": int(c.grasp_frame),
                 "release_frame": None if c.release_frame is None else int(c.release_frame),
                 "contact_point": [round(float(x), 5) for x in c.point()],
                 "confidence": round(float(self.type_confidence if c.is_interaction else 1.0), 3)}
            if c.type == "pointNonAdherent":
                d["radius"] = round(float(c.radius), 5)
            if c.type == "surfaceNonAdherent":
                d["normal"] = [round(float(x), 4) for x in c.normal]
            if c.trajectory is not None:
                tr = np.asarray(c.trajectory)
                d["displacement_m"] = [round(float(x), 5) for x in (tr.max(0) - tr.min(0))]
            out["contacts"].append(d)
        return out


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else round(float(o), 5)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.bool_,)):
        return bool(o)
    return o
