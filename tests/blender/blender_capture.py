"""A tiny capture folder made with numpy and the standard library only (no physinteract_usd, no
cv2, no trimesh): Blender's venv has neither the project nor numpy>=2.

```
DIR/object.ply        3DGS binary PLY, INRIA layout (a sphere of flat Gaussians), or
DIR/object.obj        a mesh (an octahedron subdivided once), with mesh=True
DIR/frames/00000k.png RGB frames: the object's points splatted as pixels, moving a little
DIR/masks/00000k.png  8-bit silhouettes (255 = object)
DIR/transforms.json   nerfstudio camera: fl_x fl_y cx cy w h fps transform_matrix (camera-to-world,
                      OpenGL axes: looks along -Z, +Y up)
```
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814


def write_png(path, img: np.ndarray) -> None:
    """8-bit PNG, grey (H, W) or RGB (H, W, 3), with zlib + struct."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    h, w = img.shape[:2]
    colour = 0 if img.ndim == 2 else 2
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
                           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def write_gaussian_ply(path, means, scales, quats, opacities, f_dc) -> None:
    """Binary little-endian PLY in the INRIA 3DGS layout (opacity as logit, scale as log, rot w x y z)."""
    n = len(means)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.zeros((n, len(names)), np.float32)
    data[:, 0:3] = means
    data[:, 6:9] = f_dc
    data[:, 9] = np.log(opacities / (1.0 - opacities))
    data[:, 10:13] = np.log(scales)
    data[:, 13:17] = quats
    header = ("ply\nformat binary_little_endian 1.0\n" f"element vertex {n}\n"
              + "".join(f"property float {p}\n" for p in names) + "end_header\n")
    Path(path).write_bytes(header.encode("ascii") + data.astype("<f4").tobytes())


def sphere_gaussians(n=400, radius=0.1, centre=(0.0, 0.15, 0.0), seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = np.asarray(centre) + radius * d
    # local z along the normal: the rotation taking +z to d (w x y z)
    q = np.stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(n)], 1)
    q[d[:, 2] < -0.999999] = [0, 1, 0, 0]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = radius * np.sqrt(4.0 / n) * 1.3
    scales = np.tile([r, r, r * 0.1], (n, 1))
    f_dc = (np.array([0.8, 0.3, 0.2]) - 0.5) / SH_C0 + rng.normal(scale=0.1, size=(n, 3))
    opac = rng.uniform(0.6, 0.99, size=n)
    return means, scales, q, opac, f_dc


def octasphere(radius=0.1, centre=(0.0, 0.15, 0.0)):
    """An octahedron subdivided once and pushed onto a sphere: (vertices (V,3), faces (F,3))."""
    v = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    f = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5), (0, 3, 5)]
    verts = [np.array(p, float) for p in v]
    mid = {}

    def m(a, b):
        key = (min(a, b), max(a, b))
        if key not in mid:
            p = verts[a] + verts[b]
            verts.append(p / np.linalg.norm(p))
            mid[key] = len(verts) - 1
        return mid[key]

    faces = []
    for a, b, c in f:
        ab, bc, ca = m(a, b), m(b, c), m(c, a)
        faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    return np.asarray(centre) + radius * np.array(verts), np.array(faces)


def look_at_c2w(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """nerfstudio camera-to-world (OpenGL axes: the camera looks along -Z, +Y up)."""
    eye, target, up = (np.asarray(x, float) for x in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, back, eye
    return c2w


def project(points, c2w, fx, fy, cx, cy):
    """Pixel coordinates (continuous, pixel centres at +0.5) of world points."""
    w2c = np.linalg.inv(c2w)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    x, y, z = pc[:, 0], -pc[:, 1], -pc[:, 2]  # OpenGL -> OpenCV camera axes
    return np.stack([fx * x / z + cx, fy * y / z + cy], 1)


def make_capture(root, *, n_frames=3, width=48, height=36, fps=24.0, mesh=False, masks=True,
                 cx=None, cy=None) -> Path:
    root = Path(root)
    (root / "frames").mkdir(parents=True, exist_ok=True)
    if mesh:
        verts, faces = octasphere()
        (root / "object.obj").write_text(
            "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts)
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
        pts = verts
    else:
        means, scales, quats, opac, f_dc = sphere_gaussians()
        write_gaussian_ply(root / "object.ply", means, scales, quats, opac, f_dc)
        pts = means
    fy = fx = 0.5 * height / np.tan(np.radians(35.0) / 2)
    cx = width / 2.0 if cx is None else cx
    cy = height / 2.0 if cy is None else cy
    c2w = look_at_c2w((0.35, 0.3, 0.6), (0.0, 0.15, 0.0))
    if masks:
        (root / "masks").mkdir(exist_ok=True)
    for k in range(n_frames):
        uv = project(pts + [0.002 * k, 0.0, 0.0], c2w, fx, fy, cx, cy)
        ij = np.floor(uv).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < width) & (ij[:, 1] >= 0) & (ij[:, 1] < height)
        img = np.full((height, width, 3), 51, np.uint8)
        img[ij[ok, 1], ij[ok, 0]] = (204, 77, 51)
        write_png(root / "frames" / f"{k:06d}.png", img)
        if masks:
            m = np.zeros((height, width), np.uint8)
            m[ij[ok, 1], ij[ok, 0]] = 255
            write_png(root / "masks" / f"{k:06d}.png", m)
    tj = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": width, "h": height, "fps": fps,
          "camera_model": "OPENCV", "transform_matrix": c2w.tolist()}
    (root / "transforms.json").write_text(json.dumps(tj, indent=1))
    return root
