"""End to end: a rendered frame of a stage matches its video frame.

A vertex-coloured mesh is ray-cast (trimesh, independent of the renderer) into a short "video"
in which it slides sideways; `init` builds a stage from that capture (mesh -> surface Gaussians,
camera through USD); the renderer draws the stage's Gaussians with the stage's camera over the
background estimated from the video, and frame 0 is compared with the video's frame 0.
Set PHYSINTERACT_RENDER_CHECK_DIR to keep the side-by-side PNG (video | render | 4x |diff|).
"""

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from physinteract_usd.camera import Camera


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _mesh():
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    b = trimesh.creation.box(extents=(0.12, 0.05, 0.12))
    b.apply_translation([0.0, -0.1, 0.0])
    m = trimesh.util.concatenate([a, b])
    m.apply_translation([0.0, 0.15, 0.0])
    v = m.vertices
    col = np.stack([0.5 + 0.45 * np.sin(40 * v[:, 1]), 0.5 + 0.45 * np.cos(25 * v[:, 0]),
                    0.55 + 0.4 * np.sin(20 * v[:, 2])], 1)
    m.visual.vertex_colors = np.concatenate([(col * 255).astype(np.uint8), np.full((len(v), 1), 255, np.uint8)], 1)
    return m


def _background(h, w):
    jj, ii = np.mgrid[0:h, 0:w]
    return np.stack([0.15 + 0.5 * ii / w, 0.25 + 0.3 * jj / h, np.full((h, w), 0.35)], -1)


def _raycast(mesh, cam: Camera, shift):
    """Per-pixel colour (barycentric vertex colours) and mask of the mesh moved by `shift`."""
    import trimesh

    m = mesh.copy()
    m.apply_translation(shift)
    H, W = cam.height, cam.width
    jj, ii = np.mgrid[0:H, 0:W]
    uv = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], 1)
    far = cam.unproject(uv, np.ones(len(uv)))
    o = np.repeat(cam.position[None], len(uv), 0)
    d = far - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    loc, ray, tri = m.ray.intersects_location(o, d, multiple_hits=False)
    img = _background(H, W).reshape(-1, 3).copy()
    mask = np.zeros(H * W, bool)
    bary = trimesh.triangles.points_to_barycentric(m.triangles[tri], loc)
    vc = m.visual.vertex_colors[:, :3].astype(np.float64) / 255.0
    img[ray] = np.einsum("nk,nkc->nc", bary, vc[m.faces[tri]])
    mask[ray] = True
    return img.reshape(H, W, 3).astype(np.float32), mask.reshape(H, W)


def test_stage_frame_matches_video_frame(tmp_path):
    pytest.importorskip("rtree")
    from physinteract_usd import api
    from physinteract_usd.frames import write_image, write_mask
    from physinteract_usd.render import estimate_background, render
    from physinteract_usd.usd.stage import read_stage

    W, H = 128, 96
    cam = Camera.look_at((0.3, 0.32, 0.55), (0.0, 0.12, 0.0), width=W, height=H, fov_y_deg=40)
    cam.cx += 3.0  # an off-centre principal point and non-square pixels: conventions show
    cam.fy *= 0.95
    mesh = _mesh()
    cap = tmp_path / "capture"
    (cap / "frames").mkdir(parents=True)
    (cap / "masks").mkdir()
    mesh.export(cap / "object.ply")
    frames, masks = [], []
    for k in range(4):
        img, m = _raycast(mesh, cam, [0.09 * k, 0.0, 0.0])
        write_image(cap / "frames" / f"{k:06d}.png", img)
        write_mask(cap / "masks" / f"{k:06d}.png", m)
        frames.append(img)
        masks.append(m)
    (cap / "transforms.json").write_text(json.dumps(cam.to_transforms_dict(fps=24.0)))
    stage = tmp_path / "scene.usda"
    api.init(stage, cap)
    sd = read_stage(stage)
    g = sd.gaussians
    scam = sd.camera.at(0)
    assert (scam.width, scam.height) == (W, H)

    bg = estimate_background(np.stack(frames), np.stack(masks), dilate=2)
    dt = torch.float32
    out = render(torch.tensor(g.means, dtype=dt), torch.tensor(g.covariances(), dtype=dt),
                 torch.tensor(g.sh, dtype=dt), torch.tensor(g.opacities, dtype=dt), scam,
                 background=torch.tensor(bg, dtype=dt))
    rgb = out["rgb"].numpy()
    video = frames[0]
    sil = out["alpha"].numpy() > 0.5
    iou = (sil & masks[0]).sum() / (sil | masks[0]).sum()
    mse = float(((rgb - video) ** 2).mean())
    psnr = -10 * np.log10(mse)
    inside = masks[0] & sil
    err_inside = float(np.abs(rgb - video)[inside].mean())

    panel = np.concatenate([video, rgb.clip(0, 1), np.clip(4 * np.abs(rgb - video), 0, 1)], 1)
    from physinteract_usd.frames import write_image as wi

    wi(tmp_path / "stage_frame0.png", panel)
    keep = os.environ.get("PHYSINTERACT_RENDER_CHECK_DIR")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        wi(Path(keep) / "stage_frame0.png", panel)
        (Path(keep) / "stage_frame0.json").write_text(json.dumps(
            {"iou": float(iou), "psnr": psnr, "mean_abs_err_inside": err_inside, "gaussians": len(g)}))
    # surfels of radius 1.2 x the sampling spacing thicken the outline by about a pixel (IoU ~0.9 at
    # this size); the silhouette's centre must not move: the camera conventions agree
    jj, ii = np.mgrid[0:H, 0:W]
    c_r = np.array([ii[sil].mean(), jj[sil].mean()])
    c_v = np.array([ii[masks[0]].mean(), jj[masks[0]].mean()])
    shift = float(np.abs(c_r - c_v).max())
    if keep:
        (Path(keep) / "stage_frame0_centroid_shift_px.txt").write_text(f"{shift}\n")
    assert shift < 0.25, shift
    assert iou > 0.85, iou
    assert psnr > 25.0, psnr
    assert err_inside < 0.05, err_inside
    # the background where the object never was is the video's
    free = ~np.any(np.stack(masks), 0)
    assert np.abs(rgb[free & (out["alpha"].numpy() < 1e-3)] - video[free & (out["alpha"].numpy() < 1e-3)]).max() < 0.01
