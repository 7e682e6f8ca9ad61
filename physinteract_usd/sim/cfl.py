"""Stable substep from the CFL bound: one fixed dt for a whole rollout and a whole fit.

Explicit MPM is stable while a P-wave crosses less than a fraction of a cell per substep:
dt <= cfl * dx / c_p with c_p = sqrt((lambda + 2 mu) / rho), taken at the largest E (plus the
Maxwell branch's modulus) and the largest nu the fit may reach, and while no particle moves more
than a fraction of a cell per substep (dt <= cfl_v * dx / v_max).

The adaptive substep (simulation.py) takes dt at a rung, not at the field's own largest E: the
smallest value of a ladder of ratio RUNG_RATIO below the E range's top that is >= the field's
largest E (`rung`), so a field may stiffen up to RUNG_RATIO before the model is rebuilt.
"""

from __future__ import annotations

import math

RUNG_RATIO = math.sqrt(2.0)     # the adaptive substep's ladder: dt ~ 1/sqrt(E), so ~19% more substeps a rung


def p_wave_speed(E: float, nu: float, density: float) -> float:
    """sqrt((lambda + 2 mu) / rho) [m/s]."""
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"Poisson ratio must lie in (-1, 0.5), got {nu}")
    return math.sqrt(E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu) * density))


def stable_dt(dx: float, E_max: float, nu_max: float, density: float, cfl: float = 0.4,
              max_speed: float = 0.0, cfl_speed: float = 0.25) -> float:
    """The largest stable substep [s] for stiffness up to E_max and particle speeds up to max_speed."""
    dt = cfl * dx / p_wave_speed(E_max, nu_max, density)
    if max_speed > 0.0:
        dt = min(dt, cfl_speed * dx / max_speed)
    return dt


def substeps_per_frame(fps: float, dx: float, E_max: float, nu_max: float, density: float,
                       cfl: float = 0.4, max_speed: float = 0.0) -> int:
    """Substeps per frame so that dt = 1 / (fps * substeps) <= stable_dt(...)."""
    dt = stable_dt(dx, E_max, nu_max, density, cfl=cfl, max_speed=max_speed)
    return max(1, math.ceil(1.0 / (fps * dt) - 1e-9))


def rung(e_max: float, top: float) -> float:
    """The adaptive substep's stiffness for a field whose largest E is `e_max`: the smallest value
    top / RUNG_RATIO**k (k >= 0) that is >= e_max (top itself for e_max >= top)."""
    k = max(0, int(math.floor(math.log(top / max(e_max, 1e-30)) / math.log(RUNG_RATIO) + 1e-9)))
    return top / RUNG_RATIO ** k
