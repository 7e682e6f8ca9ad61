"""What the video can see of a particle's E (#24): its strain exposure over a rollout, and the particles
whose E it cannot see (held by a support, or barely strained). Used by the confidence
(`optimize.confidence`) and by the unconstrained fill (`select.fill_unconstrained`); numpy and torch only."""

from __future__ import annotations

import numpy as np
import torch


def exposure_of_rollout(F, frames) -> np.ndarray | None:
    """`select.strain_exposure` of a rollout's deformation gradients F (per frame (P, 3, 3)) over `frames`."""
    Fs = torch.stack([F[k] for k in frames]).detach().to("cpu", torch.float64).numpy()
    sv = np.linalg.svd(Fs, compute_uv=False)
    h2 = (np.log(np.clip(sv, 1e-6, None)) ** 2).sum(-1)           # (frames, P)
    out = h2.mean(0)
    return out if np.isfinite(out).all() else None


# a particle is "unconstrained" when its strain exposure is below this share of the object's median
# (mean square strain: a tenth of the median is a third of its RMS strain); chosen before measuring,
# not fitted (`fit_select(exposure_floor=...)`, benchmarks; `FitSettings.unconstrained_floor`)
EXPOSURE_FLOOR = 0.1


def unconstrained_particles(exposure: np.ndarray, held: np.ndarray, floor: float = EXPOSURE_FLOOR) -> np.ndarray:
    """The particles whose E the video does not constrain (P,) bool: the held ones (a support moves
    them whatever their E) and the free ones whose strain exposure is below `floor` x the free
    particles' median. The rule: a particle's E enters the motion through its stress, E times its
    strain, so a particle that barely strains moves the picture by the same amount whatever its E;
    the floor is relative (to this object's median over this clip), not a number of Pa or pixels."""
    held = np.asarray(held, bool)
    e = np.asarray(exposure, np.float64)
    free = ~held & np.isfinite(e)
    if not free.any():
        return held.copy()
    return held | (free & (e < float(floor) * float(np.median(e[free]))))
