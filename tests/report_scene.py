"""A tiny scene for the report tests, with a known answer.

fit_scene's bar (a cantilever held at its left end by a fixed support) with a checkered texture
(trackable in both directions), seen at 64x48 px: the hand grasps the free end at frame 0, lifts it
over frames 0-4 and lets go at frame 5; the bar then swings back on its own until frame 9. The
frames are rendered by the package's own simulator and renderer at E = E_TRUE, so a model at
E_TRUE reproduces them (up to 8-bit rounding) and any other E does not. With `hidden_damping` the
video's bar is damped and the fit written is not (a missing effect: the model keeps swinging).

`build` writes the capture, the stage and a perfect fit (the truth written as fit version 1, with
its contacts and trajectory); `author_youngs` writes an E over the fitted field in the user's root
layer, as a user editing the stage by hand would.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd.camera import Camera
from physinteract_usd.frames import write_image, write_mask
from physinteract_usd.gaussians import Gaussians, write_ply

E_TRUE = fs.E_TRUE
N_FRAMES = 10
RELEASE = 5
WIDTH, HEIGHT = 64, 48


def gaussians(step=0.008, seed=0) -> Gaussians:
    """Small Gaussians on the bar's surface in a 2 cm checker (x against y and z)."""
    rng = np.random.default_rng(seed)
    lo, hi = fs.LO, fs.HI
    pts = []
    for axis in range(3):
        o = [a for a in range(3) if a != axis]
        u = np.arange(lo[o[0]], hi[o[0]] + 1e-9, step)
        v = np.arange(lo[o[1]], hi[o[1]] + 1e-9, step)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        for side in (lo[axis], hi[axis]):
            p = np.zeros((uu.size, 3))
            p[:, axis], p[:, o[0]], p[:, o[1]] = side, uu.ravel(), vv.ravel()
            pts.append(p)
    pts = np.unique(np.round(np.concatenate(pts), 6), axis=0)
    cell = np.floor((pts - lo) / 0.02).astype(int)
    odd = (cell.sum(1) % 2).astype(bool)
    col = np.where(odd[:, None], [0.95, 0.85, 0.25], [0.55, 0.1, 0.15]) + rng.normal(0, 0.02, (len(pts), 3))
    return Gaussians.from_colors(pts, np.clip(col, 0, 1), 0.6 * step, opacities=np.full(len(pts), 0.95))


def camera() -> Camera:
    centre = 0.5 * (fs.LO + fs.HI) + np.array([0.0, 0.0, 0.0])
    return Camera.look_at(centre + np.array([0.03, 0.05, 0.22]), centre, width=WIDTH, height=HEIGHT, fov_y_deg=45)


def contacts(sd):
    """The hand (grasping the free end from frame 0, released at RELEASE) and the support."""
    from physinteract_usd.contacts import ContactSet

    hand, support = fs._selections(sd.particles_positions)
    s = np.clip(np.arange(sd.n_frames) / (RELEASE - 1), 0.0, 1.0)
    s = s * s * (3 - 2 * s)
    traj = sd.particles_positions[hand].mean(0) + s[:, None] * np.array([0.0, 0.04, 0.0])
    return [ContactSet("hand", "pointAdherent", hand, 0, RELEASE, traj, source="groundTruth"),
            ContactSet("support", "fixed", support, source="groundTruth")]


def simulate(sd, specs, E, effects=None):
    """(x (T, P, 3), F, Gaussian means (T, N, 3), covariances (T, N, 3, 3)) at uniform E."""
    import torch

    from physinteract_usd.simulation import build_simulation

    sim = build_simulation(sd, specs, effects=effects)
    P = len(sd.particles_positions)
    with torch.no_grad():
        x, F = sim.simulate(torch.full((P,), float(E)), torch.full((P,), fs.NU_TRUE))
        mc = [sim.gaussians_at(x[k], F[k]) for k in range(sd.n_frames)]
    return (x.numpy(), F.numpy(), np.stack([m.numpy() for m, _ in mc]), np.stack([c.numpy() for _, c in mc]))


def render(sd, means, covs):
    import torch

    from physinteract_usd.render import render as rs

    g = sd.gaussians
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    rgb, sil = [], []
    with torch.no_grad():
        for k in range(len(means)):
            out = rs(t(means[k]), t(covs[k]), t(g.colors), t(g.opacities), sd.camera.at(k), background=t(fs.BACKGROUND))
            rgb.append(out["rgb"].numpy())
            sil.append(out["alpha"].numpy() > 0.5)
    return np.stack(rgb), np.stack(sil)


def perfect_fit(sd, specs, x, F, means, covs, frames):
    """The truth as a fit result (what a fit that found it would write)."""
    from physinteract_usd.fit import FitResult

    P, N = len(sd.particles_positions), len(sd.gaussians)
    fm = [{"frame": k, "psnr": 100.0, "psnr_masked": 100.0, "ssim": 1.0, "iou": 1.0} for k in range(len(frames))]
    return FitResult(youngs=np.full(P, E_TRUE), poisson=np.full(P, fs.NU_TRUE), confidence=np.ones(P),
                     trajectories={"hand": specs[0].trajectory}, positions=x, deformation=F, gaussian_means=means,
                     gaussian_covs=covs, youngs_gaussian=np.full(N, E_TRUE), poisson_gaussian=np.full(N, fs.NU_TRUE),
                     confidence_gaussian=np.ones(N), frame_metrics=fm, loss_history=[0.01, 0.001], final_loss=0.001,
                     runtime_s=1.0, device="cpu", settings={})


def build(root, *, hidden_damping: float = 0.0, n_frames: int = N_FRAMES) -> dict:
    """Capture folder + stage + the perfect fit. Returns paths and the truth. `hidden_damping` c
    [1/s]: the video's bar is damped, the fit written is the undamped truth (a missing effect)."""
    from physinteract_usd.usd.fit_io import write_fit_layer
    from physinteract_usd.usd.stage import read_stage

    root = Path(root)
    cap = root / "capture"
    (cap / "frames").mkdir(parents=True, exist_ok=True)
    (cap / "masks").mkdir(exist_ok=True)
    write_ply(gaussians(), cap / "object.ply")
    (cap / "transforms.json").write_text(json.dumps(camera().to_transforms_dict(fs.FPS)))
    blank = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    box = np.zeros((HEIGHT, WIDTH), bool)
    box[HEIGHT // 4: 3 * HEIGHT // 4, WIDTH // 4: 3 * WIDTH // 4] = True   # init refuses empty silhouettes
    for k in range(n_frames):      # placeholders: init needs their count and size
        write_image(cap / "frames" / f"{k:06d}.png", blank)
        write_mask(cap / "masks" / f"{k:06d}.png", box)
    stage = root / "scene.usda"
    api.init(stage, cap, grid=fs.GRID, padding=fs.PADDING, youngs_range=fs.E_RANGE, max_poisson=fs.MAX_POISSON,
             poisson=fs.NU_TRUE)
    sd = read_stage(stage)
    specs = contacts(sd)
    x, F, means, covs = simulate(sd, specs, E_TRUE)
    frames, sil = render(sd, means, covs)
    if hidden_damping:
        frames, sil = render(sd, *simulate(sd, specs, E_TRUE, {"damping": {"coefficient": hidden_damping}})[2:])
    for k in range(n_frames):
        write_image(cap / "frames" / f"{k:06d}.png", frames[k])
        write_mask(cap / "masks" / f"{k:06d}.png", sil[k])
    write_fit_layer(stage, sd, perfect_fit(sd, specs, x, F, means, covs, frames), specs)
    return {"root": root, "stage": stage, "frames": frames, "means": means, "specs": specs}


def author_youngs(stage, factor: float) -> None:
    """Write E = factor x the fitted field over it, in the user's root layer."""
    from pxr import Sdf, Usd, UsdGeom, Vt

    st = Usd.Stage.Open(str(stage))
    prim = st.GetPrimAtPath("/World/Object/SimParticles")
    e = np.asarray(prim.GetAttribute("primvars:physinteract:youngsModulus").Get(), np.float32)
    st.SetEditTarget(st.GetRootLayer())
    UsdGeom.PrimvarsAPI(prim).CreatePrimvar("physinteract:youngsModulus", Sdf.ValueTypeNames.FloatArray,
                                            UsdGeom.Tokens.vertex).Set(Vt.FloatArray.FromNumpy(e * factor))
    st.GetRootLayer().Save()
