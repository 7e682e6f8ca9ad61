"""The apparent stiffness of our MLS-MPM against cells across a round rod (#24, the discretisation
hypothesis): a free-free rod (no clamp, no gravity, no contact: nothing but the material and its
discretisation) is started in one of its first modes (axial, torsion, bending) by its mode's velocity
field, and its frequency read from the modal coordinate; E_apparent / E = (f_MPM / f_continuum)^2,
f_continuum the round rod's (axial: Rayleigh-Love; torsion: Saint-Venant, exact for a circle;
bending: a free-free Timoshenko beam, shear and rotary inertia, by `timoshenko_free_free`). The rod
is filled the way `fill.py` fills an object: lattice cells of spacing dx / 2 aligned with the grid,
their centres inside the rod, each particle a cell's volume (so the lattice's own area / second
moment is part of what is measured, as it is in a fit). A sag or a swing depends on E only through
these frequencies (sag ~ g / omega^2), so E_apparent is the E a fit would need to move like the
continuum at the true E, inverted: a fit at this resolution finds E_true / (E_apparent / E).

    python benchmarks/mpm_stiffness.py --cells 2,3,4,6,8 --orient x,xy45,xyz --modes axial,torsion,bending

Orientations: x (the rod along a grid axis), xy45 (in the xy plane at 45 degrees), xyz (along the
cube diagonal). Bending is across the rod in the direction closest to z (out of the xy plane).
Prints one JSON row per case and a table; --out FILE writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

ORIENT = {"x": (1.0, 0.0, 0.0), "xy45": (1.0, 1.0, 0.0), "xyz": (1.0, 1.0, 1.0), "xy30": (math.cos(math.pi / 6),
          math.sin(math.pi / 6), 0.0)}
BETA_FF, SIGMA_FF = 4.730040745, 0.982502215   # the free-free Euler-Bernoulli beam's first mode


def timoshenko_free_free(L: float, r: float, nu: float, n: int = 200) -> float:
    """First bending frequency of a free-free round Timoshenko beam (radius r, length L, E = rho = 1,
    shear coefficient 6 (1 + nu) / (7 + 6 nu), rotary inertia) over Euler-Bernoulli's
    beta^2 / (2 pi L^2) sqrt(E I / (rho A)): two-node elements, linear w and theta, shear at the
    element's midpoint (tests/test_known_answers.timoshenko_cantilever's element, free ends)."""
    import scipy.linalg

    E, rho = 1.0, 1.0
    kappa = 6 * (1 + nu) / (7 + 6 * nu)
    G, A, I, le = E / (2 * (1 + nu)), math.pi * r * r, math.pi * r ** 4 / 4, L / n
    N = 2 * (n + 1)
    K, M = np.zeros((N, N)), np.zeros((N, N))
    B = np.array([-1 / le, -0.5, 1 / le, -0.5])
    kb = E * I / le * np.array([[0, 0, 0, 0], [0, 1, 0, -1], [0, 0, 0, 0], [0, -1, 0, 1]])
    m = 0.5 * le * rho * np.diag([A, I, A, I])
    for e in range(n):
        d = np.arange(2 * e, 2 * e + 4)
        K[np.ix_(d, d)] += kb + kappa * G * A * le * np.outer(B, B)
        M[np.ix_(d, d)] += m
    lam = scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=[2, 2])[0]   # after the two rigid modes
    return math.sqrt(lam) / (BETA_FF ** 2 * math.sqrt(E * I / (rho * A)) / L ** 2)


def reference_frequency(mode: str, L: float, r: float, E: float, nu: float, rho: float) -> float:
    """The continuum round rod's first free-free frequency [Hz] of this mode."""
    c = math.sqrt(E / rho)
    if mode == "axial":     # Rayleigh-Love: lateral inertia, k = pi / L, polar radius of gyration^2 = r^2 / 2
        return c / (2 * L) / math.sqrt(1 + (nu * math.pi / L) ** 2 * r * r / 2)
    if mode == "torsion":
        return math.sqrt(E / (2 * (1 + nu)) / rho) / (2 * L)
    if mode == "bending":
        eb = BETA_FF ** 2 / (2 * math.pi * L * L) * c * r / 2       # sqrt(I / A) = r / 2
        return eb * timoshenko_free_free(L, r, nu)
    raise ValueError(mode)


def _frame(axis):
    a = np.asarray(axis, float)
    a /= np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    b = z - (z @ a) * a                       # across the rod, closest to z
    if np.linalg.norm(b) < 1e-9:
        b = np.array([0.0, 1.0, 0.0]) - a[1] * a
    b /= np.linalg.norm(b)
    return a, b, np.cross(a, b)


def rod_particles(cells: float, slender: float, axis, dx: float, phase=(0.31, 0.17, 0.43)):
    """Lattice cell centres (spacing dx / 2, aligned with a grid whose nodes are at multiples of dx)
    inside a round rod of diameter cells * dx and length slender * diameter, centred at the origin
    plus `phase` (in lattice spacings: where the rod's centre falls inside a cell)."""
    s = 0.5 * dx
    D = cells * dx
    L = slender * D
    r = 0.5 * D
    a, _, _ = _frame(axis)
    c = np.asarray(phase) * s
    ext = 0.5 * L * np.abs(a) + r + 2 * s
    lo = np.floor((c - ext) / s)
    hi = np.ceil((c + ext) / s)
    axes = [(np.arange(lo[d], hi[d]) + 0.5) * s for d in range(3)]
    p = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    q = p - c
    t = q @ a
    rad = np.linalg.norm(q - np.outer(t, a), axis=1)
    keep = (np.abs(t) <= 0.5 * L) & (rad <= r)
    return p[keep], c, L, r, s


def mode_velocity(mode: str, q: np.ndarray, a, b, L: float):
    """The mode's velocity field at rest positions q (relative to the rod's centre), unit amplitude,
    and the weights w(p) (a vector field) the modal coordinate is read with (sum m w . u / sum m w . w)."""
    t = q @ a
    if mode == "axial":
        w = np.outer(np.sin(math.pi * t / L), a)            # free-free: u ~ cos(pi s / L), s = t + L / 2
        return w, w
    if mode == "torsion":
        w = np.sin(math.pi * t / L)[:, None] * np.cross(a, q)
        return w, w
    if mode == "bending":
        xi = BETA_FF * (t / L + 0.5)
        phi = np.cosh(xi) + np.cos(xi) - SIGMA_FF * (np.sinh(xi) + np.sin(xi))
        dphi = BETA_FF / L * (np.sinh(xi) - np.sin(xi) - SIGMA_FF * (np.cosh(xi) + np.cos(xi)))
        w = np.outer(phi, b) - ((q @ b) * dphi)[:, None] * a[None, :]     # plane sections rotate
        return w, np.outer(phi, b)
    raise ValueError(mode)


def run_case(mode: str, orient: str, cells: float, slender: float = 6.0, nu: float = 0.3, E: float = 1e4,
             rho: float = 200.0, frames_per_period: int = 24, periods: float = 1.3, strain: float = 1e-3,
             dtype: str = "float32", device: str = "cpu", phase=(0.31, 0.17, 0.43), dx: float = 0.01) -> dict:
    from physinteract_usd.sim import Control, GridSpec, MPMSolver, SimModel, SimState

    a, b, _ = _frame(ORIENT[orient])
    pts, c, L, r, s = rod_particles(cells, slender, ORIENT[orient], dx, phase)
    q = pts - c
    f_ref = reference_frequency(mode, L, r, E, nu, rho)
    w_vel, w_read = mode_velocity(mode, q, a, b, L)
    # amplitude: peak strain ~ `strain` (axial pi u / L; torsion r theta' ; bending r phi'')
    omega = 2 * math.pi * f_ref
    if mode == "axial":
        u_amp = strain * L / math.pi
    elif mode == "torsion":
        u_amp = strain * L / (math.pi * r)          # the twist angle's amplitude (w scales with the radius)
    else:
        u_amp = strain * L * L / (r * BETA_FF ** 2 * 2)
    v0 = omega * u_amp * w_vel
    v0 -= v0.mean(0)                                # no drift of the whole rod
    fps = frames_per_period * f_ref
    T = int(math.ceil(periods * frames_per_period))
    pad = 3 * dx + 2 * u_amp * (r if mode == "torsion" else 1.0)
    lo = np.floor((pts.min(0) - pad) / dx) * dx     # nodes at multiples of dx: the lattice is aligned with them
    hi = pts.max(0) + pad
    grid = GridSpec(tuple(lo), dx, tuple(int(v) for v in np.ceil((hi - lo) / dx) + 1))
    m = SimModel.create(pts, s ** 3, rho, E, nu, grid=grid, fps=fps, E_max=E, gravity=(0.0, 0.0, 0.0),
                        dtype=dtype, device=device)
    st = SimState.rest(m, v0)
    c0 = time.process_time()
    out = MPMSolver(m, Control([], n_frames=T)).simulate(T, st)
    cpu = time.process_time() - c0
    x = out["x"]
    u = x - x[0][None]
    u -= u.mean(1, keepdims=True)
    mass = np.full(len(pts), 1.0)
    qt = np.einsum("p,tpk,pk->t", mass, u, w_read) / np.einsum("p,pk,pk->", mass, w_read, w_read)
    t = np.arange(T + 1) / fps
    f_mpm, fit = _frequency(t, qt, f_ref)
    n_true = math.pi * r * r * L / s ** 3
    # the stiffness alone: the particles' strain energy at the frame of the largest modal amplitude
    # against the continuum's at that amplitude (no inertia in it)
    k = int(np.argmax(np.abs(qt)))
    pe = float((m.volume * _psi(out["F"][k], E, nu)).sum())
    e_static = pe / (continuum_energy(mode, L, r, E, nu) * qt[k] ** 2)
    # the APIC affine momentum's rotary inertia: each particle a blob of variance dx^2 / 4 per axis, so a
    # twist's polar radius of gyration^2 r^2 / 2 grows by dx^2 / 2: f^2 x r^2 / (r^2 + dx^2) (stiffness exact)
    apic = r * r / (r * r + dx * dx) if mode == "torsion" else None
    return dict(mode=mode, orient=orient, cells=cells, slender=slender, nu=nu, particles=len(pts),
                volume_ratio=len(pts) / n_true, substeps=m.substeps, f_ref=f_ref, f_mpm=f_mpm, f_ratio=f_mpm / f_ref,
                E_app=(f_mpm / f_ref) ** 2, E_static=e_static, apic_inertia_pred=apic, decay_per_period=fit["decay"], fit_rms=fit["rms"], cpu_s=cpu)


def _psi(F, E, nu):
    """Fixed-corotated energy density per particle."""
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    sv = np.linalg.svd(F.astype(np.float64), compute_uv=False)
    J = np.prod(sv, axis=1)
    return mu * ((sv - 1) ** 2).sum(1) + 0.5 * lam * (J - 1) ** 2


def continuum_energy(mode: str, L: float, r: float, E: float, nu: float) -> float:
    """The continuum rod's strain energy at unit modal amplitude of `mode_velocity`'s read field
    (axial and torsion: u ~ sin(pi t / L); bending: u = phi(t) b, Euler-Bernoulli, no shear energy)."""
    A, I, J = math.pi * r * r, math.pi * r ** 4 / 4, math.pi * r ** 4 / 2
    if mode == "axial":
        return 0.5 * E * A * (math.pi / L) ** 2 * L / 2
    if mode == "torsion":
        return 0.5 * E / (2 * (1 + nu)) * J * (math.pi / L) ** 2 * L / 2
    t = np.linspace(-0.5 * L, 0.5 * L, 4001)
    xi = BETA_FF * (t / L + 0.5)
    d2 = (BETA_FF / L) ** 2 * (np.cosh(xi) - np.cos(xi) - SIGMA_FF * (np.sinh(xi) - np.sin(xi)))
    return 0.5 * E * I * float(np.trapezoid(d2 ** 2, t))


def _frequency(t, q, f_ref):
    """q(t) = A exp(-g t) sin(omega t + phi) + c by least squares: (f, {decay per period, rms / A})."""
    from scipy.optimize import curve_fit

    def model(t, A, g, om, ph, c):
        return A * np.exp(-g * t) * np.sin(om * t + ph) + c

    A0 = np.abs(q).max()
    p0 = (A0, 0.0, 2 * math.pi * f_ref, 0.0, 0.0)
    best = None
    for om0 in (0.8, 1.0, 1.25):
        try:
            p, _ = curve_fit(model, t, q, p0=(A0, 0.0, 2 * math.pi * f_ref * om0, 0.0, 0.0), maxfev=20000)
        except RuntimeError:
            continue
        res = float(np.sqrt(np.mean((model(t, *p) - q) ** 2)))
        if best is None or res < best[1]:
            best = (p, res)
    p, res = best
    om = abs(p[2])
    return om / (2 * math.pi), {"decay": float(1 - math.exp(-p[1] * 2 * math.pi / om)), "rms": res / max(abs(p[0]), 1e-30)}


def _fmt(v):
    return "-" if v is None else f"{v:.3f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", default="2,3,4,6,8", help="cells across the rod's diameter")
    ap.add_argument("--orient", default="x,xy45,xyz")
    ap.add_argument("--modes", default="axial,torsion,bending")
    ap.add_argument("--slender", type=float, default=6.0, help="length / diameter")
    ap.add_argument("--nu", type=float, default=0.3)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--phase", default="0.31,0.17,0.43", help="the rod's centre inside a lattice cell, in spacings")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    phase = tuple(float(v) for v in a.phase.split(","))
    import warp as wp

    wp.config.quiet = True
    rows = []
    for mode in a.modes.split(","):
        for orient in a.orient.split(","):
            for cells in (float(v) for v in a.cells.split(",")):
                row = run_case(mode, orient, cells, a.slender, a.nu, dtype=a.dtype, device=a.device, phase=phase)
                rows.append(row)
                print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    print("\n| mode | orient | cells across | particles | lattice vol / true | E_app / E (frequency) | E_static / E (energy) | "
          "APIC inertia prediction | decay / period | CPU s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['mode']} | {r['orient']} | {r['cells']:g} | {r['particles']} | {r['volume_ratio']:.3f} | "
              f"{r['E_app']:.3f} | {r['E_static']:.3f} | {_fmt(r['apic_inertia_pred'])} | "
              f"{r['decay_per_period']:.3f} | {r['cpu_s']:.1f} |")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
