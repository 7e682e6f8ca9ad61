"""CPU vs CUDA consistency of the differentiable MPM rollout (100 substeps, contacts and effects on).

Runs the same rollout (2 frames x 50 substeps; a grasp, a clamp, a sphere collider, the ground,
damping, plasticity and viscoelasticity; ~1000 particles on a 24^3 grid) on the CPU and on CUDA
(with and without CUDA graphs), in float64 and float32, and prints the largest difference of the
positions relative to the largest displacement, and of the gradients (dL/dE, dL/dnu, effect
parameters, trajectories) relative to their largest entry. PASS when positions agree within 1e-4
relative in both dtypes (and gradients within 1e-4 in float64, 1e-2 in float32).

    python benchmarks/check_sim_cuda.py              # cpu vs cuda:0
    python benchmarks/check_sim_cuda.py --device cpu # self-check without a GPU (graphs vs eager)
    python benchmarks/check_sim_cuda.py --save-cpu ref.npz              # here: the CPU reference
    python benchmarks/check_sim_cuda.py --cpu-ref ref.npz --kernels both # on a GPU host whose Warp has no
        # CPU compiler: CUDA with the separate and with the fused transfer kernels, each against it
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch
import warp as wp

wp.config.quiet = True
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel  # noqa: E402
from physinteract_usd.sim import solver as solver_mod  # noqa: E402

T, S = 2, 50


def scene(dtype: str, device: str):
    dx = 1.0 / 24
    sp = dx / 2
    dims = (14, 8, 9)
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in dims], indexing="ij"), -1).reshape(-1, 3)
    pts = idx * sp + np.array([0.3, 0.2 + sp / 2, 0.35])
    left = np.nonzero(idx[:, 0] == 0)[0]
    right = np.nonzero(idx[:, 0] == dims[0] - 1)[0]
    grab = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    grab[:, 0] += np.linspace(0, 0.03, T + 1)
    grab[:, 1] += np.linspace(0, 0.02, T + 1)
    top = np.array([pts[:, 0].mean(), pts[:, 1].max() + 0.05, pts[:, 2].mean()])
    sph = np.repeat(top[None], T + 1, 0)
    sph[:, 1] -= np.linspace(0, 0.03, T + 1)
    ctrl = Control([Contact("fixed", indices=left), Contact("pointAdherent", indices=right, trajectory=grab),
                    Contact("pointNonAdherent", trajectory=sph, radius=0.04, friction=0.3)], n_frames=T)
    eff = {"damping": {"coefficient": 2.0}, "ground": {"height": 0.2, "friction": 0.4},
           "plasticity": {"yieldStress": 300.0}, "viscoelasticity": {"modulus": 2e3, "relaxationTime": 0.05}}
    m = SimModel.create(pts, sp ** 3, 1000.0, 1e4, 0.3, grid=GridSpec((0, 0, 0), dx, (24, 24, 24)), fps=1.0 / (S * 2e-4),
                        substeps=S, E_max=2e4, dtype=dtype, device=device, effects=eff)
    return m, ctrl, grab, sph


def run(dtype: str, device: str, graphs: bool, fused=None):
    solver_mod.FUSED_KERNELS = fused     # None: the solver's default (fused on CUDA, separate on the CPU)
    m, ctrl, grab, sph = scene(dtype, device)
    tdev = "cpu" if device == "cpu" else device
    td = torch.float64 if dtype == "float64" else torch.float32
    P = m.n_particles
    E = torch.linspace(0.8e4, 1.2e4, P, dtype=td, device=tdev).requires_grad_(True)
    nu = torch.full((P,), 0.3, dtype=td, device=tdev, requires_grad=True)
    ys = torch.tensor(300.0, dtype=td, device=tdev, requires_grad=True)
    c = torch.tensor(2.0, dtype=td, device=tdev, requires_grad=True)
    tr = torch.tensor(grab, dtype=td, device=tdev, requires_grad=True)
    ts = torch.tensor(sph, dtype=td, device=tdev, requires_grad=True)
    ro = Rollout(m, ctrl, graphs=graphs)
    g = torch.Generator().manual_seed(0)
    W = torch.randn(T + 1, P, 3, generator=g, dtype=torch.float64).to(device=tdev, dtype=td)
    out = None
    t0 = time.perf_counter()
    for _ in range(2):   # twice: the second call replays the captured graphs
        for a in (E, nu, ys, c, tr, ts):
            a.grad = None
        x, F = ro(E, nu, effects={"plasticity": {"yieldStress": ys}, "damping": {"coefficient": c}},
                  trajectories={1: tr, 2: ts})
        ((x * W).sum() + F[-1].sum()).backward()
        out = {"x": x.detach().double().cpu().numpy(), "x0": m.x0,
               **{k: a.grad.detach().double().cpu().numpy() for k, a in
                  (("dE", E), ("dnu", nu), ("dyield", ys), ("ddamping", c), ("dgrasp", tr), ("dsphere", ts))}}
    wp.synchronize()
    out["seconds"] = time.perf_counter() - t0
    out["graphs"] = ro.graphs
    return out


def compare(a, b):
    disp = np.abs(a["x"] - a["x0"]).max()
    res = {"x": float(np.abs(a["x"] - b["x"]).max() / disp)}
    for k in a:
        if k.startswith("d"):
            res[k] = float(np.abs(a[k] - b[k]).max() / max(np.abs(a[k]).max(), 1e-30))
    return res, disp


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--save-cpu", metavar="NPZ", help="run the CPU reference only and save it (for a GPU host "
                    "whose Warp has no CPU compiler)")
    ap.add_argument("--cpu-ref", metavar="NPZ", help="compare against a CPU reference saved with --save-cpu")
    ap.add_argument("--kernels", choices=("default", "both"), default="default",
                    help="both: run the device with the separate and with the fused transfer kernels "
                    "(sim.solver.FUSED_KERNELS False / True), each against the CPU reference")
    args = ap.parse_args(argv)
    wp.init()
    if args.save_cpu:
        refs = {}
        for dtype in ("float64", "float32"):
            r = run(dtype, "cpu", graphs=False)
            refs.update({f"{dtype}/{k}": v for k, v in r.items() if isinstance(v, np.ndarray)})
        np.savez(args.save_cpu, **refs)
        print(f"saved the CPU reference to {args.save_cpu}")
        return 0
    saved = np.load(args.cpu_ref) if args.cpu_ref else None
    dev = args.device
    name = "CPU" if dev == "cpu" else wp.get_device(dev).name
    print(f"CPU vs {dev} ({name}); warp {wp.__version__}, torch {torch.__version__}; {T} frames x {S} substeps")
    ok = True
    for dtype, gtol in (("float64", 1e-4), ("float32", 1e-2)):
        try:
            if saved is not None:
                ref = {k.split("/", 1)[1]: saved[k] for k in saved.files if k.startswith(dtype + "/")}
            else:
                ref = run(dtype, "cpu", graphs=False)
            kernels = (None,) if args.kernels == "default" else (False, True)
            for graphs, fused in [(g, f) for g in (True, False) for f in kernels]:
                o = run(dtype, dev, graphs=graphs, fused=fused)
                res, disp = compare(ref, o)
                good = res["x"] < 1e-4 and all(v < gtol for k, v in res.items() if k != "x")
                ok &= good
                kern = "" if fused is None else f" kernels={'fused' if fused else 'separate'}"
                print(f"{dtype} {dev}{kern} graphs={graphs} (used: {o['graphs']}): max |dx| / max displacement "
                      f"({disp:.3g} m) = {res['x']:.2e}; gradients: "
                      + ", ".join(f"{k} {v:.1e}" for k, v in res.items() if k != "x")
                      + f"; {o['seconds']:.1f}s -> {'PASS' if good else 'FAIL'}", flush=True)
        except Exception as e:  # noqa: BLE001
            ok = False
            print(f"{dtype}: ERROR {type(e).__name__}: {e}", flush=True)
    print("RESULT:", "PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
