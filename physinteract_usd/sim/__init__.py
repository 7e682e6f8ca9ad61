"""Differentiable MLS-MPM simulator (NVIDIA Warp) with a torch.autograd front end.

Public API:

- `SimModel.create(...)`, `GridSpec` (model.py): particles, material field, grid, time, effects.
- `Effects` and the effect tables (effects.py): damping, plasticity, ground, viscoelasticity.
- `Contact`, `Control` (control.py): pointAdherent, pointNonAdherent, surfaceNonAdherent, fixed.
- `SimState` (state.py), `MPMSolver` (solver.py): Warp-level stepping.
- `Rollout`, `simulate` (rollout.py): the differentiable torch entry points.
- `stable_dt`, `substeps_per_frame` (cfl.py).

USD is kept out of this package: it never imports pxr.
"""

from typing import TYPE_CHECKING

from .cfl import p_wave_speed, stable_dt, substeps_per_frame
from .control import CONTACT_TYPES, Contact, Control
from .effects import DEFAULTS, EFFECT_NAMES, NULL_VALUES, PARAMETERS, Effects
from .model import MATERIALS, GridSpec, SimModel
from .solver import MPMSolver, SimParams
from .state import SimState

if TYPE_CHECKING:
    from .rollout import Rollout, effect_inputs, simulate


def __getattr__(name):
    """The torch entry points (rollout.py imports torch) load on first use, so importing the
    simulator's tables (effects, cfl: `effects list`, `init`) does not import torch."""
    if name in ("Rollout", "effect_inputs", "simulate"):
        from . import rollout

        return getattr(rollout, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "SimModel", "GridSpec", "MATERIALS", "Effects", "EFFECT_NAMES", "PARAMETERS", "DEFAULTS", "NULL_VALUES",
    "Contact", "Control", "CONTACT_TYPES", "SimState", "MPMSolver", "SimParams", "Rollout", "simulate",
    "effect_inputs", "stable_dt", "substeps_per_frame", "p_wave_speed",
]
