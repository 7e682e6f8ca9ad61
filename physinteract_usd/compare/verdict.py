"""The headline: does the model explain the video to its noise floor, and if not, from which frame
on and how it fails, in words.

A frame fails when its track error, with the tracker's bias removed (the video's tracks against
the same tracker's tracks on the model's rendered frames), exceeds `TRACK_FACTOR` times the
tracker's noise floor of that frame; or, where too few tracks were measured to say, when its
masked photometric error exceeds `PHOTO_FACTOR` times the photometric floor. How it fails is read from the failing frames: the
model's and the video's speeds (one keeps moving while the other settles), else the largest
component of the residual motion (along the motion, gravity or the contact normal)."""

from __future__ import annotations

import numpy as np

from .phases import phase_runs

TRACK_FACTOR = 3.0     # track error above 3x the tracker's noise: not noise
PHOTO_FACTOR = 4.0     # masked MSE above 4x (6 dB) the photometric floor
MIN_TRACKS = 5         # fewer valid tracks in a frame: judge it by its pixels


def frame_failures(track_error, track_floor, n_tracks, mse, mse_floor) -> tuple[np.ndarray, np.ndarray]:
    """(T,) bool failing frames and (T,) str what decided ('tracks' | 'pixels' | '')."""
    T = len(track_error)
    fail = np.zeros(T, bool)
    how = np.array([""] * T, dtype=object)
    for k in range(T):
        if n_tracks[k] >= MIN_TRACKS and np.isfinite(track_error[k]):
            how[k] = "tracks"
            fail[k] = track_error[k] > TRACK_FACTOR * track_floor[k]
        elif np.isfinite(mse[k]):
            how[k] = "pixels"
            fail[k] = mse[k] > PHOTO_FACTOR * mse_floor
    return fail, how


def _nanmean(a) -> float:
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def _runs_text(frames: list[int]) -> str:
    runs = []
    for k in frames:
        if runs and runs[-1][1] == k - 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def how_it_fails(fail: np.ndarray, model_speed, video_speed, track_floor, split: dict, iou=None) -> tuple[str, str]:
    """(reason code, words) for the failing frames."""
    F = np.where(fail)[0]
    sm, sv = _nanmean(np.asarray(model_speed, float)[F]), _nanmean(np.asarray(video_speed, float)[F])
    f = _nanmean(np.asarray(track_floor, float)[F])
    if np.isfinite(sm) and np.isfinite(sv):
        if sm > 2 * sv + f:
            if sv < 2 * f:
                return "model_keeps_moving", "the model keeps moving, the video settles"
            return "model_too_fast", f"the model moves faster than the video ({sm:.1f} vs {sv:.1f} px/frame)"
        if sv > 2 * sm + f:
            if sm < 2 * f:
                return "video_keeps_moving", "the video keeps moving, the model settles"
            return "model_too_slow", f"the model moves slower than the video ({sm:.1f} vs {sv:.1f} px/frame)"
    comps = {}
    for name in ("velocity", "gravity", "contact_normal"):
        vals = np.asarray(split.get(name, []), float)
        if vals.size:
            m = vals[F] if vals.ndim == 1 else vals[F].ravel()
            m = m[np.isfinite(m)]
            if m.size:
                comps[name] = float(np.mean(m))
    if comps:
        name = max(comps, key=lambda n: abs(comps[n]))
        mm = comps[name] * 1000
        if abs(mm) > 1e-6:
            words = {"velocity": ("the model moves too little along its motion (it lags the video)",
                                  "the model moves too far along its motion (it overshoots the video)"),
                     "gravity": ("the model sags too little (the video hangs lower)",
                                 "the model sags too much (the video hangs higher)"),
                     "contact_normal": ("the model stays inside the video's surface along the contact normal",
                                        "the model bulges out past the video's surface along the contact normal")}
            w = words[name][0 if mm > 0 else 1]
            return f"{name}_{'under' if mm > 0 else 'over'}", f"{w}: {abs(mm):.1f} mm on average"
    if iou is not None:
        return "silhouette", f"the silhouettes differ (IoU {_nanmean(np.asarray(iou, float)[F]):.2f})"
    return "unclear", "the error is above the noise floor"


def headline(fail: np.ndarray, phases: list[str], reason: str, *, track_error, debiased, track_floor,
             psnr_masked) -> dict:
    """{"verdict": "adequate" | "inadequate", "headline": str, "failing_frames", "first_failing_frame",
    "failing_phases"}."""
    T = len(fail)
    te = np.asarray(track_error, float)
    de = np.asarray(debiased, float)
    mean = lambda a: float(np.nanmean(a[1:])) if T > 1 and np.isfinite(a[1:]).any() else float("nan")  # noqa: E731
    err = f"track error {mean(te):.2f} px, {mean(de):.2f} px without the tracker's bias " \
          f"(noise floor {mean(np.asarray(track_floor, float)):.2f} px)"
    psnr = f"masked PSNR {np.nanmean(np.minimum(np.asarray(psnr_masked, float), 100)):.1f} dB"
    failing = [int(k) for k in np.where(fail)[0]]
    if not failing:
        return {"verdict": "adequate", "headline": f"explains the data to the noise floor: {err}; {psnr}",
                "failing_frames": [], "first_failing_frame": None, "failing_phases": []}
    first = failing[0]
    fphases = [p for p, a, b in phase_runs(phases) if any(a <= k <= b for k in failing)]
    fphases = list(dict.fromkeys(fphases))
    if all(fail[first:]):
        where = f"from frame {first} on"
    else:
        where = f"at frames {_runs_text(failing)}"
    ratio = np.where(np.isfinite(de[failing]), de[failing] / np.asarray(track_floor, float)[failing], -1.0)
    worst = int(failing[int(np.argmax(ratio))])
    text = f"inadequate {where} ({', '.join(fphases)}): {reason}; {err}, worst at frame {worst}"
    return {"verdict": "inadequate", "headline": text, "failing_frames": failing, "first_failing_frame": first,
            "failing_phases": fphases}
