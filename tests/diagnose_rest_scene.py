"""A tiny scene with frames before contact, for the camera-on-rest-frames rule (issue #22,
docs/diagnose.md "Camera causes on the rest frames").

report_scene's cantilever bar (held at its left end by a fixed support), 12 frames of 64x48 px: the
bar hangs and sags under gravity alone over frames 0-1 (the rest frames: no hand; frame 1 is the one in
the diagnosis's residual, which starts at frame 1), the hand grasps the free end at frame GRASP = 2 where
it hangs, lifts it over frames 2-6 and lets go at RELEASE = 7; it swings until frame 11. (The bar falls out
of its grid by frame 3 without the hand: two rest frames is what this bar allows.) The fitted model written on the stage is the truth without what is hidden (E_TRUE, the stage's
gravity, the stage's contacts); the video is simulated with:

- `gravity_scale`: the video's gravity x this (a depth-scale error: an object whose metric size is
  wrong by s looks, in the model's units, like gravity x s; `camera:depth_scale`'s probe);
- `hidden`: effects ({effect: params}) the model lacks;
- `floor`: a systematic error of the model that is no physics and no camera: the video's Gaussians
  `floor` x larger (softer edges in every frame) and its simulation at 4x the substeps (a finer model
  than the fit's: the discretisation error the tests' tiny bar's controls showed as depth scale);
- `noise`: Gaussian pixel noise (sigma), seed `seed`.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np

import report_scene as rs

N_FRAMES = 12
GRASP = 2
RELEASE = 7


def contacts(sd):
    """The hand (grasping the free end at GRASP, lifting until RELEASE - 1, released at RELEASE) and the
    support. The hand's path starts where the free end hangs at GRASP (the model's own, at E_TRUE)."""
    from physinteract_usd.contacts import ContactSet

    import fit_scene as fs

    hand, support = fs._selections(sd.particles_positions)
    T = sd.n_frames
    s = np.clip((np.arange(T) - GRASP) / (RELEASE - 1 - GRASP), 0.0, 1.0)
    s = s * s * (3 - 2 * s)
    sag = _hang(sd, support)[hand].mean(0)       # the free end's place at GRASP, hanging
    traj = sag + s[:, None] * np.array([0.0, 0.04, 0.0])
    return [ContactSet("hand", "pointAdherent", hand, GRASP, RELEASE, traj, source="groundTruth"),
            ContactSet("support", "fixed", support, source="groundTruth")]


_HANG = {}


def _hang(sd, support):
    """The particles at frame GRASP with only the support holding the bar (the model at E_TRUE)."""
    from physinteract_usd.contacts import ContactSet

    key = (len(sd.particles_positions), sd.n_frames)
    if key not in _HANG:
        specs = [ContactSet("support", "fixed", support, source="groundTruth")]
        x = simulate(sd, specs, rs.E_TRUE, n_frames=GRASP + 1)[0]
        _HANG[key] = x[GRASP]
    return _HANG[key]


def simulate(sd, specs, E, effects=None, *, gravity_scale: float = 1.0, substep_factor: float = 1.0,
             n_frames: int | None = None):
    """rs.simulate with the gravity scaled and the substeps x `substep_factor` (the adaptive step's
    stiffness bound x its square)."""
    import torch

    from physinteract_usd.simulation import build_simulation

    import fit_scene as fs

    if gravity_scale != 1.0:
        st = dataclasses.replace(sd.settings, gravity=tuple(float(g) * gravity_scale for g in sd.settings.gravity))
        sd = dataclasses.replace(sd, settings=st)
    T = sd.n_frames if n_frames is None else int(n_frames)
    sim = build_simulation(sd, specs, T, effects=effects)
    P = len(sd.particles_positions)
    if substep_factor != 1.0 and getattr(sim, "adaptive", False):
        sim._use_bound(sim.e_bound * substep_factor ** 2)
    with torch.no_grad():
        x, F = sim.simulate(torch.full((P,), float(E)), torch.full((P,), fs.NU_TRUE))
        mc = [sim.gaussians_at(x[k], F[k]) for k in range(T)]
    return (x.numpy(), F.numpy(), np.stack([m.numpy() for m, _ in mc]), np.stack([c.numpy() for _, c in mc]))


def build(root, *, gravity_scale: float = 1.0, hidden: dict | None = None, floor: float = 0.0, noise: float = 0.015,
          seed: int = 0) -> dict:
    from physinteract_usd.frames import write_image, write_mask
    from physinteract_usd.usd.fit_io import write_fit_layer
    from physinteract_usd.usd.stage import read_stage

    root = Path(root)
    info = rs.build(root, n_frames=N_FRAMES)       # capture, stage, a fit (overwritten below)
    stage, cap = info["stage"], root / "capture"
    sd = read_stage(stage)
    specs = contacts(sd)
    _, _, tm, tc = simulate(sd, specs, rs.E_TRUE, hidden, gravity_scale=gravity_scale,
                            substep_factor=4.0 if floor else 1.0)
    if floor:
        tc = tc * (1.0 + floor) ** 2
    frames, sil = rs.render(sd, tm, tc)
    if noise:
        rng = np.random.default_rng(seed)
        frames = np.clip(frames + rng.normal(scale=noise, size=frames.shape), 0, 1).astype(np.float32)
    for k in range(len(frames)):
        write_image(cap / "frames" / f"{k:06d}.png", frames[k])
        write_mask(cap / "masks" / f"{k:06d}.png", sil[k])
    x, F, means, covs = simulate(sd, specs, rs.E_TRUE)
    lp = stage.with_suffix("").as_posix()
    Path(lp + ".fit.usdc").unlink(missing_ok=True)
    shutil.rmtree(Path(lp + ".versions"), ignore_errors=True)
    write_fit_layer(stage, read_stage(stage), rs.perfect_fit(sd, specs, x, F, means, covs, frames), specs)
    return {"root": root, "stage": stage, "capture": cap, "specs": specs}
