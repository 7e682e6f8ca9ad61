"""A tiny fit case with a known answer, for the fit / simulate / export tests.

A striped bar (cantilever) along x: its left end held by a fixed support, a hand grasping the free
end and lifting it while gravity bends the span between. The frames are rendered by the package's
own simulator and renderer from the very particles `init` fills the bar with, at a known uniform
E, so the fit's model can match them exactly (a consistent, "inverse crime" problem: what is
tested is the optimiser and the outputs, not the model's fidelity).

Everything is tiny (a ~200-particle bar, a 10-cell grid, 5 frames, 48x32 px) so a fit iteration
costs well under a second on one CPU core.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from physinteract_usd import api
from physinteract_usd.camera import Camera
from physinteract_usd.frames import write_image, write_mask
from physinteract_usd.gaussians import Gaussians, write_ply

E_TRUE = 5.0e3
NU_TRUE = 0.3
E_RANGE = (5e2, 5e4)
MAX_POISSON = 0.4
FPS = 24.0
N_FRAMES = 5
WIDTH, HEIGHT = 48, 32
GRID = 10
PADDING = 0.3

LENGTH, THICK = 0.16, 0.05
LO = np.array([-0.08, 0.125, -0.025])                 # the bar's lower corner
HI = LO + np.array([LENGTH, THICK, THICK])
MID_YZ = 0.5 * (LO[1:] + HI[1:])
SUPPORT_CENTRE = np.array([LO[0] - 0.02, *MID_YZ])    # particles within SUPPORT_RADIUS are held still
SUPPORT_RADIUS = 0.075
HAND_CENTRE = np.array([HI[0] + 0.01, *MID_YZ])       # particles within HAND_RADIUS follow the hand
HAND_RADIUS = 0.045
LIFT = np.array([0.0, 0.03, 0.0])                     # the hand's displacement over the clip
BACKGROUND = np.array([0.15, 0.2, 0.3], np.float32)


def bar_gaussians(step=0.01, seed=0) -> Gaussians:
    """Small isotropic Gaussians on the bar's surface, coloured in stripes along x."""
    rng = np.random.default_rng(seed)
    pts = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        u = np.arange(LO[others[0]], HI[others[0]] + 1e-9, step)
        v = np.arange(LO[others[1]], HI[others[1]] + 1e-9, step)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        for side in (LO[axis], HI[axis]):
            p = np.zeros((uu.size, 3))
            p[:, axis] = side
            p[:, others[0]] = uu.ravel()
            p[:, others[1]] = vv.ravel()
            pts.append(p)
    pts = np.unique(np.round(np.concatenate(pts), 6), axis=0)
    stripe = (np.floor((pts[:, 0] - LO[0]) / 0.02).astype(int) % 2).astype(bool)
    col = np.where(stripe[:, None], [0.9, 0.75, 0.2], [0.75, 0.15, 0.15]) + rng.normal(0, 0.02, (len(pts), 3))
    return Gaussians.from_colors(pts, np.clip(col, 0, 1), 0.6 * step, opacities=np.full(len(pts), 0.95))


def camera() -> Camera:
    centre = 0.5 * (LO + HI) + np.array([0.0, -0.01, 0.0])
    return Camera.look_at(centre + np.array([0.03, 0.05, 0.25]), centre, width=WIDTH, height=HEIGHT, fov_y_deg=40)


def contacts(sd, *, lift=LIFT, release=None):
    """The hand (pointAdherent, grasping the free end at frame 0, lifting it until `release`, or to
    the end when None) and the support (fixed)."""
    from physinteract_usd.contacts import ContactSet

    hand, support = _selections(sd.particles_positions)
    end = sd.n_frames - 1 if release is None else release
    s = np.clip(np.arange(sd.n_frames) / max(end, 1), 0.0, 1.0)
    s = s * s * (3 - 2 * s)
    traj = sd.particles_positions[hand].mean(0) + s[:, None] * np.asarray(lift, float)
    return [ContactSet("hand", "pointAdherent", hand, 0, release, traj),
            ContactSet("support", "fixed", support)]


def _selections(x0):
    hand = np.where(np.linalg.norm(x0 - HAND_CENTRE, axis=1) < HAND_RADIUS)[0]
    support = np.where(np.linalg.norm(x0 - SUPPORT_CENTRE, axis=1) < SUPPORT_RADIUS)[0]
    return hand, np.setdiff1d(support, hand)


def write_gt_json(gt_dir: Path, sd, hand_traj, release=None) -> None:
    """A minimal gt/gt.json that `fit --contact-from` reads: the same contacts as `contacts`."""
    gt = {"interaction": {"type": "pointAdherent", "trajectory": np.asarray(hand_traj).tolist(),
                          "contact_point": HAND_CENTRE.tolist(), "contact_radius": HAND_RADIUS,
                          "grasp_frame": 0, "release_frame": release},
          "supports": [{"centre": SUPPORT_CENTRE.tolist(), "radius": SUPPORT_RADIUS}]}
    gt_dir.mkdir(parents=True, exist_ok=True)
    (gt_dir / "gt.json").write_text(json.dumps(gt))


def render_truth(sd, contact_specs, E=None, nu=NU_TRUE):
    """Frames (T, H, W, 3), silhouettes (T, H, W) and particle positions (T, P, 3) at E (uniform, per particle, or a
    function of the rest positions)."""
    from physinteract_usd.fit import FitProblem, Observations
    from physinteract_usd.render import render

    T = sd.n_frames
    obs = Observations(frames=np.zeros((T, HEIGHT, WIDTH, 3), np.float32))
    prob = FitProblem(sd, obs, contact_specs, device="cpu")
    P = len(sd.particles_positions)
    bg = torch.as_tensor(BACKGROUND, dtype=prob.tdtype)
    frames, masks = [], []
    with torch.no_grad():
        e = E_TRUE if E is None else E
        e = e(np.asarray(sd.particles_positions, np.float64)) if callable(e) else e   # a field: E of the rest positions
        e = torch.as_tensor(np.broadcast_to(np.asarray(e, np.float64), (P,)).copy(), dtype=prob.tdtype)
        x, F = prob.simulate(e, torch.full((P,), float(nu), dtype=prob.tdtype))
        for k in range(T):
            means, covs = prob.gaussians_at(x[k], F[k])
            out = render(means, covs, prob.colors, prob.opacities, prob.cameras[k], background=bg)
            frames.append(out["rgb"].numpy())
            masks.append(out["alpha"].numpy() > 0.5)
    return np.stack(frames), np.stack(masks), x.numpy()


def build(root, *, E=None, name="scene", density=1000.0, n_frames=N_FRAMES, release=None, e_range=E_RANGE,
          lift=LIFT, grid=GRID, preload=False, stage_preload="same") -> dict:
    """Capture folder + stage for the bar, frames rendered at E (and `density`; the hand lets go at
    `release`, None: never; `preload`: the stage's init --preload, the truth rendered from the bar prestressed on its
    support; `stage_preload`: the stage's own setting afterwards where it differs, e.g. None: left to the fit).
    Returns paths and the truth."""
    root = Path(root)
    cap = root / "capture"
    (cap / "frames").mkdir(parents=True, exist_ok=True)
    (cap / "masks").mkdir(exist_ok=True)
    g = bar_gaussians()
    write_ply(g, cap / "object.ply")
    cam = camera()
    (cap / "transforms.json").write_text(json.dumps(cam.to_transforms_dict(FPS)))
    blank = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    box = np.zeros((HEIGHT, WIDTH), bool)
    box[HEIGHT // 4: 3 * HEIGHT // 4, WIDTH // 4: 3 * WIDTH // 4] = True   # init refuses empty silhouettes
    for k in range(n_frames):  # placeholders: init only needs their count and size
        write_image(cap / "frames" / f"{k:06d}.png", blank)
        write_mask(cap / "masks" / f"{k:06d}.png", box)
    stage = root / f"{name}.usda"
    api.init(stage, cap, grid=grid, padding=PADDING, youngs_range=e_range, max_poisson=MAX_POISSON,
             poisson=NU_TRUE, density=density, preload=preload)
    from physinteract_usd.usd.stage import read_stage

    sd = read_stage(stage)
    specs = contacts(sd, lift=lift, release=release)
    frames, masks, x = render_truth(sd, specs, E=E_TRUE if E is None else E)
    for k in range(n_frames):
        write_image(cap / "frames" / f"{k:06d}.png", frames[k])
        write_mask(cap / "masks" / f"{k:06d}.png", masks[k])
    write_gt_json(root / "gt", sd, specs[0].trajectory, release)
    if stage_preload != "same" and stage_preload is not preload:    # the truth as made, the stage as the test asks
        api.init(stage, cap, grid=grid, padding=PADDING, youngs_range=e_range, max_poisson=MAX_POISSON,
                 poisson=NU_TRUE, density=density, preload=stage_preload, force=True)
    return {"root": root, "capture": cap, "stage": stage, "gt": root / "gt", "positions": x,
            "hand": specs[0].indices, "support": specs[1].indices, "frames": frames, "masks": masks}


# Explicit fit settings for the tests (never the defaults, which are tuned for real scenes and may
# change): a two-level schedule so the confidence has a spatial basis, few iterations.
SMOKE_SETTINGS = dict(levels=(1, 6), level_share=(0.5, 0.5), search_evals=2, lr_material=0.2,
                      lr_poisson=0.03, lr_trajectory=2e-4, basis_width=0.6, trajectory_levels=1,
                      weight_decay=0.0, confidence_probes=4, fit_poisson_levels=1,
                      plateau_patience=0)   # every iteration runs (tests/test_converge.py tests the stop)
SMOKE_ITERATIONS = 8


def copy_scene(src_root, dst_root) -> Path:
    """A copy of a built scene folder (stage + capture + gt); returns the copied stage path."""
    import shutil

    shutil.copytree(src_root, dst_root)
    return Path(dst_root) / "scene.usda"


def settings_factory(**fixed):
    """A FitSettings stand-in whose fields not given by the caller are `fixed` (for the CLI,
    which passes only iterations, joint and seed)."""
    from physinteract_usd.fit import FitSettings

    def make(**kw):
        return FitSettings(**{**fixed, **kw})

    return make
