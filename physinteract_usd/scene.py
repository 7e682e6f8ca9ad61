"""The scene as plain Python objects: what a stage says, free of USD (the core modules use these).

`physinteract_usd.usd.stage` reads and writes them; the simulator, renderer and fit consume them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .gaussians import Gaussians


@dataclass
class SimSettings:
    """Simulation domain and discretisation, chosen at init and stored on PhysInteractScene."""

    domain_min: np.ndarray
    domain_max: np.ndarray
    grid_resolution: tuple
    cell_size: float
    particle_spacing: float
    substeps: int
    youngs_min: float = 1e3
    youngs_max: float = 1e6
    poisson_default: float = 0.3
    poisson_max: float = 0.45
    density: float = 1000.0
    gravity: tuple = (0.0, -9.81, 0.0)
    constitutive_model: str = "fixedCorotated"
    transfer_tau: float = 0.0         # the rate transfer's time constant [s] (SimModel.transfer_tau); 0: APIC
    # the scan carries its weight (sim.preload): frame 0 prestressed on its supports. None: not said (init without
    # --preload / --no-preload): simulations take the scan stress-free until a fit decides (fit/preload_choice.py)
    preload: bool | None = False

    def to_dict(self) -> dict:
        return {"domain_min": list(map(float, self.domain_min)), "domain_max": list(map(float, self.domain_max)),
                "grid_resolution": list(map(int, self.grid_resolution)), "cell_size": self.cell_size,
                "particle_spacing": self.particle_spacing, "substeps": self.substeps,
                "youngs_min": self.youngs_min, "youngs_max": self.youngs_max,
                "poisson_default": self.poisson_default, "poisson_max": self.poisson_max,
                "density": self.density,
                "gravity": list(self.gravity), "constitutive_model": self.constitutive_model,
                "transfer_tau": self.transfer_tau,
                "preload": None if self.preload is None else bool(self.preload)}


@dataclass
class Trajectory:
    name: str
    contact_set: str              # name of the contact set it moves
    frames: np.ndarray            # (T,) frame indices
    positions: np.ndarray         # (T, 3)
    velocities: np.ndarray | None = None
    stage: str = "initial"


@dataclass
class SceneData:
    """Everything a stage says, as plain Python objects (what the core modules consume)."""

    path: Path
    fps: float
    start_frame: int
    end_frame: int
    image_size: tuple
    camera: Camera
    gaussians: Gaussians
    particles_positions: np.ndarray
    particles_volumes: np.ndarray
    particles_surface: np.ndarray
    youngs_modulus: np.ndarray
    poisson_ratio: np.ndarray
    confidence: np.ndarray | None
    settings: SimSettings
    frame_assets: list
    video_asset: str | None
    mask_assets: list
    masks_amodal: bool
    hand_mask_assets: list
    effects: dict
    contacts: list                # contacts.ContactSet, each with its initial trajectory (T0) if any
    trajectories: list            # Trajectory: every trajectory prim (initial and fitted)
    reports: list                 # one dict per fit version, oldest first (usd.reports.read_report's keys,
                                  # plus "current": bool and "snapshot": its v<N>.usdc or None)
    generator: str
    object_kind: str
    current_version: int | None = None   # the fit version the stage shows (None: not fitted)

    @property
    def current_report(self) -> dict | None:
        return next((r for r in self.reports if r.get("current")), None)

    @property
    def n_frames(self) -> int:
        return self.end_frame - self.start_frame + 1
