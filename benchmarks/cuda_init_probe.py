"""What a fresh process pays before its first useful GPU work (issue #26: the CLI small fit's ~5 s of
per-process warm-up on the H200, beyond the in-process fit). In one fresh process, in the order a fit
meets them, each timed in wall clock to a device synchronize:

    import torch          the import itself
    torch context         torch.empty(1, device=...) (CUDA context, caching allocator)
    first elementwise     a torch op's first kernel (lazy module loading)
    first conv2d (cuDNN)  the SSIM's depthwise separable blur (render/losses.py), forward + backward
    first bmm (cuBLAS)    F @ cov0 @ F^T of the splats' covariances (render/deform.py), forward + backward
    first svd (cuSOLVER)  torch.linalg.svd of (N, 3, 3) (render/deform.polar_rotation; SH degree > 0 only)
    import warp + init    Warp (and its CUDA driver init)
    warp modules          the simulator's modules loaded from the kernel cache (sim.kernels: core, adj, CUDA
                          defaults; the frame graphs'; the renderer's), each timed
    second conv2d / bmm   the same again (what every later call costs)

    python benchmarks/cuda_init_probe.py --device cuda [--json OUT/cuda_init.json]

Run it after a fit has filled Warp's kernel cache (benchmarks/gpu_cli26.sh does), else the module
loads include their compiles. On the CPU (`--device cpu`) the same steps run on the CPU: a smoke test.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--pixels", default="128x96", help="W x H of the SSIM's images (the sample's frames)")
    ap.add_argument("--gaussians", type=int, default=1500, help="splats in the covariance product (the sample's)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    rows = []
    t00 = time.perf_counter()

    def step(name, fn, sync=None):
        t = time.perf_counter()
        out = fn()
        if sync is not None:
            sync()
        rows.append((name, time.perf_counter() - t))
        return out

    torch = step("import torch", lambda: __import__("torch"))
    dev = torch.device(a.device)
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    step("torch context", lambda: torch.empty(1, device=dev), sync)
    step("first elementwise", lambda: (torch.ones(1000, device=dev) * 2 + 1).sum(), sync)
    W, H = (int(v) for v in a.pixels.lower().split("x"))
    import torch.nn.functional as Fnn

    def conv():
        x = torch.rand(1, 15, H, W, device=dev, requires_grad=True)
        g = torch.rand(11, device=dev)
        y = Fnn.conv2d(x, g.view(1, 1, 1, 11).expand(15, 1, 1, 11), groups=15)
        y = Fnn.conv2d(y, g.view(1, 1, 11, 1).expand(15, 1, 11, 1), groups=15)
        y.sum().backward()

    def bmm():
        F = torch.rand(a.gaussians, 3, 3, device=dev, requires_grad=True)
        c = torch.rand(a.gaussians, 3, 3, device=dev)
        (F @ c @ F.transpose(-1, -2)).sum().backward()

    step("first conv2d fwd+bwd (cuDNN)", conv, sync)
    step("first bmm fwd+bwd (cuBLAS)", bmm, sync)
    step("first svd (cuSOLVER)", lambda: torch.linalg.svd(torch.rand(a.gaussians, 3, 3, device=dev)), sync)
    wp = step("import warp", lambda: __import__("warp"))
    from physinteract_usd.devices import quiet_warp_init

    step("warp init", lambda: quiet_warp_init(a.device))
    from physinteract_usd.render.rasterizer import kernels as render_kernels
    from physinteract_usd.sim.frame_graphs import get_frame_kernels
    from physinteract_usd.sim.kernels import get_kernels

    K = step("sim kernels defined", lambda: get_kernels("float32"))
    get_frame_kernels("float32")
    R = render_kernels(wp.float32)
    for name in (K.modules.core, K.modules.adj, K.modules.cuda, "physinteract_framegraph_float32", R.module):
        step(f"load {name}", lambda n=name: wp.force_load(device=a.device, modules=[wp.get_module(n)], max_workers=0))
    step("second conv2d fwd+bwd", conv, sync)
    step("second bmm fwd+bwd", bmm, sync)
    total = time.perf_counter() - t00
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    print(f"fresh-process start-up costs on {name} (wall s, to a device sync)")
    print("| step | s |")
    print("|---|---:|")
    for n, s in rows:
        print(f"| {n} | {s:.3f} |")
    print(f"| **total** | {total:.3f} |")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"device": name, "steps": rows, "total_s": total}, indent=1))


if __name__ == "__main__":
    main()
