"""Why the simulation depends on its time step (#24): a cantilever under gravity, float64, on the CPU.

A rod (L 0.10 m, 0.02 x 0.02 m section, its first 0.02 m held by a fixed support; E 22.6 kPa, nu 0.4, rho
150 kg/m^3: telephone_cable's range) on a 10 mm grid, 8 particles a cell, released from straight at rest.
Per substep count a frame (fps 20): the tip's height per frame, its mean over whole periods (the static sag,
against Euler-Bernoulli), the period (against the beam's first frequency), and the ringing's decay per
period (the log decrement). The undamped continuum keeps ringing: every decay here is the method's own.

Transfers (`--transfer`):
  apic        the product's step (MPMSolver.step: APIC / MLS-MPM, pure projection every substep)
  rate:TAU    the same step, then host-side the particle keeps exp(-dt / TAU) of what the grid could not carry
              (an APIC/FLIP blend whose projection acts at a rate per unit time, like the pins' blend_dt):
              v_p <- v_grid_new(x_p) + f (v_p - v_grid_old(x_p)), f = exp(-dt / TAU), v_grid_old the
              substep's grid velocity before stress and gravity (p2g of m v + m C d). Forward only, an
              experiment: not in the kernels.

    python benchmarks/dt_convergence.py [--substeps 150,300,600,1200,2400] [--transfer apic,rate:0.002,kernel:0.01]
        [--frames 20] [--out rows.jsonl]
    # the E a model at one step needs to match a truth at another (least squares on the tip over the frames):
    python benchmarks/dt_convergence.py --truth 1200 --model 150 --scales 0.8,0.9,1,1.1,1.2,1.4,1.6 [--transfer apic]
        [--damping 0,2,4,6,8,10]     # ... and E jointly with the model's global damping c (#24)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

L, H, DX, PPC, CLAMP = 0.10, 0.02, 0.01, 2, 0.02
E0, NU, RHO, FPS = 2.26e4, 0.4, 150.0, 20.0


def rod(L=L, h=H, dx=DX, ppc=PPC, clamp=CLAMP):
    s = dx / ppc
    xs, ys = np.arange(s / 2, L, s), np.arange(s / 2, h, s)
    X = np.stack(np.meshgrid(xs, ys, ys, indexing="ij"), -1).reshape(-1, 3)
    return X, s ** 3, np.nonzero(X[:, 0] < clamp)[0]


def beam(E=E0, rho=RHO):
    """Euler-Bernoulli static tip sag [m] and first frequency [Hz] of the free length."""
    Lf = L - CLAMP
    sag = 1.5 * rho * 9.81 * Lf ** 4 / (E * H ** 2)
    f1 = 1.875 ** 2 / (2 * math.pi) * math.sqrt(E * H ** 2 / 12.0 / (rho * Lf ** 4))
    return sag, f1


class RateTransfer:
    """Host-side after MPMSolver.step (forward only): the particle keeps f = exp(-dt / tau) of the velocity
    the grid could not carry, v_p <- v_p' + f (v_p - v_grid_old(x_p)) for particles no pin drives
    (v_p' the step's APIC velocity, v_grid_old the substep's grid velocity before its forces: p2g of m v + m C d).
    tau <= 0: nothing (the product's pure APIC)."""

    def __init__(self, sol, tau: float):
        import warp as wp

        from physinteract_usd.sim.kernels import SCATTERED

        self.sol, self.wp = sol, wp
        m = sol.model
        K, d, P = sol.K, m.device, m.n_particles
        self.f = math.exp(-m.dt / tau) if tau > 0 else 0.0
        if self.f > 0:
            self.An = wp.zeros(P, dtype=K.mat33, device=d)
            self.g = [wp.zeros_like(getattr(sol, k)) for k in SCATTERED]   # the solver's scattered grid arrays
            self.gvo = wp.zeros(sol.res, dtype=K.vec3, device=d)
            self.vgo = wp.zeros(P, dtype=K.vec3, device=d)
            self.Cgo = wp.zeros(P, dtype=K.mat33, device=d)
            self.pin_id = sol.ctrl.pin_id.numpy()
            self.pin_active = sol.ctrl.pin_active.numpy()

    def __call__(self, a, b, frame: int):
        if self.f <= 0:
            return
        sol, wp, K = self.sol, self.wp, self.sol.K
        m = sol.model
        P, d = m.n_particles, m.device
        self.An.assign(m.mass[:, None, None] * a.C.numpy())
        for arr in self.g:
            arr.zero_()
        c = sol.ctrl
        wp.launch(K.p2g_scatter, P, [a.x, a.v, self.An, sol.dev["mass"], c.pin_id, c.pin_active, c.pin_pos, c.pin_kind,
                                     frame, sol.fps, sol.lo, sol.inv_dx, sol.res3, 0, sol.box, sol.dt, a.F],
                  self.g + [sol.box_flag, sol.clamped], device=d)
        gm, gmv = self.g[0].numpy(), self.g[1].numpy()
        self.gvo.assign(np.where(gm[..., None] > sol.m_eps, gmv / np.maximum(gm, 1e-300)[..., None], 0.0))
        wp.launch(K.g2p_gather, P, [a.x, self.gvo, sol.lo, sol.inv_dx, sol.res3], [self.vgo, self.Cgo], device=d)
        free = self.pin_id < 0
        free |= self.pin_active[np.maximum(self.pin_id, 0), frame] == 0
        vn = b.v.numpy()
        vn[free] += self.f * (a.v.numpy()[free] - self.vgo.numpy()[free])
        b.v.assign(vn)


def tau_of(transfer: str) -> float:
    """The host-side prototype's tau (0: none; `kernel:TAU` is the product's SimModel.transfer_tau instead)."""
    if transfer == "apic" or transfer.startswith("kernel:"):
        return 0.0
    if transfer.startswith("rate:"):
        return float(transfer.split(":")[1])
    raise ValueError(f"--transfer {transfer!r}: apic, rate:TAU (host-side prototype) or kernel:TAU (the product's)")


def kernel_tau(transfer: str) -> float:
    """SimModel.transfer_tau for `kernel:TAU` (the rate transfer in the kernels), else 0."""
    return float(transfer.split(":")[1]) if transfer.startswith("kernel:") else 0.0


def run_solver(sol, frames: int, transfer: str = "apic", per_frame: int = 1, record=None):
    """Step an MPMSolver `frames` frames from rest; `record(state)` at `per_frame` samples a frame
    (and at rest). Returns (records, CPU s)."""
    from physinteract_usd.sim import SimState

    m = sol.model
    a, b = SimState.rest(m), SimState.zeros(m.n_particles, m.dtype, m.device)
    hook = RateTransfer(sol, tau_of(transfer))
    out = [record(a)]
    every = max(1, m.substeps // per_frame)
    t0 = time.process_time()
    for k in range(frames):
        for s in range(m.substeps):
            sol.step(a, b, k, s)
            hook(a, b, k)
            a, b = b, a
            if (s + 1) % every == 0 and (s + 1) // every <= per_frame:
                out.append(record(a))
    return out, time.process_time() - t0


def simulate(substeps: int, transfer: str = "apic", frames: int = 20, E=E0, dtype="float64", per_frame: int = 1,
             dx: float = DX, damping: float = 0.0):
    """Tip height (m, from rest) at `per_frame` samples a frame; and process CPU seconds."""
    from physinteract_usd.sim import Contact, Control, GridSpec, MPMSolver, SimModel

    X, vol, held = rod(dx=dx)
    grid = GridSpec.around(X, dx, padding=[0.03, 0.08, 0.03])
    ctrl = Control([Contact("fixed", indices=held)], n_frames=frames)
    m = SimModel.create(X, vol, RHO, E, NU, grid=grid, fps=FPS, substeps=substeps, dtype=dtype,
                        transfer_tau=kernel_tau(transfer),
                        effects={"damping": {"coefficient": float(damping)}} if damping > 0 else None)
    tip = np.argsort(X[:, 0])[-16:]
    y0 = X[tip, 1].mean()
    ys, cpu = run_solver(MPMSolver(m, ctrl), frames, transfer, per_frame,
                         lambda s: float(s.x.numpy()[tip, 1].mean() - y0))
    return np.array(ys), cpu


def analyse(y: np.ndarray, rate: float) -> dict:
    """Period, mean over whole periods, log decrement per period from the tip's lows (y sampled at `rate` Hz)."""
    lows = [k for k in range(1, len(y) - 1) if y[k] < y[k - 1] and y[k] <= y[k + 1]]

    def sub(k):
        a, b, c = y[k - 1], y[k], y[k + 1]
        den = a - 2 * b + c
        return k + (0.5 * (a - c) / den if den > 0 else 0.0), b - (a - c) ** 2 / (8 * den) if den > 0 else b

    out = {"lows": len(lows)}
    if len(lows) >= 3:
        tl = [sub(k) for k in lows]
        out["period_s"] = (tl[-1][0] - tl[0][0]) / (len(tl) - 1) / rate
        whole = y[lows[0]:lows[-1]]
        mean = float(whole.mean())
        out["mean_sag_m"] = -mean
        amp = [mean - v for _, v in tl]
        if min(amp) > 0:
            out["log_decrement"] = float(math.log(amp[0] / amp[-1]) / (len(amp) - 1))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--substeps", default="150,300,600,1200,2400")
    ap.add_argument("--transfer", default="apic")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--samples", type=int, default=6, help="tip samples a frame (for the period and decay)")
    ap.add_argument("--dx", type=float, default=DX, help=f"grid cell [m] (default {DX}: 2 cells across the rod)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--truth", type=int, default=0, help="with --model: the truth's substeps a frame (E = E0)")
    ap.add_argument("--model", type=int, default=0, help="with --truth: the model's substeps a frame, E swept")
    ap.add_argument("--scales", default="0.8,0.9,1,1.1,1.2,1.4,1.6", help="the model's E / E0")
    ap.add_argument("--damping", default="", help="with --truth/--model: also scan the model's global damping c "
                    "(1/s; the `damping` effect) jointly with --scales, e.g. 0,2,4,6,8,10 (#24)")
    a = ap.parse_args(argv)
    if a.truth and a.model:
        for tr in a.transfer.split(","):
            yt, _ = simulate(a.truth, tr, a.frames, dx=a.dx)
            rms = {}
            for sc in (float(v) for v in a.scales.split(",")):
                ym, cpu = simulate(a.model, tr, a.frames, E=E0 * sc, dx=a.dx)
                rms[sc] = float(np.sqrt(np.mean((ym[1:] - yt[1:]) ** 2)))
            ks = sorted(rms)
            i = int(np.argmin([rms[k] for k in ks]))
            best = ks[i]
            if 0 < i < len(ks) - 1:      # a parabola through the best three (in log E)
                x = np.log(ks[i - 1:i + 2])
                c = np.polyfit(x, [rms[k] for k in ks[i - 1:i + 2]], 2)
                best = float(np.exp(-c[1] / (2 * c[0]))) if c[0] > 0 else best
            row = {"transfer": tr, "truth_substeps": a.truth, "model_substeps": a.model, "dx": a.dx,
                   "rms_mm": {str(k): round(1e3 * v, 3) for k, v in rms.items()}, "best_E_over_truth": round(best, 3)}
            if a.damping:     # the model with a global damping c too: the joint least squares over E x c (#24)
                grid = {}
                for cc in (float(v) for v in a.damping.split(",")):
                    for sc in (float(v) for v in a.scales.split(",")):
                        ym, _ = simulate(a.model, tr, a.frames, E=E0 * sc, dx=a.dx, damping=cc)
                        grid[(sc, cc)] = float(np.sqrt(np.mean((ym[1:] - yt[1:]) ** 2)))
                (bs, bc), brms = min(grid.items(), key=lambda kv: kv[1])
                row["joint"] = {"E_over_truth": bs, "c": bc, "rms_mm": round(1e3 * brms, 3),
                                "rms_mm_grid": {f"{k[0]},{k[1]}": round(1e3 * v, 3) for k, v in grid.items()}}
            print(json.dumps(row), flush=True)
            if a.out:
                with open(a.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
        return
    sag, f1 = beam()
    print(json.dumps({"beam": {"static_tip_sag_mm": round(1e3 * sag, 3), "f1_hz": round(f1, 3)}}), flush=True)
    for tr in a.transfer.split(","):
        for n in (int(v) for v in a.substeps.split(",")):
            y, cpu = simulate(n, tr, a.frames, per_frame=a.samples, dx=a.dx)
            an = analyse(y, FPS * a.samples)
            row = {"transfer": tr, "substeps": n, "dx": a.dx, "particles": len(rod(dx=a.dx)[0]), "dt": 1.0 / (FPS * n), "cpu_s": round(cpu, 1),
                   "tip_mm_per_frame": [round(1e3 * v, 3) for v in y[::a.samples]],
                   "mean_sag_over_beam": round(an["mean_sag_m"] / sag, 4) if "mean_sag_m" in an else None,
                   "f_over_beam": round(1.0 / an["period_s"] / f1, 4) if "period_s" in an else None,
                   "log_decrement": round(an["log_decrement"], 4) if "log_decrement" in an else None}
            print(json.dumps(row), flush=True)
            if a.out:
                with open(a.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
