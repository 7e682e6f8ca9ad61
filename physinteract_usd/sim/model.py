"""SimModel: the immutable description of a simulation (particles, material, grid, time, effects)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import warp as wp

from . import cfl as _cfl
from .effects import Effects, PARAMETERS, validate_values

MATERIALS = {"fixedCorotated": 0, "neoHookean": 1}
GROUND_CONTACTS = ("nodes", "penalty")   # SimModel.ground_contact


def _np_dtype(dtype: str):
    return np.float64 if dtype == "float64" else np.float32


@dataclass(frozen=True)
class GridSpec:
    """A regular background grid: node (i, j, k) sits at lower + (i, j, k) * dx."""

    lower: tuple[float, float, float]
    dx: float
    resolution: tuple[int, int, int]

    def __post_init__(self):
        object.__setattr__(self, "lower", tuple(float(v) for v in self.lower))
        object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))
        if not self.dx > 0:
            raise ValueError("grid dx must be > 0")
        if min(self.resolution) < 4:
            raise ValueError("grid resolution must be >= 4 nodes per axis")

    @property
    def upper(self) -> tuple[float, float, float]:
        return tuple(lo + (n - 1) * self.dx for lo, n in zip(self.lower, self.resolution))

    @property
    def valid_lower(self) -> np.ndarray:
        """Particles must stay in [valid_lower, valid_upper): the quadratic stencil fits on the grid."""
        return np.asarray(self.lower) + 0.5 * self.dx

    @property
    def valid_upper(self) -> np.ndarray:
        return np.asarray(self.lower) + (np.asarray(self.resolution) - 1.5) * self.dx

    @classmethod
    def around(cls, points: np.ndarray, dx: float, padding: float | Sequence[float] = 0.0,
               lower: Sequence[float] | None = None, upper: Sequence[float] | None = None) -> "GridSpec":
        """A grid covering ``points`` plus ``padding`` [m] (scalar or per axis), or an explicit box.

        Two cells more than the box on each side keep the stencil of a particle at the box's
        boundary on the grid.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pad = np.broadcast_to(np.asarray(padding, dtype=np.float64), (3,))
        lo = pts.min(0) - pad if lower is None else np.asarray(lower, dtype=np.float64)
        hi = pts.max(0) + pad if upper is None else np.asarray(upper, dtype=np.float64)
        lo = lo - 2.0 * dx
        res = np.ceil((hi + 2.0 * dx - lo) / dx).astype(int) + 1
        return cls(tuple(lo), float(dx), tuple(int(r) for r in res))


@dataclass(frozen=True, eq=False)
class SimModel:
    """Particles, material field, grid, time stepping, gravity and effects. Immutable.

    Build with `SimModel.create(...)`, which checks the inputs and picks the substep from the CFL
    bound at ``E_max`` (the largest E the fit may reach) unless ``substeps`` is given. The
    per-particle ``E`` / ``nu`` here are defaults: a rollout takes them as (differentiable) inputs.
    """

    x0: np.ndarray                      # (P, 3) rest positions [m]
    volume: np.ndarray                  # (P,) rest volumes [m^3]
    density: float                      # [kg/m^3]
    E: np.ndarray                       # (P,) default Young's modulus [Pa]
    nu: np.ndarray                      # (P,) default Poisson ratio
    material: str                       # "fixedCorotated" | "neoHookean"
    grid: GridSpec
    fps: float
    substeps: int                       # substeps per frame
    gravity: tuple[float, float, float]
    effects: Effects
    dtype: str                          # "float32" | "float64"
    device: str
    E_max: float                        # the CFL bound was taken here; larger E is refused
    nu_max: float
    contact_band: float                 # width [m] of the smoothed contact boundary (0 = hard)
    pin_gain: float                     # a node's pin blend: clamp(pin_gain * (share - pin_floor), 0, 1), share =
                                        # its pinned mass / its mass (pin_floor 0: >= 1/pin_gain pinned is fully pinned)
    blend_dt: float = 0.0               # partial pin / collider blends act at their weight once per this
                                        # time [s] (a rate, whatever the substep); 0: once per substep
    pin_floor: float = 0.0              # nodes with a pinned share below this are free (see pin_gain)
    support_gain: float | None = None   # the pin rule of the supports (fixed contacts): (support_gain, support_floor)
    support_floor: float | None = None  # where a node's pinned mass is a support's; None: the grasps' (pin_gain,
                                        # pin_floor). A node both reach mixes the two by its supports' share
    transfer_tau: float = 0.0           # the rate transfer's time constant [s] (docs/sim.md): free particles keep
                                        # exp(-dt / tau) of the velocity the grid could not carry each substep, so the
                                        # transfer's dissipation is a rate per second; 0: APIC (today's, bit for bit)
    stencil_check: bool = True          # a particle whose stencil was clamped at the grid's edge during a frame is an
                                        # error ("left the grid", even when the state then goes non-finite); False:
                                        # only the frame's end is checked, as before #24 (the synthetic truths keep
                                        # their retries, so captures generated before regenerate the same)
    ground_contact: str = "nodes"       # how the ground effect's plane acts (GROUND_CONTACTS): "nodes", a projection of
                                        # the grid nodes' velocity (today's; it brakes a rolling body: docs/sim.md), or
                                        # "penalty", an elastic push at each particle within its half spacing of the plane
                                        # with Coulomb friction at its contact point, scattered through the grid (a ball
                                        # rolls on: tests/test_rolling_ball.py)
    _dev: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def create(cls, positions, volumes, density: float = 1000.0, E=1.0e5, nu=0.3, *,
               material: str = "fixedCorotated", grid: GridSpec, fps: float, substeps: int | None = None,
               E_max: float | None = None, nu_max: float = 0.45, E_v_max: float | None = None,
               cfl: float = 0.4, max_speed: float = 0.0, gravity=(0.0, -9.81, 0.0),
               effects: Effects | dict | None = None, dtype: str = "float32", device: str = "cpu",
               contact_band: float | None = None, pin_gain: float = 4.0, blend_dt: float = 0.0,
               pin_floor: float = 0.0, transfer_tau: float | None = 0.0, stencil_check: bool = True,
               ground_contact: str = "nodes", support_rule: tuple[float, float] | None = None) -> "SimModel":
        x0 = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        P = x0.shape[0]
        if P == 0:
            raise ValueError("no particles")
        vol = np.broadcast_to(np.asarray(volumes, dtype=np.float64), (P,)).copy()
        Ea = np.broadcast_to(np.asarray(E, dtype=np.float64), (P,)).copy()
        nua = np.broadcast_to(np.asarray(nu, dtype=np.float64), (P,)).copy()
        if material not in MATERIALS:
            raise ValueError(f"material must be one of {', '.join(MATERIALS)}, not {material!r}")
        if dtype not in ("float32", "float64"):
            raise ValueError("dtype must be float32 or float64")
        if not np.all(vol > 0) or not density > 0:
            raise ValueError("volumes and density must be > 0")
        if not np.all(Ea > 0):
            raise ValueError("E must be > 0")
        if not (np.all(nua > -1.0) and np.all(nua < 0.5)):
            raise ValueError("nu must lie in (-1, 0.5)")
        if not isinstance(effects, Effects):
            effects = Effects(effects or {})
        for eff, vals in effects.params.items():
            for p, v in vals.items():
                validate_values(eff, p, v)
        if ground_contact not in GROUND_CONTACTS:
            raise ValueError(f"ground_contact must be one of {', '.join(GROUND_CONTACTS)}, not {ground_contact!r}")
        tau_t = float(transfer_tau or 0.0)
        if not (np.isfinite(tau_t) and tau_t >= 0.0):
            raise ValueError(f"transfer_tau must be >= 0 s (0: APIC), not {transfer_tau!r}")
        E_max = float(Ea.max() if E_max is None else E_max)
        if Ea.max() > E_max * (1 + 1e-6):
            raise ValueError(f"default E up to {Ea.max():g} Pa exceeds E_max = {E_max:g} Pa")
        nu_max = max(float(nu_max), float(nua.max()))
        stiff = E_max
        if "viscoelasticity" in effects:
            ev = effects.params["viscoelasticity"]["modulus"]
            stiff += max(ev, E_max if E_v_max is None else float(E_v_max))
        if substeps is None:
            substeps = _cfl.substeps_per_frame(fps, grid.dx, stiff, nu_max, density, cfl=cfl, max_speed=max_speed)
        band = grid.dx if contact_band is None else float(contact_band)
        sg, sf = (None, None) if support_rule is None else (float(support_rule[0]), float(support_rule[1]))
        for name, (g_, f_) in (("pin rule", (pin_gain, pin_floor)), ("support rule", (sg, sf))):
            if g_ is not None and not (float(g_) > 0 and 0 <= float(f_) < 1):
                raise ValueError(f"{name}: the gain must be > 0 and the floor in [0, 1), not ({g_}, {f_})")
        m = cls(x0=x0, volume=vol, density=float(density), E=Ea, nu=nua, material=material, grid=grid,
                fps=float(fps), substeps=int(substeps), gravity=tuple(float(g) for g in gravity),
                effects=effects, dtype=dtype, device=str(wp.get_device(device)), E_max=E_max, nu_max=nu_max,
                contact_band=band, pin_gain=float(pin_gain), blend_dt=float(blend_dt),
                pin_floor=float(pin_floor), transfer_tau=tau_t, stencil_check=bool(stencil_check),
                ground_contact=ground_contact, support_gain=sg, support_floor=sf)
        lo, hi = grid.valid_lower, grid.valid_upper
        if np.any(x0 < lo) or np.any(x0 >= hi):
            raise ValueError(f"particles at rest lie outside the grid's valid box [{lo}, {hi}); "
                             "enlarge the grid (GridSpec.around with padding)")
        return m

    # ------------------------------------------------------------------ derived values
    @property
    def n_particles(self) -> int:
        return self.x0.shape[0]

    @property
    def mass(self) -> np.ndarray:
        return self.volume * self.density

    @property
    def support_rule(self) -> tuple[float, float]:
        """(gain, floor) of the supports' pin rule (the grasps' where none was set)."""
        if self.support_gain is None:
            return self.pin_gain, self.pin_floor
        return self.support_gain, self.support_floor

    @property
    def dt(self) -> float:
        return 1.0 / (self.fps * self.substeps)

    @property
    def np_dtype(self):
        return _np_dtype(self.dtype)

    @property
    def material_id(self) -> int:
        return MATERIALS[self.material]

    def stable_dt(self, cfl: float = 0.4) -> float:
        return _cfl.stable_dt(self.grid.dx, self.E_max, self.nu_max, self.density, cfl=cfl)

    def replace(self, **changes) -> "SimModel":
        """A copy with some fields changed (e.g. ``effects=``); device arrays are rebuilt."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "_dev"}
        d.update(changes)
        if "effects" in changes and not isinstance(d["effects"], Effects):
            d["effects"] = Effects(d["effects"])
        return SimModel(**d)

    def effect_vector(self) -> list[float]:
        return self.effects.vector()

    # ------------------------------------------------------------------ device arrays (cached)
    def device_arrays(self) -> dict:
        """x0, mass, volume, default E / nu on the model's device, in the model's dtype."""
        if not self._dev:
            from .kernels import get_kernels
            K = get_kernels(self.dtype)
            nd = self.np_dtype
            d = self.device
            self._dev.update(
                x0=wp.array(self.x0.astype(nd), dtype=K.vec3, device=d),
                mass=wp.array(self.mass.astype(nd), dtype=K.T, device=d),
                volume=wp.array(self.volume.astype(nd), dtype=K.T, device=d),
                E=wp.array(self.E.astype(nd), dtype=K.T, device=d),
                nu=wp.array(self.nu.astype(nd), dtype=K.T, device=d),
            )
        return self._dev


def effect_parameter_names() -> list[tuple[str, str]]:
    """All (effect, parameter) pairs, in the schema's naming."""
    return [(e, p) for e, ps in PARAMETERS.items() for p in ps]
