"""Forward+backward time of the Warp Gaussian-splat renderer, on the scene gsplat_probe.py uses.

Scene (as .dev/probes/gsplat_probe.py): N Gaussians with means uniform in [-0.3, 0.3]^2 x
[1.7, 2.3] in front of an identity OpenCV camera, fx = fy = 1.2 W, isotropic scale 0.01 (random
rotations do not matter then), opacity 0.8, random colours; loss = rgb.sum() + alpha.sum(), all
gradients (means, covariances, colours, opacities) computed. Times are medians of wall-clock
time with a device synchronisation, after warm-up (compilation excluded).

    python benchmarks/bench_render.py --device cpu [--sizes 2000x128,10000x256] [--reps 5]
    python benchmarks/bench_render.py --device cuda --png out.png --check-cpu

Prints a markdown table (and with --json, JSON lines).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import numpy as np
import torch

from physinteract_usd.camera import GL_TO_CV, Camera
from physinteract_usd.render import RasterSettings, render, render_batch

DEFAULT_SIZES = "2000x128,10000x256,10000x512,100000x256,100000x512"


def probe_scene(n: int, size: int, device: str, dtype=torch.float32, seed: int = 0):
    """The gsplat probe's scene, as (means, covs (N,6), colors, opacities, camera)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 0.6
    means[:, 2] += 2.0
    s = 0.01
    cov6 = torch.zeros(n, 6)
    cov6[:, 0] = cov6[:, 3] = cov6[:, 5] = s * s
    colors = torch.rand(n, 3, generator=g)
    op = torch.full((n,), 0.8)
    cam = Camera(1.2 * size, 1.2 * size, size / 2, size / 2, size, size, GL_TO_CV.copy())
    t = lambda x: x.to(device=device, dtype=dtype)  # noqa: E731
    return t(means), t(cov6), t(colors), t(op), cam


def _sync(device):
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_fwd_bwd(n, size, device, reps=5, warmup=2, settings=None):
    means, cov6, colors, op, cam = probe_scene(n, size, device)
    params = [x.clone().requires_grad_(True) for x in (means, cov6, colors, op)]

    def step():
        for p in params:
            p.grad = None
        out = render(*params, cam, settings=settings)
        (out["rgb"].sum() + out["alpha"].sum()).backward()

    def fwd():
        with torch.no_grad():
            render(*params, cam, settings=settings)

    return _time_steps(step, fwd, device, reps, warmup)


def _time_steps(step, fwd, device, reps, warmup):
    """Forward+backward (`step`) and forward (`fwd`) timed after `warmup` steps: ms, median and min
    of `reps`."""
    for _ in range(warmup):
        step()
    _sync(device)
    res = {}
    for name, fn in (("fwd_bwd", step), ("fwd", fwd)):
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            _sync(device)
            ts.append(1e3 * (time.perf_counter() - t0))
        res[name + "_ms"] = statistics.median(ts)
        res[name + "_min_ms"] = min(ts)
    return res


def time_batch(n, size, device, M, reps=5, warmup=2, settings=None):
    """`render_batch` of M images (the scene's Gaussians moved a little per image, one camera) forward
    and forward+backward: ms for all M (median, min)."""
    means, cov6, colors, op, cam = probe_scene(n, size, device)
    g = torch.Generator().manual_seed(1)
    shift = (0.002 * torch.randn(M, 1, 3, generator=g)).to(device=device, dtype=means.dtype)
    mb = (means[None] + shift).clone().requires_grad_(True)
    cb = cov6[None].expand(M, n, 6).clone().requires_grad_(True)
    cams = [cam] * M

    def step():
        mb.grad = cb.grad = None
        out = render_batch(mb, cb, colors, op, cams, settings=settings)
        (out["rgb"].sum() + out["alpha"].sum()).backward()

    def fwd():
        with torch.no_grad():
            render_batch(mb, cb, colors, op, cams, settings=settings)

    return _time_steps(step, fwd, device, reps, warmup)


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    import os

    return f"{platform.processor() or platform.machine()} CPU, {os.cpu_count()} cores visible (Warp CPU: 1 thread)"


def consistency_check(size=256, n=10000, out_png=None, cuda_settings=None, cpu_ref=None, devices=("cpu", "cuda")):
    """One render forward+backward on CUDA (with `cuda_settings`) and on CPU (defaults), float32:
    max abs differences. `cpu_ref`: an .npz of the CPU side saved earlier (a GPU host's Warp may
    have no CPU compiler); devices=("cpu",) with cpu_ref saves it."""
    res = {}
    outs = {}
    if cpu_ref and "cpu" not in devices:
        z = np.load(cpu_ref)
        outs["cpu"] = {k: torch.as_tensor(z[k]) for k in z.files}
    for dev in devices:
        means, cov6, colors, op, cam = probe_scene(n, size, dev)
        params = [x.clone().requires_grad_(True) for x in (means, cov6, colors, op)]
        o = render(*params, cam, background=torch.tensor([0.1, 0.1, 0.2], device=dev),
                   settings=cuda_settings if dev == "cuda" else None)
        g = torch.Generator().manual_seed(1)
        w = torch.rand(size, size, 3, generator=g).to(dev)
        ((o["rgb"] * w).sum() + o["alpha"].sum() + 0.1 * o["depth"].sum()).backward()
        outs[dev] = {k: v.detach().cpu() for k, v in o.items()}
        outs[dev].update({f"grad_{k}": p.grad.cpu() for k, p in zip(("means", "cov6", "colors", "opacities"), params)})
    if "cuda" not in outs:
        np.savez(cpu_ref, **{k: v.numpy() for k, v in outs["cpu"].items()})
        return {}
    for k in outs["cpu"]:
        a, b = outs["cpu"][k], outs["cuda"][k]
        res[k] = {"max_abs": float((a - b).abs().max()), "max_ref": float(a.abs().max())}
    if out_png:
        write_png(out_png, outs["cuda"]["rgb"].numpy())
    return res


def write_png(path, img) -> None:
    """(H, W, 3) float in [0, 1] -> 8-bit PNG, stdlib only (the GPU host may lack OpenCV/PIL)."""
    import struct
    import zlib

    a = (np.clip(np.asarray(img, dtype=np.float64), 0, 1) * 255 + 0.5).astype(np.uint8)
    h, w = a.shape[:2]
    raw = b"".join(b"\x00" + a[j].tobytes() for j in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    with open(path, "wb") as f:
        f.write(png)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default=DEFAULT_SIZES, help="comma list of NxSIZE")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--tile-size", type=int, default=None, help="default: 16 on CUDA, 8 on CPU")
    ap.add_argument("--lockstep", type=int, choices=(0, 1), default=None,
                    help="backward walks each tile's list in lockstep (default: on CUDA only)")
    ap.add_argument("--backward", choices=("pixel", "tiled"), default="pixel",
                    help="pixel: per-pixel atomics (default); tiled: block reduction per Gaussian (CUDA)")
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="torch intra-op threads on CPU (default 1: Warp's CPU backend is single-threaded "
                         "and torch's thread pool only adds overhead on small images)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--batch", type=int, default=0,
                    help="also M images in one pass (render_batch, as the batched fit renders its copies' and "
                         "frames' images): ms per image against one render per image")
    ap.add_argument("--png", help="also save the rendered image of the first size here")
    ap.add_argument("--check-cpu", action="store_true", help="CPU vs this device: one fwd+bwd, max abs diff")
    ap.add_argument("--cpu-ref", help="with --check-cpu: the CPU side from this .npz (saved with --save-cpu)")
    ap.add_argument("--save-cpu", help="compute the CPU side of the consistency check only, save it here, exit")
    a = ap.parse_args(argv)
    settings = RasterSettings(tile_size=a.tile_size,
                              lockstep=None if a.lockstep is None else bool(a.lockstep), backward=a.backward)
    if a.device == "cpu" and a.torch_threads:
        torch.set_num_threads(a.torch_threads)
    import warp as wp

    wp.config.quiet = True
    wp.init()
    print(f"device: {a.device}: {device_name(a.device)}; torch {torch.__version__}, warp {wp.__version__}, "
          f"python {platform.python_version()}, tile {settings.resolved_tile_size(a.device)}, "
          f"backward {a.backward}, lockstep {settings.resolved_lockstep(a.device)}, torch threads {torch.get_num_threads()}")
    rows = []
    print("| Gaussians | image | fwd+bwd median ms | fwd median ms | fwd+bwd min ms |")
    print("|---:|---:|---:|---:|---:|")
    for item in a.sizes.split(","):
        n, size = (int(x) for x in item.lower().split("x"))
        try:
            r = time_fwd_bwd(n, size, a.device, a.reps, a.warmup, settings)
        except Exception as exc:  # keep going: report the failure in the table
            print(f"| {n} | {size}^2 | failed: {exc.__class__.__name__}: {exc} | | |")
            continue
        rows.append({"n": n, "size": size, "device": a.device, **r})
        print(f"| {n} | {size}^2 | {r['fwd_bwd_ms']:.2f} | {r['fwd_ms']:.2f} | {r['fwd_bwd_min_ms']:.2f} |")
        sys.stdout.flush()
    if a.batch > 1:
        print(f"\n{a.batch} images in one pass (render_batch) against one render each, ms per image (median)\n")
        print("| Gaussians per image | image | batched fwd+bwd | one by one fwd+bwd | batched fwd | one by one fwd |")
        print("|---:|---:|---:|---:|---:|---:|")
        for r in list(rows):
            if "batch" in r:
                continue
            b = time_batch(r["n"], r["size"], a.device, a.batch, a.reps, a.warmup, settings)
            M = a.batch
            rows.append({"n": r["n"], "size": r["size"], "device": a.device, "batch": M,
                         **{k: v / M for k, v in b.items()}})
            print(f"| {r['n']} | {r['size']}^2 | {b['fwd_bwd_ms'] / M:.3f} | {r['fwd_bwd_ms']:.3f} | "
                  f"{b['fwd_ms'] / M:.3f} | {r['fwd_ms']:.3f} |")
    if a.json:
        for r in rows:
            print(json.dumps(r))
    if a.png:
        n, size = (int(x) for x in a.sizes.split(",")[0].lower().split("x"))
        means, cov6, colors, op, cam = probe_scene(n, size, a.device)
        with torch.no_grad():
            o = render(means, cov6, colors, op, cam, background=torch.tensor([0.1, 0.1, 0.2], device=a.device))
        write_png(a.png, o["rgb"].cpu().numpy())
        print(f"saved {a.png}")
    if a.save_cpu:
        consistency_check(cpu_ref=a.save_cpu, devices=("cpu",))
        print(f"saved the CPU reference to {a.save_cpu}")
        return
    if a.check_cpu:
        res = consistency_check(cuda_settings=settings, cpu_ref=a.cpu_ref,
                                devices=("cuda",) if a.cpu_ref else ("cpu", "cuda"))
        print(f"CPU vs CUDA (backward {a.backward} on CUDA), one forward+backward (10k Gaussians, 256^2, "
              "float32): max abs difference")
        for k, v in res.items():
            print(f"  {k}: {v['max_abs']:.3e} (max |value| {v['max_ref']:.3e})")
        print(json.dumps({"consistency": res}))


if __name__ == "__main__":
    main()
