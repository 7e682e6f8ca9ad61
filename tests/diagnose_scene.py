"""Tiny scenes for the diagnosis tests and benchmark: report_scene's bar (held at its left end,
lifted by the hand at its free end over frames 0-4, released at frame 5, swinging until frame 9),
whose video has something the fitted model lacks.

`build(root, hidden=..., ...)` writes the capture, the stage and a fit (version 1) that is the
truth without what is hidden: the video is simulated with `hidden` effects ({effect: params}),
optionally with the true hand released `release_shift` frames later than the stage says, or
holding a grasp moved by `contact_offset` metres, and with Gaussian pixel noise `noise` (sigma,
like `synth --noise`); the stage's contacts and fitted animation are the base model's (no hidden
effect, the stage's timing and contact). A control is `build(root)` with noise only; `truth_split` > 1 simulates
the video on a grid that many times finer (`refine.refine_scene`), the stage's fit staying the coarse model.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

import report_scene as rs


def build(root, *, hidden: dict | None = None, noise: float = 0.0, seed: int = 0, release_shift: int = 0,
          contact_offset=None, truth_split: int = 1) -> dict:
    from physinteract_usd.frames import write_image, write_mask
    from physinteract_usd.usd.fit_io import write_fit_layer
    from physinteract_usd.usd.stage import read_stage

    root = Path(root)
    info = rs.build(root)                     # capture, stage, the perfect fit (overwritten below)
    stage, cap = info["stage"], root / "capture"
    sd = read_stage(stage)
    stage_specs = rs.contacts(sd)             # what the stage (and the fit) believe
    true_specs = list(stage_specs)
    if release_shift:
        h = true_specs[0]
        true_specs[0] = dataclasses.replace(h, release_frame=int(h.release_frame) + int(release_shift))
    if contact_offset is not None:
        from scipy.spatial import cKDTree

        h = true_specs[0]
        x0 = sd.particles_positions
        held = set(np.asarray(true_specs[1].indices).tolist())
        free = np.array([i for i in range(len(x0)) if i not in held])
        _, nn = cKDTree(x0[free]).query(x0[h.indices] + np.asarray(contact_offset))
        true_specs[0] = dataclasses.replace(h, indices=np.unique(free[nn]).astype(np.int64),
                                            trajectory=np.asarray(h.trajectory) + np.asarray(contact_offset))
    if truth_split > 1:
        # the video's truth on a grid `truth_split` times finer (as a real video is the continuum and the suite's
        # truths are finer than their fits): the same bar, E and hand path (refine.refine_scene)
        from physinteract_usd.refine import refine_scene

        fine_sd, fine_specs, _ = refine_scene(sd, truth_split, contacts=true_specs)
        _, _, tm, tc = rs.simulate(fine_sd, fine_specs, rs.E_TRUE, hidden)
    else:
        _, _, tm, tc = rs.simulate(sd, true_specs, rs.E_TRUE, hidden)
    frames, sil = rs.render(sd, tm, tc)
    if noise:
        rng = np.random.default_rng(seed)
        frames = np.clip(frames + rng.normal(scale=noise, size=frames.shape), 0, 1).astype(np.float32)
    for k in range(len(frames)):
        write_image(cap / "frames" / f"{k:06d}.png", frames[k])
        write_mask(cap / "masks" / f"{k:06d}.png", sil[k])
    if hidden or release_shift or contact_offset is not None or truth_split > 1:
        x, F, means, covs = rs.simulate(sd, stage_specs, rs.E_TRUE)
        lp = stage.with_suffix("").as_posix()
        for suffix in (".fit.usdc",):
            p = Path(lp + suffix)
            if p.exists():
                p.unlink()
        import shutil

        shutil.rmtree(Path(lp + ".versions"), ignore_errors=True)
        write_fit_layer(stage, read_stage(stage), rs.perfect_fit(sd, stage_specs, x, F, means, covs, frames),
                        stage_specs)
    return {"root": root, "stage": stage, "capture": cap, "specs": stage_specs, "true_specs": true_specs}
