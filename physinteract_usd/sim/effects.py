"""The optional physical effects: names, parameters, null values and the flat parameter vector.

Names and parameter names follow the USD schema (`PhysInteractDampingAPI` ...
`physinteract:damping:coefficient` ...). Each effect is switched on by being present in an
`Effects`; when on, its parameters are differentiable inputs of the rollout. At its null value an
effect vanishes exactly (the rollout is then bitwise the rollout without it, up to the extra work):

=================  ==========================  =======================  =======================
effect             parameters [unit]           null                     equation (see docs/sim.md)
=================  ==========================  =======================  =======================
damping            coefficient c [1/s]         c = 0                    grid v <- v exp(-c dt)
plasticity         yieldStress tau_Y [Pa]      tau_Y = inf              von Mises on Hencky strain
ground             height h [m], friction mu   off (no plane)           plane y = h, Coulomb mu
viscoelasticity    modulus E_v [Pa],           E_v = 0                  Maxwell branch (SLS),
                   relaxationTime tau [s]                               dev. Hencky, relaxes e^-dt/tau
=================  ==========================  =======================  =======================

Short aliases are accepted wherever a parameter is named: c, tau_Y, h, mu, E_v, tau.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

from . import kernels as _k

EFFECT_NAMES = ("damping", "plasticity", "ground", "viscoelasticity")

PARAMETERS: dict[str, tuple[str, ...]] = {
    "damping": ("coefficient",),
    "plasticity": ("yieldStress",),
    "ground": ("height", "friction"),
    "viscoelasticity": ("modulus", "relaxationTime"),
}

DEFAULTS: dict[str, dict[str, float]] = {
    "damping": {"coefficient": 0.0},
    "plasticity": {"yieldStress": math.inf},
    "ground": {"height": 0.0, "friction": 0.5},
    "viscoelasticity": {"modulus": 0.0, "relaxationTime": 0.1},
}

# the value of each effect at which it vanishes (ground has none: it vanishes by being off)
NULL_VALUES: dict[str, dict[str, float] | None] = {
    "damping": {"coefficient": 0.0},
    "plasticity": {"yieldStress": math.inf},
    "ground": None,
    "viscoelasticity": {"modulus": 0.0},
}

ALIASES = {"c": "coefficient", "tau_Y": "yieldStress", "tauY": "yieldStress", "h": "height",
           "mu": "friction", "E_v": "modulus", "Ev": "modulus", "tau": "relaxationTime"}

# slot of each parameter in the flat vector the kernels read
SLOTS: dict[tuple[str, str], int] = {
    ("damping", "coefficient"): _k.I_DAMP_C,
    ("plasticity", "yieldStress"): _k.I_YIELD,
    ("ground", "height"): _k.I_GROUND_H,
    ("ground", "friction"): _k.I_GROUND_MU,
    ("viscoelasticity", "modulus"): _k.I_VISCO_E,
    ("viscoelasticity", "relaxationTime"): _k.I_VISCO_TAU,
}
N_PARAMS = _k.N_EFFECT_PARAMS

FLAGS = {"damping": _k.F_DAMPING, "plasticity": _k.F_PLASTICITY, "ground": _k.F_GROUND,
         "viscoelasticity": _k.F_VISCO}


def canonical(effect: str, param: str) -> str:
    """The schema name of ``param`` of ``effect`` (accepts the short aliases)."""
    if effect not in PARAMETERS:
        raise KeyError(f"unknown effect {effect!r}; known: {', '.join(EFFECT_NAMES)}")
    name = ALIASES.get(param, param)
    if name not in PARAMETERS[effect]:
        raise KeyError(f"effect {effect!r} has no parameter {param!r}; it has {', '.join(PARAMETERS[effect])}")
    return name


@dataclass(frozen=True)
class Effects:
    """The enabled effects and their default parameter values.

    ``Effects({"damping": {"coefficient": 2.0}, "ground": {}})`` enables damping (c = 2/s) and the
    ground with its defaults (h = 0, mu = 0.5). Missing parameters take `DEFAULTS`.
    """

    params: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    def __post_init__(self):
        full: dict[str, dict[str, float]] = {}
        for eff, ps in dict(self.params).items():
            if eff not in PARAMETERS:
                raise KeyError(f"unknown effect {eff!r}; known: {', '.join(EFFECT_NAMES)}")
            vals = dict(DEFAULTS[eff])
            for k, v in dict(ps or {}).items():
                vals[canonical(eff, k)] = float(v)
            full[eff] = vals
        object.__setattr__(self, "params", full)

    @property
    def enabled(self) -> tuple[str, ...]:
        return tuple(e for e in EFFECT_NAMES if e in self.params)

    def __contains__(self, effect: str) -> bool:
        return effect in self.params

    @property
    def flags(self) -> int:
        f = 0
        for e in self.params:
            f |= FLAGS[e]
        return f

    def with_effect(self, effect: str, **params: float) -> "Effects":
        d = {k: dict(v) for k, v in self.params.items()}
        d[effect] = {**d.get(effect, {}), **params}
        return Effects(d)

    def without(self, effect: str) -> "Effects":
        return Effects({k: v for k, v in self.params.items() if k != effect})

    def vector(self) -> list[float]:
        """The flat parameter vector (defaults for the effects that are off; the kernels ignore them)."""
        vec = [0.0] * N_PARAMS
        for eff in EFFECT_NAMES:
            vals = self.params.get(eff, DEFAULTS[eff])
            for p in PARAMETERS[eff]:
                vec[SLOTS[(eff, p)]] = vals[p]
        return vec


def validate_values(effect: str, param: str, value: float) -> None:
    """Raise ValueError for values outside an effect's domain (plain floats; used on defaults)."""
    if param == "coefficient" and value < 0:
        raise ValueError("damping coefficient must be >= 0")
    if param == "yieldStress" and not value > 0:
        raise ValueError("plasticity yieldStress must be > 0 (inf = off)")
    if param == "friction" and value < 0:
        raise ValueError("ground friction must be >= 0")
    if param == "modulus" and value < 0:
        raise ValueError("viscoelasticity modulus must be >= 0")
    if param == "relaxationTime" and not value > 0:
        raise ValueError("viscoelasticity relaxationTime must be > 0")
