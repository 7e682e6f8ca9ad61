"""What a hidden effect's "1x" does to the frames (issue #22): per effect and strength, the synth's particle
calibration (`synth --calibrate particles`, the default: RMS projected particle displacement = s x 0.5 px) and
what it changes in the noise-free frames, D^2 / sigma^2 (mean squared change over frames 1.. and the pixels the
hand leaves, and over the object's silhouette in either render; sigma 0.015), beside the frame calibration
(`--calibrate frames`: D^2 = s x sigma^2) and its parameter. The scene's setup is `synth`'s (same seed, same
camera, same hand, noise-free). **Development data** (the synthetic suite).

CPU (foam_bar, 16 frames, the truth at --fit-grid 16: ~4 CPU s a simulation; the default grid 24 is ~20 s):

    python benchmarks/hidden_frame_change.py --scene foam_bar --frames 16 --fit-grid 16 \\
        --effects damping,viscoelasticity,plasticity,ground --strengths 1,2 --out /tmp/hfc.json

`--frames-calibration` adds the frame calibration per case (~6-12 more simulations each).
"""

from __future__ import annotations

import argparse
import importlib
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def setup(scene: str, size: str, frames: int, fit_grid, seed: int, device: str):
    G = importlib.import_module("physinteract_usd.synth.generate")

    spec, sz = G.SCENES[scene], G.SIZES[size]
    if fit_grid:
        sz = dataclasses.replace(sz, fit_grid=int(fit_grid))
    gt = G.GroundTruth(spec, sz, frames, device=device)
    g, _ = G.surface_gaussians(spec, gt.shape, sz.gaussians, seed)
    cam = G.frame_camera(spec, gt, sz)
    blur = 3 if spec.origin == "real" else 1
    return gt, cam, G._scene_renderer(spec, gt, sz, size, g, cam, blur, seed, device)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="foam_bar")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--fit-grid", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effects", default="damping,viscoelasticity,plasticity,ground")
    ap.add_argument("--strengths", default="1,2")
    ap.add_argument("--sigma", type=float, default=0.015)
    ap.add_argument("--frames-calibration", action="store_true")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    G = importlib.import_module("physinteract_usd.synth.generate")

    c0 = time.process_time()
    gt, cam, render = setup(a.scene, a.size, a.frames, a.fit_grid, a.seed, a.device)
    base_x, base_F = gt.run()
    b = render(base_x, base_F)
    print(f"{a.scene}: {len(gt.x0)} particles, {gt.substeps} substeps/frame; base {time.process_time() - c0:.1f} CPU s",
          flush=True)
    sub = np.arange(0, base_x.shape[1], max(1, base_x.shape[1] // 400))
    s2 = a.sigma ** 2
    rows = []
    quiet = lambda *_a, **_k: None  # noqa: E731

    def measure(eff, params):
        x, F = gt.run({eff: params})
        r = render(x, F)
        obj = r[2] | b[2]
        return {"px": G._pixel_effect(cam, x[:, sub], base_x[:, sub]),
                "d2_frame": G.frame_change(r[0], b[0], r[3], b[3]) / s2,
                "d2_mask": G.frame_change(r[0], b[0], r[3], b[3], mask=obj) / s2,
                "mask_share": float(obj[1:].mean())}

    for eff in a.effects.split(","):
        for s in (float(v) for v in a.strengths.split(",")):
            c1 = time.process_time()
            params, _ = G.calibrate_effect(gt, cam, eff, s, base_x, log=quiet)
            row = {"effect": eff, "strength": s, "particles": dict(params=params, **measure(eff, params))}
            if a.frames_calibration:
                fp, ratio, info = G.calibrate_frames(gt, lambda x, F: (lambda o: (o[0], o[3]))(render(x, F)), eff, s,
                                                     base_x, b[0], b[3], a.sigma, log=quiet)
                row["frames"] = dict(params=fp, calibrated_ratio=ratio, simulations=len(info["trace"]),
                                     trace=info["trace"],
                                     **measure(eff, fp))
            row["cpu_s"] = round(time.process_time() - c1, 1)
            rows.append(row)
            p = row["particles"]
            line = (f"{eff:16s} {s:4g}x  particles: {p['px']:.3f} px, D^2/s^2 frame {p['d2_frame']:7.2f}, "
                    f"mask {p['d2_mask']:7.2f} ({_fmt(p['params'])})")
            if "frames" in row:
                f = row["frames"]
                line += (f" | frames: D^2/s^2 {f['d2_frame']:.2f} ({f['simulations']} sims), {f['px']:.3f} px "
                         f"({_fmt(f['params'])})")
            print(line + f"  [{row['cpu_s']} CPU s]", flush=True)
            if a.out:
                Path(a.out).write_text(json.dumps({"args": vars(a), "rows": rows}, indent=1, default=float))
    if os.environ.get("OUT"):
        Path(os.environ["OUT"], "hidden_frame_change.json").write_text(
            json.dumps({"args": vars(a), "rows": rows}, indent=1, default=float))
    print(f"total {time.process_time() - c0:.0f} CPU s")
    return 0


def _fmt(params: dict) -> str:
    return ", ".join(f"{k} {v:.4g}" for k, v in params.items())


if __name__ == "__main__":
    sys.exit(main())
