"""Stages with fit versions, made fast: `fake_fit` writes a version through the real writer
(`usd.fit_io.write_fit_layer`) from a FitResult built by hand (a uniform field, the rest pose as
its animation), so the version logic is tested without running the optimiser. Also: file hashes
for "nothing the user authored changed", and a folder root cannot write into."""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
from pathlib import Path

import numpy as np


def fake_result(sd, E: float, *, loss: float, interrupted: bool = False, history=None, effects=None):
    from physinteract_usd.fit import FitResult

    P, T = len(sd.particles_positions), sd.n_frames
    g = sd.gaussians
    N = len(g)
    covs = g.covariances()
    fm = [{"frame": k, "psnr": 30.0 + k, "psnr_masked": 25.0 + k, "ssim": 0.9, "iou": 0.8} for k in range(T)]
    return FitResult(
        youngs=np.full(P, E), poisson=np.full(P, 0.3), confidence=np.full(P, 0.5), trajectories={},
        positions=np.repeat(sd.particles_positions[None], T, 0), deformation=np.tile(np.eye(3), (T, P, 1, 1)),
        gaussian_means=np.repeat(g.means[None], T, 0), gaussian_covs=np.repeat(covs[None], T, 0),
        youngs_gaussian=np.full(N, E), poisson_gaussian=np.full(N, 0.3), confidence_gaussian=np.full(N, 0.5),
        frame_metrics=fm, loss_history=list(history or [loss * 1.5, loss]), final_loss=loss, runtime_s=1.0,
        device="cpu (test)", settings={"iterations": 2}, effects=dict(effects or {}), interrupted=interrupted)


def fake_fit(stage, E: float, *, loss: float, interrupted: bool = False, keep_best: bool = True, contacts=(),
             trajectories=None, shift=0.0):
    """Write a version of uniform E with final loss `loss` (its animation: the rest pose moved up
    by `shift` metres from frame 1 on); returns write_fit_layer's dict."""
    from physinteract_usd.usd.fit_io import write_fit_layer
    from physinteract_usd.usd.stage import read_stage

    sd = read_stage(stage)
    r = fake_result(sd, E, loss=loss, interrupted=interrupted)
    r.positions[1:, :, 1] += shift
    r.gaussian_means[1:, :, 1] += shift
    r.trajectories = dict(trajectories or {})
    return write_fit_layer(stage, sd, r, list(contacts), keep_best=keep_best)


def tree_md5(folder) -> dict:
    """{relative path: md5} of every file under `folder` (names and contents)."""
    folder = Path(folder)
    return {str(p.relative_to(folder)): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@contextlib.contextmanager
def unwritable(folder):
    """`folder` made unwritable for this process (chattr +i for root, chmod otherwise); yields
    False when neither works here (the caller skips)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    how = None
    if os.geteuid() == 0:
        if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0:
            how = "chattr"
    else:
        folder.chmod(0o555)
        how = "chmod"
    probe = folder / ".probe"
    try:
        probe.touch()
        probe.unlink()
        ok = False
    except OSError:
        ok = True
    try:
        yield ok
    finally:
        if how == "chattr":
            subprocess.run(["chattr", "-i", str(folder)], capture_output=True)
        elif how == "chmod":
            folder.chmod(0o755)
