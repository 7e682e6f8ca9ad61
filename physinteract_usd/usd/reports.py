"""The stage codec of fit reports: one `PhysInteractFitReport` prim per fitted model version,
`/World/PhysInteract/FitReport_v<N>` (version, status, creation time, effects, per-frame metrics,
loss history, final loss, runtime, device, settings and effect parameters as JSON, whether the
confidence was estimated, what the fit started from). Read back as a dict: the keys of
`read_report` are what `SceneData.reports`, `versions list --json` and the report verb use."""

from __future__ import annotations

import json

import numpy as np
from pxr import Sdf, Usd, Vt

REPORT_TYPE = "PhysInteractFitReport"
REPORT_PREFIX = "FitReport_v"


def json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def _mean(v) -> float | None:
    v = [float(x) for x in v if np.isfinite(x)]
    return float(np.mean(v)) if v else None


def read_report(prim: Usd.Prim) -> dict:
    """{"name", "version", "status" (complete | interrupted), "created" (ISO 8601 UTC, "" for a
    report written before versions had one), "effects", "frames", per-frame "psnr",
    "psnr_masked", "ssim", "iou", their means in "metrics", "loss_history", "final_loss",
    "runtime_s", "device", "settings", "effect_parameters", "confidence_estimated",
    "resumed_from", "material_model" (the model the fit chose and why, `FitResult.model`; {} if none)}."""
    g = lambda n: prim.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
    arr = lambda n: list(g(n) or [])  # noqa: E731
    settings = g("settings") or ""
    params = g("effectParameters") or ""
    ce = g("confidenceEstimated")
    out = {"name": prim.GetName(), "version": int(g("version")), "status": str(g("status") or "complete"),
           "created": str(g("createdTime") or ""), "effects": [str(x) for x in arr("effects")],
           "frames": [int(x) for x in arr("frameIndices")], "psnr": arr("framePsnr"),
           "psnr_masked": arr("framePsnrMasked"), "ssim": arr("frameSsim"), "iou": arr("frameIou"),
           "loss_history": arr("lossHistory"), "final_loss": float(g("finalLoss")),
           "runtime_s": float(g("runtimeSeconds")), "device": str(g("device")),
           "settings": json.loads(settings) if settings else {},
           "effect_parameters": json.loads(params) if params else {},
           "confidence_estimated": True if ce is None else bool(ce),
           "resumed_from": str(g("resumedFrom") or ""),
           "material_model": json.loads(g("materialModel") or "{}")}
    out["metrics"] = {k: _mean(out[k]) for k in ("psnr", "psnr_masked", "ssim", "iou")}
    return out


def report_versions(layer: Sdf.Layer, parent: Sdf.Path) -> list[int]:
    """The versions of the reports a layer holds."""
    spec = layer.GetPrimAtPath(parent)
    out = []
    if spec is None:
        return out
    for child in spec.nameChildren:
        if child.typeName == REPORT_TYPE:
            attr = child.attributes.get("physinteract:version")
            out.append(int(attr.default) if attr is not None and attr.default is not None else 1)
    return out


def write_report(stage: Usd.Stage, parent: Sdf.Path, version: int, result, effect_parameters: dict | None = None,
                 *, status: str = "complete", created: str = "", confidence_estimated: bool = True,
                 resumed_from: str = ""):
    """The report of model version `version` from a fit result (its frame metrics, loss history,
    final loss, runtime, device, settings and effects) and what the version record adds: status
    (complete | interrupted), creation time, whether the confidence was estimated, what it resumed."""
    f32 = lambda a: Vt.FloatArray.FromNumpy(np.asarray(a, np.float32))  # noqa: E731
    rp = stage.DefinePrim(parent.AppendChild(f"{REPORT_PREFIX}{version}"), REPORT_TYPE)
    fm = result.frame_metrics
    ra = lambda name, v: rp.GetAttribute(f"physinteract:{name}").Set(v)  # noqa: E731
    ra("version", version)
    ra("status", status)
    ra("createdTime", created)
    ra("effects", Vt.TokenArray(sorted(result.effects)))
    ra("frameIndices", Vt.IntArray([int(f["frame"]) for f in fm]))
    for key, attr in (("psnr", "framePsnr"), ("psnr_masked", "framePsnrMasked"), ("ssim", "frameSsim"),
                      ("iou", "frameIou")):
        ra(attr, f32([min(float(f[key]), 100.0) if np.isfinite(f[key]) else 100.0 for f in fm]))
    ra("lossHistory", f32(result.loss_history))
    ra("finalLoss", float(result.final_loss))
    ra("runtimeSeconds", float(result.runtime_s))
    ra("device", str(result.device))
    ra("settings", json.dumps(result.settings, default=json_default))
    ra("effectParameters", json.dumps(effect_parameters or {}, default=json_default))
    ra("materialModel", json.dumps(getattr(result, "model", None) or {}, default=json_default))
    ra("confidenceEstimated", bool(confidence_estimated))
    ra("resumedFrom", str(resumed_from))
    return rp
