"""The projected score test, as linear algebra (numpy only).

With r (n,) the residual of the fitted model (model minus data), J_b (n, p) its Jacobian columns
w.r.t. the base parameters (what the fit already adjusts: log E per region, nu, the trajectory's
low-rank basis) and j (n,) the column of a candidate parameter the model lacks:

    j_perp = j - J_b (J_b^+ j)               what the base parameters cannot absorb
    drop   = (r . j_perp)^2 / |j_perp|^2     the Gauss-Newton loss drop of fitting the candidate
                                             jointly with the base (loss = sum r^2)
    step   = -(r . j_perp) / |j_perp|^2      the candidate's Gauss-Newton step

A parameter bounded at its null (damping c >= 0) only gets the drop when its step points into its
domain (`sign=+1`: the step must be positive).

Significance (`block_signflip`): residuals are correlated in time and space, so the n terms
r_i u_i (u = j_perp / |j_perp|) are summed over blocks (a few consecutive frames x a tile of the
image) and the statistic (sum_b V_b)^2 is compared with its distribution under random sign flips
of the blocks (exact when few blocks, Monte Carlo otherwise): a randomisation test that assumes
only that blocks are independent and symmetric under the null, not that pixels are white.
Several probes of one candidate (a grid of yield stresses, three contact offsets) share the
flips, and the test uses their maximum, so probing more does not cry wolf more often.
"""

from __future__ import annotations

import itertools

import numpy as np


def project_out(J: np.ndarray | None, j: np.ndarray, ridge: float = 1e-10) -> np.ndarray:
    """j less its least-squares fit by the columns of J (columns scaled to unit norm; singular
    values below `ridge` of the largest are cut, so near-collinear base columns are harmless)."""
    j = np.asarray(j, np.float64)
    if J is None or J.size == 0:
        return j.copy()
    J = np.asarray(J, np.float64)
    if J.ndim == 1:
        J = J[:, None]
    norms = np.linalg.norm(J, axis=0)
    keep = norms > 1e-300
    if not keep.any():
        return j.copy()
    A = J[:, keep] / norms[keep]
    coef, *_ = np.linalg.lstsq(A, j, rcond=ridge)
    return j - A @ coef


def gauss_newton_drop(r: np.ndarray, j_perp: np.ndarray, sign: int = 0) -> tuple[float, float]:
    """(predicted drop of sum r^2, step) along j_perp; `sign` +1 / -1: the step must have that sign
    (a bounded parameter at its bound), else the drop is 0 and the step 0."""
    r = np.asarray(r, np.float64)
    nn = float(j_perp @ j_perp)
    if nn <= 1e-300:
        return 0.0, 0.0
    d = float(r @ j_perp)
    step = -d / nn
    if sign and step * sign <= 0:
        return 0.0, 0.0
    return d * d / nn, step


def discrete_drop(r: np.ndarray, j_perp: np.ndarray, sign: int = 0) -> tuple[float, float]:
    """(drop of sum r^2, Gauss-Newton step) for a probe that can only be taken whole: a discrete change
    (the grasp one frame later, the grasp one particle layer larger), whose smallest realisable
    amplitude is the probe itself. The drop is that of amplitude 1 (or -1 where `sign` is 0 and it is
    better), the base re-adjusted jointly: |P r|^2 - |P r + j_perp|^2 = |j_perp|^2 (2 t - 1), t the
    Gauss-Newton step; 0 when the probe itself does not lower the loss (t < 1/2: the residual asks for
    a fraction of the change, which no setting of the cause gives). The step is reported as is."""
    r = np.asarray(r, np.float64)
    nn = float(j_perp @ j_perp)
    if nn <= 1e-300:
        return 0.0, 0.0
    step = -float(r @ j_perp) / nn
    a = 1.0 if sign > 0 or (sign == 0 and step >= 0) else -1.0
    if sign < 0:
        a = -1.0
    drop = nn * (2.0 * step * a - 1.0)
    return (drop, step) if drop > 0 else (0.0, step)


ABSORBED = 1e-6   # |j_perp| / |j| below this: the base parameters absorb the candidate (round-off is left)


def predicted_drop(r: np.ndarray, J_base: np.ndarray | None, j: np.ndarray, sign: int = 0) -> tuple[float, float]:
    """`gauss_newton_drop` of the candidate column j after projecting out the base columns (0 when
    the base absorbs all but round-off of it)."""
    jp = project_out(J_base, j)
    if np.linalg.norm(jp) <= ABSORBED * np.linalg.norm(j):
        return 0.0, 0.0
    return gauss_newton_drop(r, jp, sign)


def joint_step(r: np.ndarray, J_base: np.ndarray | None, j: np.ndarray) -> tuple[np.ndarray, float]:
    """The joint Gauss-Newton step (base coefficients a, candidate step t) minimising
    |r + J_base a + j t|^2: t equals `gauss_newton_drop`'s step."""
    if J_base is None or J_base.size == 0:
        nn = float(j @ j)
        return np.zeros(0), (-float(r @ j) / nn if nn > 0 else 0.0)
    A = np.column_stack([J_base, j])
    sol, *_ = np.linalg.lstsq(A, -r, rcond=None)
    return sol[:-1], float(sol[-1])


def block_sums(values: np.ndarray, blocks: np.ndarray, n_blocks: int) -> np.ndarray:
    """Sum of `values` (n,) or (n, m) per block label (n,) -> (n_blocks,) or (n_blocks, m)."""
    values = np.asarray(values, np.float64)
    if values.ndim == 1:
        return np.bincount(blocks, weights=values, minlength=n_blocks)
    return np.stack([np.bincount(blocks, weights=values[:, c], minlength=n_blocks) for c in range(values.shape[1])], 1)


def one_sided_square(z: np.ndarray, signs: np.ndarray) -> np.ndarray:
    """z^2 where the step -z has the allowed sign (or any sign where signs == 0), else 0."""
    ok = (signs == 0) | (np.sign(-z) == np.sign(signs))
    return np.where(ok, z * z, 0.0)


def block_signflip(V: np.ndarray, signs=None, n_flips: int = 4000, seed: int = 0) -> tuple[float, float]:
    """(statistic, p-value) of the max over probes of the (one-sided) squared sum of block
    contributions V (B, m) against random sign flips of the blocks."""
    V = np.asarray(V, np.float64)
    if V.ndim == 1:
        V = V[:, None]
    V = V[np.abs(V).sum(1) > 0]
    m = V.shape[1]
    signs = np.zeros(m) if signs is None else np.asarray(signs, np.float64).reshape(m)
    B = len(V)
    if B == 0:
        return 0.0, 1.0
    obs = float(one_sided_square(V.sum(0), signs).max())
    if B <= 12:
        E = np.array(list(itertools.product((1.0, -1.0), repeat=B)))
    else:
        rng = np.random.default_rng(seed)
        E = rng.choice((1.0, -1.0), size=(n_flips, B))
    Z = E @ V                                      # (S, m)
    null = one_sided_square(Z, signs[None]).max(1)
    # the identity flip is one of the draws (exact enumeration holds it; add it to Monte Carlo)
    if B <= 12:
        p = float(np.mean(null >= obs * (1 - 1e-12)))
    else:
        p = float((1 + np.sum(null >= obs * (1 - 1e-12))) / (1 + len(null)))
    return obs, p


def paired_drop(r_ref: np.ndarray, r_new: np.ndarray, blocks: np.ndarray, n_blocks: int, *, n_flips: int = 4000,
                seed: int = 0) -> dict:
    """A one-sided paired test that `r_new` (the same elements as `r_ref`: held-back frames' residuals of
    two models) has a lower mean square than `r_ref`, with the threshold from the data's own spread.

    Per block b (a few frames x an image tile, as the score test's: blocks independent, whatever the
    correlation inside one) d_b = sum_{i in b} (r_ref_i^2 - r_new_i^2) / n: the drop D = sum_b d_b
    of the mean square. Under the null (no better, the blocks' differences symmetric about 0) every
    sign pattern of the d_b is as likely: p = P(sum_b e_b d_b >= D) over random signs e_b (exact for
    <= 12 blocks, else `n_flips` draws), and the drop's standard error is the same randomisation's,
    se = sqrt(sum_b d_b^2). Returns {"drop", "se", "p", "blocks" (those with a difference)}."""
    r_ref = np.asarray(r_ref, np.float64)
    r_new = np.asarray(r_new, np.float64)
    n = max(len(r_ref), 1)
    d = np.bincount(np.asarray(blocks, np.int64), weights=(r_ref * r_ref - r_new * r_new) / n, minlength=n_blocks)
    d = d[d != 0]
    D = float(d.sum())
    se = float(np.sqrt(np.sum(d * d)))
    B = len(d)
    if B == 0:
        return {"drop": D, "se": se, "p": 1.0, "blocks": 0}
    at = D - 1e-12 * abs(D) - 1e-300              # the observed sum itself counts (round-off aside)
    if B <= 12:
        E = np.array(list(itertools.product((1.0, -1.0), repeat=B)))
        p = float(np.mean(E @ d >= at))
    else:
        rng = np.random.default_rng(seed)
        null = rng.choice((1.0, -1.0), size=(n_flips, B)) @ d
        p = float((1 + np.sum(null >= at)) / (1 + n_flips))
    return {"drop": D, "se": se, "p": p, "blocks": int(B)}


__all__ = ["ABSORBED", "project_out", "gauss_newton_drop", "discrete_drop", "predicted_drop", "joint_step", "block_sums", "block_signflip",
           "one_sided_square", "paired_drop"]
