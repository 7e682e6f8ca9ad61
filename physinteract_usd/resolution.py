"""How stiff our MLS-MPM is against the continuum, by cells across a thin round part (numpy only; #24).

Measured by `benchmarks/mpm_stiffness.py` (docs/benchmarks/fit.md, "Apparent stiffness vs cells
across"): a free-free round rod filled as `fill.py` fills an object (lattice spacing dx / 2 aligned
with the grid), started in one mode, its frequency against the continuum's; E_apparent / E =
(f_MPM / f_continuum)^2, the mean over three orientations to the grid (along an axis, 45 degrees in
a plane, along the cube diagonal: they differ by <= 0.09 at 3 cells and <= 0.04 from 4 on), float32,
nu 0.3 (nu 0.4 gives the same within 0.003 at 4 and 6 cells). Stretching is exact at any resolution
(within 4% from 2 cells); a **twist swings slow** (0.79 at 4 cells across, 0.93 at 8) **because it is
heavy, not soft**: the APIC affine momentum gives every particle the inertia of a blob of variance
dx^2 / 4 per axis, which adds dx^2 / 2 to the rod's polar radius of gyration^2 (r^2 / 2): the
frequency's E_app is r^2 / (r^2 + dx^2) within 0.03, while the strain energy at a given twist is the
continuum's within 5% from 4 cells ("torsion_static"); bending is 0.95 +- 0.05 at 4 cells.

`continuum_youngs` maps a fitted E to the continuum's under one curve: opt-in, a post-processing of a
fit's E (nothing in the fit calls it); which curve applies is the caller's choice, and the twist's
dynamic curve only where the motion's inertia is the wire's own spin (a free rod's twist), which a
recorded motion's `apic_extra_inertia` measures: the synthetic telephone cable's poke moves over
~40 mm, and its APIC inertia at grid auto is 0.7% of its kinetic energy (docs/benchmarks/fit.md).
"""

from __future__ import annotations

import numpy as np

# cells across the diameter -> E_apparent / E (benchmarks/mpm_stiffness.py, mean over x / xy45 / xyz,
# the rows of docs/benchmarks/fit.md)
CELLS = np.array([2.0, 3.0, 4.0, 6.0, 8.0])
CURVES = {
    # the twist's frequency: slow by the APIC rotary inertia, r^2 / (r^2 + dx^2) = n^2 / (n^2 + 4) within 0.03
    # (the stiffness is nearly right: "torsion_static"); applies to motion borne by the twist's inertia only
    "torsion": np.array([0.470, 0.688, 0.786, 0.890, 0.929]),
    # the twist's strain energy at a given twist against the continuum's G J (the lattice's own J included)
    "torsion_static": np.array([0.838, 0.921, 0.952, 0.980, 0.987]),
    # the bending frequency against a free-free Timoshenko beam (L / D = 6); +-0.05 by orientation and by
    # where the rod's axis falls in a cell (0.997-1.026 at 4 cells with the axis on a lattice plane)
    "bending": np.array([0.822, 0.911, 0.950, 0.981, 0.988]),
    "axial": np.array([1.0, 1.0, 1.0, 1.0, 1.0]),      # measured 0.96-1.03 from 2 cells
}
# beyond the table: 1 - (1 - k_8) (8 / n)^TAIL_POWER (torsion 4 -> 6 -> 8 cells fall as n^-1.5)
TAIL_POWER = 1.5


def apparent_stiffness(cells, mode: str = "torsion") -> np.ndarray:
    """E_apparent / E of a round part `cells` grid cells across, deformed in `mode` (torsion,
    bending, axial). Between the table's points: linear in log(cells); below 2 cells: the 2-cell
    value (a part that thin is not resolved at all: say so rather than trust a factor); above 8: a
    power-law tail toward 1."""
    if mode not in CURVES:
        raise ValueError(f"mode must be one of {', '.join(CURVES)}, not {mode!r}")
    n = np.asarray(cells, dtype=np.float64)
    if np.any(~np.isfinite(n)) or np.any(n <= 0):
        raise ValueError("cells across must be finite and > 0")
    k = CURVES[mode]
    inside = np.interp(np.log(np.clip(n, CELLS[0], CELLS[-1])), np.log(CELLS), k)
    tail = 1.0 - (1.0 - k[-1]) * (CELLS[-1] / np.maximum(n, CELLS[-1])) ** TAIL_POWER
    return np.where(n > CELLS[-1], tail, inside)


def relative_stiffness(cells_fit, cells_truth, mode: str = "torsion") -> np.ndarray:
    """E_app(fit's resolution) / E_app(the truth's): a fit at `cells_fit` matching motion simulated at
    `cells_truth` finds E_truth / this (in a part deforming in `mode`)."""
    return apparent_stiffness(cells_fit, mode) / apparent_stiffness(cells_truth, mode)


def continuum_youngs(E, cells, mode: str = "torsion") -> np.ndarray:
    """The continuum E a fitted E at `cells` across stands for: E x E_app(cells) (per particle when
    E and cells are arrays)."""
    return np.asarray(E, dtype=np.float64) * apparent_stiffness(cells, mode)


def apic_extra_inertia(rest: np.ndarray, positions: np.ndarray, fps: float, dx, mass=None, k: int = 12,
                       subset=None) -> np.ndarray:
    """The APIC affine momentum's extra kinetic energy over the particles' own, for a recorded motion
    at grid cells `dx` (a scalar or an array of them): kappa = (dx^2 / 4) sum m |grad v|^2 / sum m |v|^2.

    Every APIC / MLS-MPM particle carries the inertia of a blob of variance dx^2 / 4 per axis (the
    quadratic B-spline's D), so a motion whose velocity varies over a length l moves as if ~(dx / l)^2
    heavier: a free rod's twist is slow by r^2 / (r^2 + dx^2) (benchmarks/mpm_stiffness.py). A fit at
    dx matching motion made at dx_truth needs E x (1 + kappa(dx)) / (1 + kappa(dx_truth)) where the
    motion is inertia-borne (a swing); where it is quasi-static (a sag, a slow pull) E is not biased by it.

    rest (P, 3), positions (T, P, 3) at `fps`; grad v per particle by least squares over its k
    nearest rest neighbours (velocities by central differences of the frames); mass (P,) or equal;
    `subset`: the particles summed over (indices; default all), their neighbours from all."""
    from scipy.spatial import cKDTree

    rest = np.asarray(rest, np.float64)
    x = np.asarray(positions, np.float64)
    if x.ndim != 3 or x.shape[1:] != rest.shape or len(x) < 3:
        raise ValueError("positions must be (T >= 3, P, 3) with P = len(rest)")
    P = len(rest)
    m = np.ones(P) if mass is None else np.broadcast_to(np.asarray(mass, np.float64), (P,))
    sub = np.arange(P) if subset is None else np.asarray(subset)
    _, nb = cKDTree(rest).query(rest[sub], k=min(k + 1, P))
    m = m[sub]
    dX = rest[nb[:, 1:]] - rest[sub][:, None]                              # (S, k, 3)
    A = np.einsum("pki,pkj->pij", dX, dX)
    Ainv = np.linalg.pinv(A)
    v = 0.5 * fps * (x[2:] - x[:-2])                                       # (T-2, P, 3)
    dv = v[:, nb[:, 1:]] - v[:, sub][:, :, None]                           # (T-2, S, k, 3)
    G = np.einsum("tpki,pkj,pjl->tpil", dv, dX, Ainv)                      # d v / d X
    g2 = (m[None] * (G ** 2).sum((2, 3))).sum()
    v2 = (m[None] * (v[:, sub] ** 2).sum(2)).sum()
    return np.asarray(dx, np.float64) ** 2 / 4 * g2 / max(v2, 1e-300)
