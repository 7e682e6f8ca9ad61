"""Residual statistics in the manner of system identification's `resid`: whiteness (the
residuals' autocorrelation over time) and their correlation with the input (the interaction's
motion), with the 99% band of an uncorrelated series; and the per-particle residual map (each
simulation particle gets the residual of the tracked Gaussians nearest to it at rest)."""

from __future__ import annotations

import numpy as np

Z99 = 2.58


def nan_rms(a: np.ndarray, axis=0) -> np.ndarray:
    a = np.asarray(a, float)
    with np.errstate(invalid="ignore"):
        n = np.isfinite(a).sum(axis)
        s = np.nansum(a ** 2, axis)
        return np.where(n > 0, np.sqrt(s / np.maximum(n, 1)), np.nan)


def particle_map(values: np.ndarray, gaussian_rest: np.ndarray, particles_rest: np.ndarray, k: int = 4) -> np.ndarray:
    """(P,) per-particle values from per-Gaussian ones (n,) (nan: not measured): inverse-distance
    weights over the k nearest measured Gaussians at rest. All nan when none is measured."""
    from scipy.spatial import cKDTree

    values = np.asarray(values, float)
    ok = np.isfinite(values)
    P = len(particles_rest)
    if not ok.any():
        return np.full(P, np.nan)
    pts, vals = np.asarray(gaussian_rest, float)[ok], values[ok]
    k = min(k, len(vals))
    d, i = cKDTree(pts).query(np.asarray(particles_rest, float), k=k)
    if k == 1:
        d, i = d[:, None], i[:, None]
    w = 1.0 / np.maximum(d, 1e-6)
    return (w * vals[i]).sum(1) / w.sum(1)


def _band(n: int) -> float:
    return float(Z99 / np.sqrt(max(n, 1)))


def autocorrelation(res: np.ndarray, valid: np.ndarray, max_lag: int) -> dict:
    """Pooled normalised autocorrelation of residual series: res (T, n, d) (each track a series of
    d-vectors), valid (T, n). r(tau) = sum_i sum_t e_i(t).e_i(t + tau) / sum_i sum_t |e_i(t)|^2 over
    the pairs where both are valid. The band uses the number of frames (tracks are correlated in
    space, so pooling them buys no independence)."""
    e = np.where(valid[..., None], res, 0.0)
    T = len(e)
    max_lag = int(max(0, min(max_lag, T - 2)))
    den = float((e ** 2).sum())
    lags, r = list(range(max_lag + 1)), []
    for tau in lags:
        both = valid[: T - tau] & valid[tau:]
        num = float((e[: T - tau] * e[tau:] * both[..., None]).sum())
        r.append(num / den if den > 0 else 0.0)
    n_frames = int(valid.any(1).sum())
    band = _band(n_frames)
    return {"lags": lags, "r": r, "band": band, "frames": n_frames,
            "white": bool(all(abs(x) <= band for x in r[1:])) if len(r) > 1 else True}


def cross_correlation(e: np.ndarray, u: np.ndarray, max_lag: int) -> dict:
    """Normalised cross-correlation r(tau) = sum_t e(t) u(t - tau) / sqrt(sum e^2 sum u^2) of a
    residual series e (T,) with an input u (T,) (nan: left out), tau = -max_lag..max_lag (positive:
    the residual follows the input)."""
    e = np.asarray(e, float)
    u = np.asarray(u, float)
    ok = np.isfinite(e) & np.isfinite(u)
    e0 = np.where(ok, e - np.nanmean(np.where(ok, e, np.nan)) if ok.any() else 0.0, 0.0)
    u0 = np.where(ok, u - np.nanmean(np.where(ok, u, np.nan)) if ok.any() else 0.0, 0.0)
    T = len(e)
    max_lag = int(max(0, min(max_lag, T - 2)))
    den = float(np.sqrt((e0 ** 2).sum() * (u0 ** 2).sum()))
    lags = list(range(-max_lag, max_lag + 1))
    r = []
    for tau in lags:
        if tau >= 0:
            num = float((e0[tau:] * u0[: T - tau]).sum())
        else:
            num = float((e0[: T + tau] * u0[-tau:]).sum())
        r.append(num / den if den > 0 else 0.0)
    band = _band(int(ok.sum()))
    return {"lags": lags, "r": r, "band": band, "frames": int(ok.sum()),
            "uncorrelated": bool(all(abs(x) <= band for x in r))}
