"""Tiny capture folders for tests: a Gaussian sphere (or a mesh), a few frames, a camera, masks.

The frames here are plain projections of the object's points (cv2), good enough for I/O tests;
the renderer's and synth's tests make real renders.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from physinteract_usd.camera import Camera
from physinteract_usd.frames import write_image, write_mask
from physinteract_usd.gaussians import Gaussians, write_ply


def sphere_gaussians(n=800, radius=0.1, centre=(0.0, 0.15, 0.0), seed=0, sh_degree=1) -> Gaussians:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = np.asarray(centre) + radius * d
    # flat Gaussians tangent to the sphere: local z along the normal
    z = np.array([0.0, 0.0, 1.0])
    q = np.stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(n)], 1)
    q[d[:, 2] < -0.999999] = [0, 1, 0, 0]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    del z
    r = radius * np.sqrt(4.0 / n) * 1.3
    scales = np.tile([r, r, r * 0.1], (n, 1))
    k = (sh_degree + 1) ** 2
    sh = rng.normal(scale=0.05, size=(n, k, 3))
    sh[:, 0] = (np.array([0.8, 0.3, 0.2]) - 0.5) / 0.28209479177387814 + rng.normal(scale=0.1, size=(n, 3))
    opac = rng.uniform(0.6, 0.99, size=n)
    return Gaussians(means, scales, q, opac, sh)


def default_camera(width=64, height=48) -> Camera:
    return Camera.look_at((0.35, 0.3, 0.6), (0.0, 0.15, 0.0), width=width, height=height, fov_y_deg=35)


def make_capture(root, *, n_frames=4, width=64, height=48, fps=24.0, masks=True, video=False,
                 fps_in_json=True, object_kind="gaussians", per_frame_camera=False) -> Path:
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    cam = default_camera(width, height)
    if object_kind == "gaussians":
        g = sphere_gaussians()
        write_ply(g, root / "object.ply")
        pts = g.means
    else:
        import trimesh

        mesh = trimesh.creation.icosphere(2, radius=0.1)
        mesh.apply_translation([0.0, 0.15, 0.0])
        mesh.visual.vertex_colors = np.tile([200, 80, 40, 255], (len(mesh.vertices), 1))
        mesh.export(root / f"object.{object_kind}")
        pts = mesh.vertices
    frames = []
    mks = []
    for k in range(n_frames):
        img = np.full((height, width, 3), 0.2, np.float32)
        uv, _ = cam.project(pts + np.array([0.002 * k, 0, 0]))
        m = np.zeros((height, width), bool)
        ij = np.floor(uv).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < width) & (ij[:, 1] >= 0) & (ij[:, 1] < height)
        img[ij[ok, 1], ij[ok, 0]] = (0.8, 0.3, 0.2)
        m[ij[ok, 1], ij[ok, 0]] = True
        frames.append(img)
        mks.append(m)
    if video:
        from physinteract_usd.frames import write_video

        write_video(root / "video.mp4", np.stack(frames), fps)
    else:
        (root / "frames").mkdir(exist_ok=True)
        for k, f in enumerate(frames):
            write_image(root / "frames" / f"{k:06d}.png", f)
    if masks:
        (root / "masks").mkdir(exist_ok=True)
        for k, m in enumerate(mks):
            write_mask(root / "masks" / f"{k:06d}.png", m)
    tj = cam.to_transforms_dict(fps if fps_in_json else None)
    if per_frame_camera:
        tj.pop("transform_matrix")
        tj["frames"] = [{"file_path": f"frames/{k:06d}.png", "transform_matrix": cam.c2w.tolist()}
                        for k in range(n_frames)]
    (root / "transforms.json").write_text(json.dumps(tj, indent=1))
    return root
