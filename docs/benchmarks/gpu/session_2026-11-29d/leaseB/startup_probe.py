"""Where a CUDA fit's process start goes (#26): each step's seconds, in the order the CLI meets them."""
import time
T0 = time.perf_counter()
def lap(name, t=[T0]):
    now = time.perf_counter(); print(f"{name:40s} {now - t[0]:6.2f} s  (total {now - T0:6.2f})", flush=True); t[0] = now
import numpy as np; lap("import numpy")
import torch; lap("import torch")
x = torch.zeros(1, device="cuda"); torch.cuda.synchronize(); lap("torch CUDA context + first tensor")
import warp as wp; lap("import warp")
wp.init(); lap("wp.init()")
wp.zeros(1, device="cuda"); wp.synchronize(); lap("warp first CUDA array")
from pxr import Usd, UsdGeom; lap("import pxr")
import cv2; lap("import cv2")
import trimesh; lap("import trimesh")
import physinteract_usd.cli; lap("import physinteract_usd.cli")
from physinteract_usd.app import fit as appfit; lap("import physinteract_usd.app.fit")
from physinteract_usd.simulation import warm_kernels
t = time.perf_counter(); names = warm_kernels("cuda"); lap(f"warm_kernels('cuda') (cached: {len(names)} modules)")
