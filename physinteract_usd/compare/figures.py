"""What the report shows: side-by-side frames (video | model | error heat map with the track
residuals drawn on it) as images, and the plots (matplotlib, as PNG bytes): per-frame metrics
against the noise floor shaded by phase, the residual motion split, whiteness and correlation with
the input, where on the object the residual is, and the error across fit versions."""

from __future__ import annotations

import io

import numpy as np

from .phases import PHASE_COLORS, PHASES, phase_runs

HEAT_MIN = 0.1   # the heat map's scale: at least 0.1 (of the [0, 1] colour range)


def _u8(img) -> np.ndarray:
    return np.clip(np.asarray(img, np.float32) * 255 + 0.5, 0, 255).astype(np.uint8)


def heat_scale(comparison, frames) -> float:
    err = np.abs(comparison.renders["rgb"] - np.asarray(frames[: len(comparison.renders["rgb"])], np.float32)).mean(-1)
    return float(max(HEAT_MIN, np.percentile(err, 99.5)))


def side_by_side(comparison, frames, hand_masks, k: int, *, vmax: float, min_height: int = 240,
                 max_arrows: int = 150) -> np.ndarray:
    """(H', 3 W', 3) uint8 RGB: video | model | |error| (inferno, 0..vmax; the hand grey) with the
    track residuals drawn on it (green, from the model's point: the video's track minus the model
    video's track, i.e. without the tracker's bias), a header naming frame, phase and errors."""
    import cv2

    video = np.asarray(frames[k], np.float32)
    model = comparison.renders["rgb"][k]
    H, W = video.shape[:2]
    s = max(1, int(np.ceil(min_height / H)))
    err = np.abs(model - video).mean(-1) / vmax
    heat = cv2.applyColorMap(_u8(np.clip(err, 0, 1)), cv2.COLORMAP_INFERNO)[:, :, ::-1].copy()
    if hand_masks is not None:
        heat[np.asarray(hand_masks[k], bool)] = (110, 110, 110)
    up = lambda a: cv2.resize(a, (W * s, H * s), interpolation=cv2.INTER_NEAREST)  # noqa: E731
    panels = [up(_u8(video)), up(_u8(model)), up(heat)]
    tr = comparison.tracks
    if tr:
        # the residual the verdict judges (video's track minus the model video's track: the tracker's
        # bias removed), drawn from the model's point
        v = np.where(tr["both"][k])[0]
        if len(v) > max_arrows:
            v = v[np.linspace(0, len(v) - 1, max_arrows).astype(int)]
        for i in v:
            a = tr["model_uv"][k][i]
            b = a + tr["measured_uv"][k][i] - tr["model_video_uv"][k][i]
            a, b = (tuple(int(round(c * s)) for c in p) for p in (a, b))
            cv2.line(panels[2], a, b, (60, 255, 60), 1, cv2.LINE_AA)
            cv2.circle(panels[2], b, 1, (60, 255, 60), -1)
    body = np.concatenate(panels, axis=1)
    d = comparison.frames[k]
    bar = np.full((22, body.shape[1], 3), 255, np.uint8)
    colour = tuple(int(PHASE_COLORS[d["phase"]][i:i + 2], 16) for i in (1, 3, 5))
    bar[:, :8] = colour
    te = d.get("track_error_px")
    de = d.get("track_error_debiased_px")
    text = (f"frame {k}  {d['phase']}  PSNR {d['psnr_masked']:.1f} dB (masked)  IoU {d['iou']:.2f}" +
            (f"  track {te:.2f} px" if te is not None else "") +
            (f" ({de:.2f} px without the tracker's bias)" if de is not None else "") + ("  FAILS" if d.get("fails") else ""))
    cv2.putText(bar, text, (12, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for j, name in enumerate(("video", "model", f"error 0-{vmax:.2f}, track residuals")):
        (tw, th), _ = cv2.getTextSize(name, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
        x0, y0 = j * W * s, H * s
        body[y0 - th - 8: y0, x0: x0 + tw + 8] = 0
        cv2.putText(body, name, (x0 + 4, y0 - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([bar, body], axis=0)


def png_bytes(rgb_u8: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb_u8[:, :, ::-1]))
    if not ok:
        raise RuntimeError("could not encode a PNG")
    return buf.tobytes()


# ---------------------------------------------------------------------------------- plots
def _fig_png(fig) -> bytes:
    import matplotlib.pyplot as plt

    bio = io.BytesIO()
    fig.savefig(bio, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return bio.getvalue()


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _shade(ax, phases, legend=False):
    for p, a, b in phase_runs(phases):
        ax.axvspan(a - 0.5, b + 0.5, color=PHASE_COLORS[p], alpha=0.35, lw=0, label=p if legend else None)


def _fails(ax, comparison):
    for d in comparison.frames:
        if d.get("fails"):
            ax.axvline(d["frame"], color="#cb181d", lw=0.8, alpha=0.6)


def plot_metrics(comparison) -> bytes:
    """Per frame: PSNR (full, masked) with the floor; SSIM and IoU; track error with the tracker's
    floor (and 3x it, the failing line); phases shaded, failing frames marked."""
    plt = _plt()
    fr = comparison.frames
    k = [d["frame"] for d in fr]
    g = lambda key: [np.nan if d.get(key) is None else d[key] for d in fr]  # noqa: E731
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    out = dict(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax = axes[0]
    _shade(ax, comparison.phases, legend=True)
    ax.plot(k, g("psnr"), "o-", color="#2171b5", label="PSNR")
    ax.plot(k, g("psnr_masked"), "s-", color="#08306b", label="PSNR (masked)")
    ax.axhline(comparison.floor.psnr_floor, ls="--", color="k", lw=1, label="noise floor (masked)")
    ax.set_ylabel("dB")
    ax.legend(**out)
    ax = axes[1]
    _shade(ax, comparison.phases)
    ax.plot(k, g("ssim"), "o-", color="#238b45", label="SSIM")
    ax.plot(k, g("iou"), "s-", color="#6a51a3", label="silhouette IoU")
    ax.set_ylim(min(0.5, np.nanmin(g("iou") + g("ssim")) - 0.05), 1.02)
    ax.legend(**out)
    ax = axes[2]
    _shade(ax, comparison.phases)
    _fails(ax, comparison)
    from .verdict import TRACK_FACTOR

    ax.plot(k, g("track_error_px"), "o-", color="#fc9272", label="track error (video vs model's Gaussians)")
    ax.plot(k, g("tracker_bias_px"), "x--", color="#969696", label="tracker bias (its error on the model's frames)")
    ax.plot(k, g("track_error_debiased_px"), "o-", color="#a50f15", lw=2, label="track error without the bias (judged)")
    ax.plot(k, comparison.floor.track_px, "--", color="k", lw=1, label="tracker noise floor")
    ax.plot(k, TRACK_FACTOR * comparison.floor.track_px, ":", color="k", lw=1.2,
            label=f"{TRACK_FACTOR:g} x floor: a frame fails above")
    ax.set_ylabel("px")
    ax.set_xlabel("frame")
    ax.legend(**out)
    return _fig_png(fig)


def plot_split(comparison) -> bytes:
    """Mean signed residual motion per frame (video minus model, mm) along the model's velocity,
    gravity and the contact normal, with its total size."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3))
    _shade(ax, comparison.phases)
    _fails(ax, comparison)
    T = len(comparison.frames)
    for name, style in (("velocity", "o-"), ("gravity", "s-"), ("contact_normal", "^-"), ("total", "k--")):
        y = [np.nan if v is None else v * 1000 for v in comparison.split.get(name, [None] * T)]
        ax.plot(range(T), y, style, label=name.replace("_", " ") + (" (mean |r|)" if name == "total" else ""), ms=4)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("frame")
    ax.set_ylabel("residual motion (mm)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _fig_png(fig)


def plot_whiteness(comparison) -> bytes:
    """Autocorrelation of the residual motion (whiteness) and its cross-correlation with the
    hand's motion, each with the 99% band of an uncorrelated series (as `resid` draws them)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(8, 2.8))
    for ax, d, title in ((axes[0], comparison.whiteness, "residual autocorrelation"),
                         (axes[1], comparison.input_correlation, "residual vs hand motion")):
        ax.axhspan(-d["band"], d["band"], color="#c6dbef", alpha=0.6, label="99% band")
        ax.stem(d["lags"], d["r"], basefmt=" ")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("lag (frames)")
        ax.set_ylim(-1.05, 1.05)
    axes[0].legend(fontsize=7)
    return _fig_png(fig)


def plot_residual_map(comparison, frame0) -> bytes:
    """Where on the object the residual is, per phase: the tracked Gaussians at frame 0 over the
    first video frame, coloured by their RMS residual motion (mm) in that phase."""
    plt = _plt()
    names = [p for p in ("all",) + PHASES if p in comparison.gaussian_residual and p != "rest"]
    uv0 = comparison.tracks.get("uv0", np.zeros((0, 2)))
    vals = {p: comparison.gaussian_residual[p] * 1000 for p in names}
    finite = np.concatenate([v[np.isfinite(v)] for v in vals.values()] + [np.zeros(1)])
    vmax = max(float(np.percentile(finite, 98)), 1e-3)
    fig, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 2.6), squeeze=False)
    H, W = frame0.shape[:2]
    for ax, p in zip(axes[0], names):
        ax.imshow(np.asarray(frame0) * 0.5 + 0.25)
        v = vals[p]
        ok = np.isfinite(v)
        sc = ax.scatter(uv0[ok, 0] - 0.5, uv0[ok, 1] - 0.5, c=v[ok], s=4, cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(p, fontsize=9)
        ax.set_xlim(0, W)
        ax.set_ylim(H, 0)
        ax.axis("off")
    fig.colorbar(sc, ax=axes[0].tolist(), shrink=0.8, label="RMS residual (mm)")
    return _fig_png(fig)


def plot_versions(versions: list[dict]) -> bytes:
    """The final loss and mean PSNR of every fit version on the stage, with its effects."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 2.8))
    if not versions:
        ax.text(0.5, 0.5, "no fit versions on the stage", ha="center", va="center")
        ax.axis("off")
        return _fig_png(fig)
    v = [d["version"] for d in versions]
    loss = [np.nan if d.get("loss") is None else d["loss"] for d in versions]
    ax.plot(v, loss, "o-", color="#cb181d", ms=9, label="final loss")
    ax.set_xlabel("fit version")
    ax.set_ylabel("loss", color="#cb181d")
    ax.set_xticks(v)
    ax2 = ax.twinx()
    ax2.plot(v, [np.nan if d.get("psnr") is None else d["psnr"] for d in versions], "s--", color="#2171b5", ms=5,
             label="mean PSNR")
    ax2.set_ylabel("PSNR (dB)", color="#2171b5")
    for d, y in zip(versions, loss):
        ax.annotate("+".join(d.get("effects") or []) or "base", (d["version"], y), fontsize=7,
                    textcoords="offset points", xytext=(3, 5))
    return _fig_png(fig)
