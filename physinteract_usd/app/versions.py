"""`versions`: the stage's fit versions (every fit is one, never lost; docs/versions.md): list them,
and make one current (its material, animation and contacts back into the fit layer)."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..usd.stage import frame_range, stage_versions
from ..usd.versions import use_version

SUMMARY_KEYS = ("version", "status", "created", "effects", "final_loss", "iterations", "runtime_s", "device",
                "resumed_from", "confidence_estimated", "current", "snapshot")


def list_versions(stage_path) -> dict:
    """{"stage", "current", "versions": [{"version", "status", "created", "effects", "final_loss",
    "psnr", "psnr_masked", "ssim", "iou" (means over frames), "iterations", "runtime_s", "device",
    "resumed_from", "confidence_estimated", "current", "snapshot" (its v<N>.usdc, None when only
    the report remains)}]}, oldest first."""
    reports, current = stage_versions(stage_path)
    out = []
    for r in reports:
        d = {k: r.get(k) for k in SUMMARY_KEYS}
        d["iterations"] = len(r.get("loss_history") or [])
        d.update(r.get("metrics") or {})
        out.append(d)
    return {"stage": str(Path(stage_path)), "current": current, "versions": out}


def use(stage_path, version) -> dict:
    """Make `version` current. Returns {"version", "previous", "layer"}."""
    try:
        n = int(version)
    except (TypeError, ValueError):
        raise InputError("VERSION", f"must be a version number (as `versions list` shows), got {version!r}") from None
    if n < 1:
        raise InputError("VERSION", f"versions count from 1, got {n}")
    return use_version(stage_path, n, *frame_range(stage_path))
