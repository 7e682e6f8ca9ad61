"""Control: the interactions that drive a rollout (contacts with their trajectories).

Contact types (the contract's names):

- ``pointAdherent``: particles ``indices`` follow the contact's trajectory while grasped
  (grasp_frame <= k < release_frame), with the velocity (p[k+1] - p[k]) * fps constant inside frame
  k; they are free outside the window. On the grid, node velocities are blended towards the
  prescribed velocity by the share of the node's mass that grasped particles carry.
- ``fixed``: a support (clamp, hook, second hand): like pointAdherent with velocity zero.
- ``pointNonAdherent``: a sphere or capsule collider whose centre moves along the trajectory; it
  pushes (removes the approaching normal velocity, with optional Coulomb friction) but never pulls.
- ``surfaceNonAdherent``: a moving plane (point = trajectory, fixed unit ``normal``; the object is
  on the side the normal points to) with Coulomb friction.

Trajectories are positions per frame, shape (T+1, 3), frame 0 = rest; the rollout takes them as
differentiable inputs. Collider boundaries are smoothed over ``model.contact_band`` (see docs/sim.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import warp as wp

from .kernels import MAX_COLLIDERS, S_CAPSULE, S_PLANE, S_SPHERE, get_kernels

CONTACT_TYPES = ("pointAdherent", "pointNonAdherent", "surfaceNonAdherent", "fixed")
PIN_TYPES = ("pointAdherent", "fixed")
COLLIDER_TYPES = ("pointNonAdherent", "surfaceNonAdherent")


@dataclass
class Contact:
    type: str
    indices: np.ndarray | Sequence[int] | None = None   # particles (pointAdherent, fixed)
    trajectory: np.ndarray | None = None                # (T+1, 3) positions per frame
    grasp_frame: int = 0
    release_frame: int | None = None                    # None: held to the end
    shape: str = "sphere"                               # pointNonAdherent: sphere | capsule
    radius: float = 0.0                                 # sphere / capsule radius [m]
    axis: Sequence[float] = (0.0, 0.0, 0.0)             # capsule half-axis (centre to an end) [m]
    normal: Sequence[float] = (0.0, 1.0, 0.0)           # surfaceNonAdherent plane normal
    friction: float = 0.0                               # Coulomb mu of a collider

    def __post_init__(self):
        if self.type not in CONTACT_TYPES:
            raise ValueError(f"contact type must be one of {', '.join(CONTACT_TYPES)}, not {self.type!r}")
        if self.indices is not None:
            self.indices = np.asarray(self.indices, dtype=np.int64).reshape(-1)
        if self.trajectory is not None and not _is_torch(self.trajectory):
            self.trajectory = np.asarray(self.trajectory, dtype=np.float64)
        if self.type in PIN_TYPES and (self.indices is None or self.indices.size == 0):
            raise ValueError(f"a {self.type} contact needs particle indices")
        if self.type != "fixed" and self.trajectory is None:
            raise ValueError(f"a {self.type} contact needs a trajectory (T+1, 3)")
        if self.type == "pointNonAdherent":
            if self.shape not in ("sphere", "capsule"):
                raise ValueError("pointNonAdherent shape must be sphere or capsule")
            if not self.radius > 0:
                raise ValueError("pointNonAdherent collider needs a radius > 0")
            if self.shape == "capsule" and not np.linalg.norm(self.axis) > 0:
                raise ValueError("capsule collider needs a non-zero half-axis")
        if self.type == "surfaceNonAdherent" and not np.linalg.norm(self.normal) > 0:
            raise ValueError("surfaceNonAdherent needs a non-zero normal")
        if self.friction < 0:
            raise ValueError("friction must be >= 0")

    @property
    def is_pin(self) -> bool:
        return self.type in PIN_TYPES

    @property
    def is_collider(self) -> bool:
        return self.type in COLLIDER_TYPES

    def active_mask(self, n_frames: int) -> np.ndarray:
        r = n_frames if self.release_frame is None else int(self.release_frame)
        k = np.arange(n_frames)
        return ((k >= int(self.grasp_frame)) & (k < r)).astype(np.int32)


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


@dataclass
class Control:
    """The interactions of a rollout of ``n_frames`` frames."""

    contacts: list[Contact] = field(default_factory=list)
    n_frames: int = 1

    def __post_init__(self):
        self.contacts = list(self.contacts)
        if self.n_frames < 1:
            raise ValueError("n_frames must be >= 1")
        for i, c in enumerate(self.contacts):
            if c.trajectory is not None and tuple(c.trajectory.shape) != (self.n_frames + 1, 3):
                raise ValueError(f"contact {i} ({c.type}): trajectory must have shape "
                                 f"({self.n_frames + 1}, 3), got {tuple(c.trajectory.shape)}")
        if len(self.colliders) > MAX_COLLIDERS:
            raise ValueError(f"at most {MAX_COLLIDERS} non-adherent contacts are supported")

    @property
    def pins(self) -> list[int]:
        """Indices (into contacts) of the pointAdherent and fixed contacts, in order."""
        return [i for i, c in enumerate(self.contacts) if c.is_pin]

    @property
    def colliders(self) -> list[int]:
        return [i for i, c in enumerate(self.contacts) if c.is_collider]

    @property
    def trajectory_contacts(self) -> list[int]:
        """Contacts whose trajectory is a differentiable input (all but fixed)."""
        return [i for i, c in enumerate(self.contacts) if c.type != "fixed"]

    def pin_positions(self) -> np.ndarray:
        """(max(1, K_pin), T+1, 3) trajectories of the pins (fixed supports: zeros = at rest)."""
        T = self.n_frames
        out = np.zeros((max(1, len(self.pins)), T + 1, 3))
        for r, i in enumerate(self.pins):
            c = self.contacts[i]
            if c.type != "fixed":
                out[r] = _to_np(c.trajectory)
        return out

    def collider_positions(self) -> np.ndarray:
        T = self.n_frames
        out = np.zeros((max(1, len(self.colliders)), T + 1, 3))
        for r, i in enumerate(self.colliders):
            out[r] = _to_np(self.contacts[i].trajectory)
        return out

    def max_speed(self, fps: float) -> float:
        """The largest contact speed along the trajectories [m/s]."""
        s = 0.0
        for c in self.contacts:
            if c.trajectory is not None:
                tr = _to_np(c.trajectory)
                if len(tr) > 1:
                    s = max(s, float(np.linalg.norm(np.diff(tr, axis=0), axis=1).max() * fps))
        return s


def _to_np(t) -> np.ndarray:
    if _is_torch(t):
        return t.detach().cpu().double().numpy()
    return np.asarray(t, dtype=np.float64)


class ControlArrays:
    """A Control's device arrays for the kernels (built once per rollout; trajectories rewritten per call)."""

    def __init__(self, model, control: Control):
        K = get_kernels(model.dtype)
        d = model.device
        nd = model.np_dtype
        P = model.n_particles
        T = control.n_frames
        self.control = control
        self.n_frames = T
        pin_id = np.full(P, -1, dtype=np.int32)
        pins = control.pins
        for r, i in enumerate(pins):
            c = control.contacts[i]
            idx = c.indices
            if idx.min() < 0 or idx.max() >= P:
                raise ValueError(f"contact {i} ({c.type}): particle indices out of range [0, {P})")
            if np.any(pin_id[idx] >= 0):
                raise ValueError(f"contact {i} ({c.type}) shares particles with another adherent/fixed contact")
            pin_id[idx] = r
        pin_active = np.zeros((max(1, len(pins)), T), dtype=np.int32)
        pin_kind = np.zeros(max(1, len(pins)), dtype=np.int32)     # 1: a support (fixed), 0: a grasp
        for r, i in enumerate(pins):
            pin_active[r] = control.contacts[i].active_mask(T)
            pin_kind[r] = int(control.contacts[i].type == "fixed")
        cols = control.colliders
        n = max(1, len(cols))
        shape = np.zeros(n, np.int32)
        col_active = np.zeros((n, T), np.int32)
        geom = np.zeros((n, 3))
        radius = np.zeros(n)
        mu = np.zeros(n)
        for r, i in enumerate(cols):
            c = control.contacts[i]
            col_active[r] = c.active_mask(T)
            mu[r] = c.friction
            if c.type == "surfaceNonAdherent":
                shape[r] = S_PLANE
                geom[r] = np.asarray(c.normal, dtype=np.float64) / np.linalg.norm(c.normal)
            else:
                shape[r] = S_CAPSULE if c.shape == "capsule" else S_SPHERE
                geom[r] = np.asarray(c.axis, dtype=np.float64)
                radius[r] = c.radius
        self.n_pins = len(pins)
        self.n_col = len(cols)
        self.pin_id = wp.array(pin_id, dtype=wp.int32, device=d)
        self.pin_active = wp.array(pin_active, dtype=wp.int32, device=d)
        self.pin_pos = wp.array(control.pin_positions().astype(nd), dtype=K.vec3, device=d)
        self.pin_kind = wp.array(pin_kind, dtype=wp.int32, device=d)
        self.col_shape = wp.array(shape, dtype=wp.int32, device=d)
        self.col_active = wp.array(col_active, dtype=wp.int32, device=d)
        self.col_pos = wp.array(control.collider_positions().astype(nd), dtype=K.vec3, device=d)
        self.col_geom = wp.array(geom.astype(nd), dtype=K.vec3, device=d)
        self.col_radius = wp.array(radius.astype(nd), dtype=K.T, device=d)
        self.col_mu = wp.array(mu.astype(nd), dtype=K.T, device=d)
