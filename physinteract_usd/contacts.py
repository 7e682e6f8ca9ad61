"""The one contact type: what touches or holds the object, when, and how it moves.

A `ContactSet` is what a `PhysInteractContactSet` prim says, plus the initial trajectory T0 of the
`PhysInteractTrajectory` prim that moves it. Extraction produces them, the synthetic ground truth
and the `simulate` interaction spec are read into them, the stage codec (`usd.contacts`) reads and
writes them, the fit and `simulate` consume them (`simulation.build_simulation` turns them into the
simulator's `sim.Contact` controls). No USD and no torch here.

Types (the contract's names):
- ``pointAdherent``: the hand grasps ``indices`` from ``grasp_frame`` until ``release_frame``
  (None: never released); they follow ``trajectory``.
- ``pointNonAdherent``: a sphere of ``radius`` moving along ``trajectory`` pushes (never pulls).
- ``surfaceNonAdherent``: a plane through ``trajectory`` with unit ``normal`` (the object's side).
- ``fixed``: a support that holds ``indices`` still.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

CONTACT_TYPES = ("pointAdherent", "pointNonAdherent", "surfaceNonAdherent", "fixed")
INTERACTION_TYPES = CONTACT_TYPES[:3]
PIN_TYPES = ("pointAdherent", "fixed")          # hold particles
COLLIDER_TYPES = ("pointNonAdherent", "surfaceNonAdherent")
SOURCES = ("extracted", "user", "groundTruth")  # the stage's `physinteract:source` tokens
DEFAULT_NAMES = {"pointAdherent": "hand", "pointNonAdherent": "finger", "surfaceNonAdherent": "palm",
                 "fixed": "support"}


@dataclass
class ContactSet:
    """A contact or support. Frames are video frames (USD time codes); positions metres, world."""

    name: str
    type: str
    indices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # SimParticles held
    grasp_frame: int = 0
    release_frame: int | None = None          # None: never released
    trajectory: np.ndarray | None = None      # (T, 3) initial trajectory T0, frames 0..T-1
    radius: float = 0.0                       # pointNonAdherent: the sphere's radius [m]
    normal: tuple = (0.0, 1.0, 0.0)           # surfaceNonAdherent: unit normal toward the object
    friction: float = 0.5                     # colliders: Coulomb mu
    contact_point: np.ndarray | None = None   # where it touches at rest (None: the mean of `indices`)
    source: str = "extracted"                 # extracted | user | groundTruth
    guessed: bool = False                     # fixed: no still region was in view; the first fit sizes it

    def __post_init__(self):
        if self.type not in CONTACT_TYPES:
            raise ValueError(f"contact {self.name!r}: type must be one of {', '.join(CONTACT_TYPES)}, "
                             f"not {self.type!r}")
        if self.source not in SOURCES:
            raise ValueError(f"contact {self.name!r}: source must be one of {', '.join(SOURCES)}, not {self.source!r}")
        self.indices = np.asarray(self.indices if self.indices is not None else [], np.int64).reshape(-1)
        self.grasp_frame = int(self.grasp_frame)
        self.release_frame = None if self.release_frame is None else int(self.release_frame)
        if self.trajectory is not None:
            self.trajectory = np.asarray(self.trajectory, np.float64).reshape(-1, 3)
        if self.contact_point is not None:
            self.contact_point = np.asarray(self.contact_point, np.float64).reshape(3)
        self.normal = tuple(float(v) for v in self.normal)
        self.radius = float(self.radius)
        self.friction = float(self.friction)
        self.guessed = bool(self.guessed)

    # ------------------------------------------------------------------ what it is
    @property
    def is_support(self) -> bool:
        return self.type == "fixed"

    @property
    def is_interaction(self) -> bool:
        return self.type != "fixed"

    @property
    def holds_particles(self) -> bool:
        return self.type in PIN_TYPES

    @property
    def sized_by_fit(self) -> bool:
        """A support the extraction guessed (no still region was in view): the first fit sizes it
        (`fit.problem.support_layer`, `fit.optimize.select_supports`); measured, user and true sets
        stay as they are."""
        return self.type == "fixed" and self.source == "extracted" and self.guessed

    def point(self, x0: np.ndarray | None = None) -> np.ndarray:
        """Where it touches at rest: `contact_point`, else the mean of its particles, else the
        trajectory's first sample, else the origin."""
        if self.contact_point is not None:
            return self.contact_point
        if len(self.indices) and x0 is not None:
            return np.asarray(x0, np.float64)[self.indices].mean(0)
        if self.trajectory is not None and len(self.trajectory):
            return self.trajectory[0]
        return np.zeros(3)

    def active(self, frame: int) -> bool:
        """Whether the contact acts during frame `frame` (grasp <= frame < release)."""
        return self.grasp_frame <= frame and (self.release_frame is None or frame < self.release_frame)

    def replace(self, **changes) -> "ContactSet":
        return replace(self, **changes)


def supports(contacts) -> list:
    return [c for c in contacts if c.type == "fixed"]


def interactions(contacts) -> list:
    return [c for c in contacts if c.type != "fixed"]


def check_disjoint(contacts, where: str = "contacts") -> None:
    """Each particle follows at most one pointAdherent / fixed contact (ValueError naming both)."""
    held: dict[int, str] = {}
    for c in contacts:
        if c.type not in PIN_TYPES:
            continue
        for i in np.asarray(c.indices, np.int64).tolist():
            if i in held and held[i] != c.name:
                raise ValueError(f"{where}: '{held[i]}' and '{c.name}' hold the same particles (each particle "
                                 "follows one contact)")
            held[i] = c.name


def held_elsewhere(contacts, skip) -> np.ndarray:
    """The particle indices every contact but `skip` holds."""
    idx = [np.asarray(c.indices, np.int64) for c in contacts if c is not skip and len(c.indices)]
    return np.concatenate(idx) if idx else np.zeros(0, np.int64)


def moved_contact(c: ContactSet, off, x0: np.ndarray, contacts) -> ContactSet:
    """Contact `c` moved by `off` (3,) on the object: its held particles the nearest free ones to the
    old ones moved, its trajectory and contact point with them (a collider: its trajectory moved)."""
    from scipy.spatial import cKDTree

    off = np.asarray(off, float)
    tr = None if c.trajectory is None else np.asarray(c.trajectory) + off
    if c.type == "pointAdherent" and len(c.indices):
        free = np.setdiff1d(np.arange(len(x0)), held_elsewhere(contacts, c))
        _, nn = cKDTree(x0[free]).query(x0[np.asarray(c.indices)] + off)
        idx = np.unique(free[np.atleast_1d(nn)])
        return replace(c, indices=idx.astype(np.int64), trajectory=tr,
                       contact_point=None if c.contact_point is None else np.asarray(c.contact_point) + off)
    return replace(c, trajectory=tr)
