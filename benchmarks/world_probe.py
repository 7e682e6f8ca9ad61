"""Loss components against a uniform E, with the TRUE interaction, on one world-suite capture
(development split only): does the video determine E for our model, and which term sees it?

    python benchmarks/world_probe.py WORK CAPTURE GRID MULTIPLES [MAX_PARTICLES]
    python benchmarks/world_probe.py data/world_dev dev_0008 auto 0.25,1,4 6000

GRID: "sugg" (the capture's suggested grid), "auto" or a number; MULTIPLES of the true median E.
Prints, per E: frame 0's L1 (the appearance floor), the mean L1, SSIM, silhouette and a
frame-difference L1 over the other frames, and the CPU time. docs/benchmarks/world_fits.md."""
import json, shutil, sys, time
from pathlib import Path
import numpy as np, torch
sys.path.insert(0, "benchmarks")
from physinteract_usd import api
from physinteract_usd.app.fit import prepare_fit, make_problem
from world_fit import add_ground
from physinteract_usd.errors import InputError
from physinteract_usd.synth.splits import refuse_validation


def main(argv) -> int:
    work, n, grid = Path(argv[0]), argv[1], argv[2]
    mults = [float(m) for m in argv[3].split(",")]
    maxp = int(argv[4]) if len(argv) > 4 else 15000
    cap, gt = work / n, work / f"{n}.gt"
    try:
        refuse_validation(cap, "world_probe.py")     # a tuning tool: never on the validation split
        refuse_validation(gt, "world_probe.py")
    except InputError as exc:
        print(f"world_probe.py: error: {exc.oneline()}", file=sys.stderr)
        return 2
    g = json.loads((gt / "gt.json").read_text()); s = g["suggested_init"]
    E_true = np.load(gt / "youngs_modulus.npy"); Em = float(np.median(E_true))
    d = Path(f"/tmp/world_probe/{n}_{grid}"); shutil.rmtree(d, ignore_errors=True); d.mkdir(parents=True)
    st = d / "scene.usda"
    api.init(st, cap, grid=s["grid"] if grid == "sugg" else (grid if grid == "auto" else int(grid)), padding=s["padding"], youngs_range=tuple(s["youngs_range"]),
             max_poisson=s["max_poisson"], density=s["density"], max_particles=maxp, log=lambda *a: None)
    res = api.extract(st, log=lambda *a: None, preview=False)
    fl = res.evidence.get("floor")
    if fl: add_ground(st, fl["height"], fl.get("friction", 0.5))
    job = prepare_fit(st, iterations=1, contact_from=gt, log=lambda *a: None)
    prob = make_problem(job); sd = job.scene; P = len(sd.particles_positions)
    masks = prob.masks
    mv = [float((masks[k] != masks[0]).float().sum() / max(float(masks[0].sum()), 1)) if masks is not None else -1 for k in range(prob.T)]
    print(n, "grid", sd.settings.grid_resolution, "P", P, "E true", f"{Em:.4g}", "video mask change per frame (share of object px):",
          np.round(mv, 3).tolist(), flush=True)
    nu = torch.full((P,), float(np.median(np.load(gt / "poisson_ratio.npy"))), dtype=torch.float32)
    I0 = prob.frames[0]
    for f in mults:
        E = torch.full((P,), Em * f, dtype=torch.float32)
        t0 = time.process_time()
        with torch.no_grad():
            try:
                x, F = prob.simulate(E, nu)
            except Exception as e:
                print(f"E x{f}: {type(e).__name__}", flush=True); continue
            comps = {"l1": [], "ssim": [], "mask": [], "diff": []}
            R0 = prob.render_frame(0, x[0], F[0])["rgb"]
            for k in range(prob.T):
                out = prob.render_frame(k, x[k], F[k])
                c = prob.frame_loss(k, out)
                for q in ("l1", "ssim", "mask"):
                    if q in c: comps[q].append(float(c[q]))
                w = prob.weight[k] if prob.weight is not None else 1.0
                comps["diff"].append(float(((out["rgb"] - R0) - (prob.frames[k] - I0)).abs().mul(w if torch.is_tensor(w) and w.dim() == out["rgb"].dim() else (w[..., None] if torch.is_tensor(w) else 1.0)).mean()))
        print(f"E x{f:<6g} frame0 l1 {comps['l1'][0]:.4f} | mean l1 {np.mean(comps['l1'][1:]):.5f} ssim {np.mean(comps['ssim'][1:]):.5f} "
              f"mask {np.mean(comps['mask'][1:]) if comps['mask'] else -1:.5f} diff {np.mean(comps['diff'][1:]):.5f}  ({time.process_time()-t0:.0f} cpu-s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
