"""Shared helpers for the simulator tests (tests/test_sim_*.py): small scenes and FD checks."""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

wp.config.quiet = True


def block(n=(4, 4, 4), spacing=0.025, corner=(0.3, 0.12, 0.3)) -> np.ndarray:
    """A regular block of particles (n[0] x n[1] x n[2]) with its lower corner at ``corner``."""
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    return idx * spacing + np.asarray(corner) + 0.5 * spacing


def directional_check(loss_fn, args: list[torch.Tensor], scales: list[float], eps=1e-6, seed: int = 0):
    """Directional derivatives of loss_fn(*args) along a random direction per argument: (analytic, central FD).

    args are float64 leaf tensors; scales set each direction's magnitude (about the argument's size),
    eps the FD step along it (a float, or one per argument).
    """
    eps_list = list(eps) if isinstance(eps, (list, tuple)) else [eps] * len(args)
    gen = torch.Generator().manual_seed(seed)
    args = [a.detach().clone().requires_grad_(True) for a in args]
    L = loss_fn(*args)
    L.backward()
    out = []
    for i, (a, s, eps) in enumerate(zip(args, scales, eps_list)):
        d = torch.randn(a.shape, generator=gen, dtype=a.dtype) * s
        an = float((a.grad * d).sum())
        with torch.no_grad():
            ap = [b.detach().clone() for b in args]
            am = [b.detach().clone() for b in args]
            ap[i] = ap[i] + eps * d
            am[i] = am[i] - eps * d
            fd = float((loss_fn(*ap) - loss_fn(*am)) / (2 * eps))
        out.append((an, fd))
    return out


def rel_err(an: float, fd: float) -> float:
    return abs(an - fd) / max(abs(fd), 1e-300)
