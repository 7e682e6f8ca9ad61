"""A coil's static sag against cells across its wire (#24): is the synthetic telephone cable's coil
resolved at `init --grid auto` (4 cells across the wire)? The suite's coil in miniature: a helix of
coil radius 30 mm, pitch 45 mm, wire 28 mm (scenes.COIL_*), `--turns` turns, held at both ends (the
first and last wire diameter of its length fixed), sagging under gravity, damped to rest
(mass-proportional damping); filled as fill.py fills (lattice dx / 2 aligned with the grid). The
sag of the coil's middle at n cells across against the finest n: a static E bias of the fit at n is
sag(n) / sag(finest) (the sag goes as 1 / E).

    python benchmarks/coil_sag.py --cells 3,4,6,8 [--turns 1.5] [--seconds 2.0]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

R_COIL, PITCH, WIRE = 0.03, 0.045, 0.028


def helix(u):
    """The centreline at turn fraction u (0..turns), axis y (down as u grows)."""
    t = 2 * math.pi * np.asarray(u)
    return np.stack([R_COIL * np.cos(t), -PITCH * np.asarray(u), R_COIL * np.sin(t)], -1)


def coil_particles(cells: float, turns: float, phase=(0.31, 0.17, 0.43)):
    dx = WIRE / cells
    s = dx / 2
    us = np.linspace(0, turns, int(4000 * turns))
    c = helix(us)
    lo, hi = c.min(0) - WIRE, c.max(0) + WIRE
    o = np.asarray(phase) * s
    axes = [o[d] + (np.arange(np.floor((lo[d] - o[d]) / s), np.ceil((hi[d] - o[d]) / s)) + 0.5) * s for d in range(3)]
    p = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    from scipy.spatial import cKDTree

    dist, j = cKDTree(c).query(p)
    keep = dist <= WIRE / 2
    return p[keep], us[j[keep]], dx, s


def run(cells: float, turns: float, seconds: float, damping: float, E=7.5e3, nu=0.4, rho=150.0, fps=20.0,
        E_max=None) -> dict:
    from physinteract_usd.sim import Contact, Control, GridSpec, MPMSolver, SimModel

    pts, u, dx, s = coil_particles(cells, turns)
    held_len = WIRE / (2 * math.pi * math.hypot(R_COIL, PITCH / (2 * math.pi)))   # one wire diameter, in turns
    held = np.nonzero((u <= held_len) | (u >= turns - held_len))[0]
    mid = np.nonzero(np.abs(u - turns / 2) <= 0.5 * held_len)[0]
    T = int(round(seconds * fps))
    lo = np.floor((pts.min(0) - 0.06) / dx) * dx
    hi = pts.max(0) + 0.03
    grid = GridSpec(tuple(lo), dx, tuple(int(v) for v in np.ceil((hi - lo) / dx) + 1))
    m = SimModel.create(pts, s ** 3, rho, E, nu, grid=grid, fps=fps, E_max=E_max or E, dtype="float32",
                        effects={"damping": {"coefficient": damping}})
    c0 = time.process_time()
    out = MPMSolver(m, Control([Contact("fixed", indices=held)], n_frames=T)).simulate(T)
    cpu = time.process_time() - c0
    y = out["x"][:, mid, 1].mean(1) - pts[mid, 1].mean()
    return {"cells": cells, "dx_mm": 1000 * dx, "particles": len(pts), "held": len(held), "substeps": m.substeps,
            "sag_mm": -1000 * float(y[-1]), "sag_prev_mm": -1000 * float(y[-2]),
            "sag_curve_mm": [round(-1000 * float(v), 3) for v in y[:: max(1, T // 10)]], "cpu_s": cpu,
            "y_mm": (-1000 * y).tolist(),
            "volume_cm3": len(pts) * s ** 3 * 1e6}


def match(a):
    """The dynamic question: the coil starts straight at rest and drops, rings under gravity (no
    damping but the method's own); the fine coil's mid-coil y(t) is the truth; the coarse coil's E
    is swept (x 0.7 .. 1.4) for the least squares match. A best E above 1 means the coarse model
    needs a stiffer E to move like the fine one (its own dissipation and inertia), below 1 that it
    is stiffer than the fine one."""
    truth_cells, fits = a.match.split(":")
    fps = 60.0
    ref = run(float(truth_cells), a.turns, a.seconds, a.damping, fps=fps)
    yt = np.array(ref["y_mm"])
    print(json.dumps({k: v for k, v in ref.items() if k not in ("y_mm", "sag_curve_mm")}), flush=True)
    factors = np.exp(np.linspace(np.log(0.7), np.log(1.4), 11))
    for n in (float(v) for v in fits.split(",")):
        res = []
        for f in factors:
            r = run(n, a.turns, a.seconds, a.damping, E=7.5e3 * f, E_max=7.5e3 * factors[-1], fps=fps)
            y = np.array(r["y_mm"])
            res.append((float(f), float(np.sqrt(np.mean((y - yt) ** 2))), float(np.sqrt(np.mean((y[len(y) // 2:] -
                        yt[len(y) // 2:]) ** 2))), r["cpu_s"]))
            print(json.dumps({"cells": n, "factor": round(f, 4), "rms_mm": round(res[-1][1], 3),
                              "rms_second_half_mm": round(res[-1][2], 3), "mean_mm": round(float(y.mean()), 3),
                              "truth_mean_mm": round(float(yt.mean()), 3)}), flush=True)
        best = min(res, key=lambda t: t[1])
        i = [t[0] for t in res].index(best[0])
        if 0 < i < len(res) - 1:                    # a parabola through the best and its neighbours in log E
            x = np.log([res[i - 1][0], res[i][0], res[i + 1][0]])
            yv = [res[i - 1][1] ** 2, res[i][1] ** 2, res[i + 1][1] ** 2]
            c = np.polyfit(x, yv, 2)
            best_f = float(np.exp(-c[1] / (2 * c[0]))) if c[0] > 0 else best[0]
        else:
            best_f = best[0]
        print(json.dumps({"cells_truth": float(truth_cells), "cells_fit": n, "best_E_factor": round(best_f, 4),
                          "rms_at_best_mm": round(best[1], 3), "rms_at_1_mm": round(res[5][1], 3)}), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", default="3,4,6,8")
    ap.add_argument("--turns", type=float, default=1.5)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--damping", type=float, default=25.0)
    ap.add_argument("--match", default=None, help="CELLS_TRUTH:CELLS_FIT,...: undamped (--damping 0), the coarse "
                    "coil's E that best matches the fine coil's mid-coil drop-and-ring y(t) (an E sweep)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.match:
        return match(a)
    import warp as wp

    wp.config.quiet = True
    rows = []
    for n in (float(v) for v in a.cells.split(",")):
        r = run(n, a.turns, a.seconds, a.damping)
        rows.append(r)
        print(json.dumps(r), flush=True)
    ref = rows[-1]["sag_mm"]
    print("\n| cells across the wire | dx mm | particles | volume cm^3 | sag mm (last / previous frame) | sag / finest | CPU s |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['cells']:g} | {r['dx_mm']:.2f} | {r['particles']} | {r['volume_cm3']:.1f} | {r['sag_mm']:.3f} / "
              f"{r['sag_prev_mm']:.3f} | {r['sag_mm'] / ref:.3f} | {r['cpu_s']:.0f} |")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
