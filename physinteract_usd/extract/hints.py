"""The user's hints (`result.Hint`): parsed from the CLI's flags (`parse_hint`), checked against
the stage and the video (`check_hint`), and placed in the image (`hint_location`)."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .analysis import Analysis
from .geometry import sample
from .result import Hint
from .segmentation import dilate


# ------------------------------------------------------------------------------ parsing
def parse_pixel(text: str, flag: str) -> tuple[int, tuple[float, float]]:
    """`K,U,V` (frame, column, row as an image viewer shows them, 0-based) -> (K, pixel centre)."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise InputError(flag, f"expected K,U,V (frame, column, row), got {text!r}")
    try:
        k = int(parts[0])
        u, v = float(parts[1]), float(parts[2])
    except ValueError:
        raise InputError(flag, f"expected an integer frame and two numbers, got {text!r}") from None
    if not (np.isfinite(u) and np.isfinite(v)):
        raise InputError(flag, f"pixel coordinates must be finite, got {text!r}")
    return k, (u + 0.5, v + 0.5)


def parse_indices(text: str, flag: str) -> np.ndarray:
    """`I,J,...` -> particle indices (int64)."""
    try:
        idx = [int(p) for p in str(text).replace(" ", "").split(",") if p != ""]
    except ValueError:
        raise InputError(flag, f"expected comma-separated particle indices, got {text!r}") from None
    if not idx:
        raise InputError(flag, "no particle index given")
    return np.asarray(idx, np.int64)


def parse_frame(text, flag: str, never_ok: bool = False) -> int:
    """A frame number (`never` / `none` for a release that never comes, with `never_ok`)."""
    t = str(text).strip().lower()
    if never_ok and t in ("never", "none"):
        return Hint.NEVER
    try:
        k = int(t)
    except ValueError:
        what = "a frame number or 'never'" if never_ok else "a frame number"
        raise InputError(flag, f"expected {what}, got {text!r}") from None
    if k < 0:
        raise InputError(flag, f"frame must be >= 0, got {k}")
    return k


def parse_hint(pixel: str | None = None, particles: str | None = None, support_pixels=None,
               support_particles: str | None = None, grasp_radius: float | None = None,
               grasp_frame=None, release_frame=None) -> Hint | None:
    """The CLI's hint flags: `--hint-pixel K,U,V` (frame K, pixel column U and row V as an image
    viewer shows them, 0-based; the pixel's centre is used), `--hint-particles I,J,...`
    (SimParticles indices), `--support-pixel K,U,V` (a list: where the object is held) and
    `--support-particles I,J,...`, `--grasp-radius R` (metres), `--grasp-frame K` and
    `--release-frame K` (or `never`). None when none is given; InputError naming the flag
    otherwise."""
    if isinstance(support_pixels, str):
        support_pixels = [support_pixels]
    if (pixel is None and particles is None and not support_pixels and support_particles is None
            and grasp_radius is None and grasp_frame is None and release_frame is None):
        return None
    hint = Hint()
    if grasp_frame is not None:
        hint.grasp_frame = parse_frame(grasp_frame, "--grasp-frame")
    if release_frame is not None:
        hint.release_frame = parse_frame(release_frame, "--release-frame", never_ok=True)
    if grasp_radius is not None:
        r = float(grasp_radius)
        if not np.isfinite(r) or r <= 0:
            raise InputError("--grasp-radius", f"must be a positive length in metres, got {grasp_radius}")
        hint.grasp_radius = r
    if pixel is not None:
        hint.frame, hint.pixel = parse_pixel(pixel, "--hint-pixel")
    if particles is not None:
        hint.particles = parse_indices(particles, "--hint-particles")
    if support_pixels:
        hint.support_pixels = [parse_pixel(t, "--support-pixel") for t in support_pixels]
    if support_particles is not None:
        hint.support_particles = parse_indices(support_particles, "--support-particles")
    return hint


# ------------------------------------------------------------------------------ checks
def check_pixel(k, uv, scene, T, flag):
    """InputError naming `flag` when frame k is outside the video or pixel uv outside the frame."""
    if not (0 <= int(k) < T):
        raise InputError(flag, f"frame {k} is outside the video (0..{T - 1})")
    u, v = map(float, uv)
    W, H = scene.camera.width, scene.camera.height
    if not (0 <= u < W and 0 <= v < H):
        raise InputError(flag, f"pixel ({u - 0.5:g}, {v - 0.5:g}) is outside the {W}x{H} frame")


def check_hint(hint, scene, T):
    """The hint checked against the stage (particle count, the object's extent) and a video of T
    frames; particle indices sorted and made unique. InputError naming the flag otherwise."""
    if hint is None:
        return hint
    P = len(scene.particles_positions)
    if hint.support_particles is not None and len(hint.support_particles):
        idx = np.asarray(hint.support_particles)
        if not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= P:
            raise InputError("--support-particles", f"particle indices must be integers in [0, {P}) (the stage "
                             f"has {P} simulation particles)")
        hint.support_particles = np.unique(idx.astype(np.int64))
    for k, uv in hint.support_pixels or []:
        check_pixel(k, uv, scene, T, "--support-pixel")
    if hint.grasp_radius is not None:
        ext = float(np.max(np.ptp(np.asarray(scene.particles_positions, float), axis=0)))
        if not 0 < hint.grasp_radius <= ext:  # nan fails the comparison too
            raise InputError("--grasp-radius", f"must be a length in metres in (0, {ext:.3g}] (the object's "
                             f"extent), got {hint.grasp_radius}")
    check_timing(hint, T)
    if hint.is_empty:
        return hint
    if hint.particles is not None and len(hint.particles):
        idx = np.asarray(hint.particles)
        if not np.issubdtype(idx.dtype, np.integer):
            raise InputError("--hint-particles", "particle indices must be integers")
        if idx.min() < 0 or idx.max() >= P:
            raise InputError("--hint-particles", f"particle indices must lie in [0, {P}) (the stage has {P} "
                             "simulation particles)")
        hint.particles = np.unique(idx.astype(np.int64))
    if hint.pixel is not None:
        k = 0 if hint.frame is None else hint.frame
        check_pixel(k, hint.pixel, scene, T, "--hint-pixel")
        hint.frame = int(k)
    return hint


def check_timing(hint, T):
    """The user's grasp and release frames inside the video, the release after the grasp."""
    g, r = hint.grasp_frame, hint.release_frame
    if g is not None and not (0 <= int(g) < T - 1):
        raise InputError("--grasp-frame", f"frame {g} is outside the video's first {T - 1} frames (0..{T - 2}: "
                         "the hand must hold on for at least one frame)")
    if r is not None and r != Hint.NEVER:
        if not (0 < int(r) < T):
            raise InputError("--release-frame", f"frame {r} is outside the video (1..{T - 1}; 'never' for a hand "
                             "that holds on to the end)")
        if g is not None and int(r) <= int(g):
            raise InputError("--release-frame", f"frame {r} is not after the grasp frame {g}")


def hint_location(an: Analysis, hint):
    """(2D location, particle indices, frame) of the hint; Nones without one."""
    if hint is None or hint.is_empty:
        return None, None, None
    if hint.particles is not None and len(hint.particles):
        uv, _ = an.cam0.project(an.x0[hint.particles].mean(0)[None])
        return uv[0], hint.particles, hint.frame
    c = np.asarray(hint.pixel, np.float64)
    k = hint.frame
    on_obj = dilate(an.obj[k] | an.rest.silhouette | an.hand[k], max(2, int(round(an.R))))
    if not sample(on_obj.astype(np.float32), c[None], order=0)[0]:
        raise InputError("--hint-pixel", f"pixel ({c[0]:g}, {c[1]:g}) in frame {k} is not on or next to the "
                         "object")
    return c, None, k
