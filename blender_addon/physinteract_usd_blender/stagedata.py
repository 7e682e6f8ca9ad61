"""What the add-on reads from a physinteract-usd stage with Blender's own USD (`pxr`, 25.08 in
Blender 5.0), and the one file it writes: the Gaussian splats as plain points. No bpy here.

Blender's USD import skips the splats (`UsdVol.ParticleField3DGaussianSplat` is newer than its
USD), but its `pxr` reads the prim's attributes as untyped data: positions (time-sampled after a
fit or a simulation), scales, opacities and `primvars:displayColor`. `write_splat_points` turns
them into a `UsdGeom.Points` file that Blender's importer does read (an animated POINTCLOUD), with
per-point colour, radius and opacity.

Also read here: the stage's timing (fps, frame range), its contact sets (what extraction found
and the user's hints, shown back after an import), the SimParticles' rest positions, and the fit
reports (per-frame PSNR / SSIM / IoU: the error curve when the CLI has no `report` verb).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

try:
    from pxr import Sdf, Usd, UsdGeom, Vt
except ImportError:  # pragma: no cover - set up by the add-on (pip bpy keeps pxr in its own site-packages)
    Sdf = Usd = UsdGeom = Vt = None

SPLATS = "/World/Object/Splats"
PARTICLES = "/World/Object/SimParticles"
SCENE = "/World/PhysInteract"
NEVER = 1e9                 # releaseTime of a contact never released (the schema's default)
MARK = "physinteract_blender"
# the radius of the sphere standing for a Gaussian: its two largest scales' geometric mean times
# this (a Gaussian of opacity 1 covers more than half of its peak within ~1.18 sigma)
SPLAT_RADIUS = 1.2


class StageError(RuntimeError):
    """One line: the file and the problem."""


def _open(path) -> "Usd.Stage":
    if Usd is None:
        raise StageError("Blender's USD Python module (pxr) is not available")
    if not os.path.exists(path):
        raise StageError(f"{path}: file not found")
    reload_layers(path)
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise StageError(f"{path}: cannot be opened as a USD stage")
    return stage


def reload_layers(path) -> None:
    """Re-read the layers of `path` that this process already holds (USD keeps an opened layer
    while anything uses it, e.g. an imported cache): the CLI replaces them on disk between runs."""
    if Sdf is None:
        return
    seen, todo = set(), [os.path.abspath(str(path))]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        layer = Sdf.Layer.Find(p)
        if layer is None:
            continue
        try:
            layer.Reload()
        except Exception:  # noqa: BLE001 - a layer gone from disk: the open below says so
            continue
        for sub in layer.subLayerPaths:
            todo.append(os.path.normpath(os.path.join(os.path.dirname(p), sub)))


# ---------------------------------------------------------------------------------- timing
def timing(path) -> dict:
    """{"fps", "start", "end"}: timeCodesPerSecond and the frame range (frame k is time code k)."""
    st = _open(path)
    return {"fps": float(st.GetTimeCodesPerSecond()), "start": int(round(st.GetStartTimeCode())), "end": int(round(st.GetEndTimeCode()))}


def fps_fields(fps: float) -> tuple[int, float]:
    """Blender's (render.fps, render.fps_base) for a frame rate: 20 -> (20, 1.0), 29.97 -> (30, 1.001)."""
    if fps <= 0 or not math.isfinite(fps):
        raise StageError(f"frame rate {fps} is not a positive number")
    whole = max(1, int(round(fps)))
    return whole, whole / fps


# ------------------------------------------------------------------------------- particles
def rest_points(path) -> np.ndarray:
    """SimParticles' rest positions (P, 3) in the stage's frame: the default value the init layer
    authors, else frame 0 of the animation."""
    st = _open(path)
    attr = UsdGeom.Points(st.GetPrimAtPath(PARTICLES)).GetPointsAttr()
    v = attr.Get(Usd.TimeCode.Default()) if attr else None
    if v is None and attr:
        v = attr.Get(0)
    if v is None:
        raise StageError(f"{path}: no {PARTICLES} points")
    return np.asarray(v, np.float64).reshape(-1, 3)


def has_primvar(path, prim_path: str, name: str) -> bool:
    st = _open(path)
    prim = st.GetPrimAtPath(prim_path)
    return bool(prim) and bool(prim.GetAttribute(f"primvars:{name}"))


def contact_sets(path) -> list[dict]:
    """The composed stage's PhysInteractContactSet prims as plain dicts: name, type, source ('user'
    for a hint or an override, 'extracted', ...), grasp, release (None: never), indices, point
    (the contact point, stage frame), radius (collider radius, 0 when none)."""
    st = _open(path)
    scene = st.GetPrimAtPath(SCENE)
    out = []
    if not scene:
        return out
    for p in scene.GetChildren():
        if p.GetTypeName() != "PhysInteractContactSet" and not p.GetAttribute("physinteract:contactType"):
            continue
        g = lambda n, p=p: p.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
        rel = g("releaseTime")
        out.append({
            "name": p.GetName(), "type": str(g("contactType") or ""), "source": str(g("source") or "user"),
            "grasp": int(round(g("graspTime") or 0)),
            "release": None if rel is None or not math.isfinite(rel) or rel >= NEVER else int(round(rel)),
            "indices": [int(i) for i in (g("particleIndices") or [])],
            "point": [float(x) for x in (g("contactPoint") or (0.0, 0.0, 0.0))],
            "radius": float(g("colliderRadius") or 0.0),
            "guessed": bool(g("extentGuessed") or False),
        })
    return out


def fit_reports(path) -> list[dict]:
    """The fit reports, oldest version first: {"version", "effects", "frames", "psnr", "ssim",
    "iou", "final_loss"} with per-frame lists (what `report --json` summarises)."""
    st = _open(path)
    scene = st.GetPrimAtPath(SCENE)
    out = []
    if not scene:
        return out
    for p in scene.GetChildren():
        if p.GetTypeName() != "PhysInteractFitReport" and not p.GetAttribute("physinteract:framePsnr"):
            continue
        g = lambda n, p=p: p.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
        frames = [int(x) for x in (g("frameIndices") or [])]
        vals = {k: [float(x) for x in (g(a) or [])] for k, a in
                (("psnr", "framePsnr"), ("ssim", "frameSsim"), ("iou", "frameIou"))}
        effects = g("effects")
        out.append({"version": int(g("version") or 0), "effects": [str(e) for e in (effects or [])],
                    "frames": frames or list(range(len(vals["psnr"]))), **vals,
                    "final_loss": float(g("finalLoss")) if g("finalLoss") is not None else None,
                    "status": str(g("status") or "")})
    return sorted(out, key=lambda r: r["version"])


def report_from_stage(path) -> dict:
    """A `report --json`-shaped dict from the stage's newest fit report (frames with psnr, ssim,
    iou; the top-level means; versions): the panel's fallback when the CLI has no `report`."""
    reps = fit_reports(path)
    if not reps:
        raise StageError(f"{path}: no fit report on the stage yet (run fit)")
    cur = reps[-1]
    frames = [{"frame": f, "psnr": cur["psnr"][i] if i < len(cur["psnr"]) else None,
               "ssim": cur["ssim"][i] if i < len(cur["ssim"]) else None,
               "iou": cur["iou"][i] if i < len(cur["iou"]) else None} for i, f in enumerate(cur["frames"])]

    def mean(key):
        v = [x for x in cur[key] if x is not None and math.isfinite(x)]
        return float(np.mean(v)) if v else None

    return {"psnr": mean("psnr"), "ssim": mean("ssim"), "iou": mean("iou"), "frames": frames,
            "versions": [{"version": r["version"], "effects": r["effects"],
                          "psnr": float(np.mean(r["psnr"])) if r["psnr"] else None, "loss": r["final_loss"]}
                         for r in reps],
            "source": "stage"}


# --------------------------------------------------------------------------- splats as points
def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def splat_radius(scales: np.ndarray) -> np.ndarray:
    """(N,) radius of the sphere standing for each Gaussian, from its (N, 3) linear scales."""
    s = np.sort(np.abs(np.asarray(scales, np.float64)), axis=1)
    return SPLAT_RADIUS * np.sqrt(s[:, 1] * s[:, 2])


def splat_points_path(path) -> Path:
    """Where the points standing for `path`'s splats go: `<stem>.splats.usdc` beside it."""
    p = Path(path)
    return p.with_name(p.stem + ".splats.usdc")


def write_splat_points(path, out=None) -> Path | None:
    """Write the stage's Gaussian splats as a `UsdGeom.Points` file Blender imports: positions
    (time-sampled when the splats are), widths = 2 x `splat_radius` (time-sampled with the scales),
    `primvars:displayColor` (the splats' colour converted from sRGB to linear, so a render with
    the Standard view transform shows the captured colours), `primvars:opacity`. Stage metadata (Y
    up, metres, fps and frame range) as the source's. Returns the file, or None when the stage has
    no splats. Written atomically; refuses to replace a file this add-on did not write."""
    st = _open(path)
    prim = st.GetPrimAtPath(SPLATS)
    if not prim or not prim.GetAttribute("positions"):
        return None
    out = Path(out) if out is not None else splat_points_path(path)
    if out.exists():
        old = Sdf.Layer.FindOrOpen(str(out))
        mark = dict(old.customLayerData).get(MARK) if old is not None else None
        if not mark:
            raise StageError(f"{out}: exists and was not written by the PhysInteract add-on: "
                             "move it away to import the splats' look")
    pos_attr, scl_attr = prim.GetAttribute("positions"), prim.GetAttribute("scales")
    times = [t for t in pos_attr.GetTimeSamples()]
    scl_times = set(scl_attr.GetTimeSamples()) if scl_attr else set()
    rest = pos_attr.Get(Usd.TimeCode.Default())
    if rest is None:
        rest = pos_attr.Get(times[0]) if times else None
    if rest is None:
        return None
    n = len(rest)
    colour = prim.GetAttribute("primvars:displayColor").Get() if prim.GetAttribute("primvars:displayColor") else None
    if colour is not None and len(colour) == n:
        rgb = np.asarray(colour, np.float64).reshape(n, 3)
    else:  # the SH's DC term (coefficient-major per Gaussian)
        deg = prim.GetAttribute("radiance:sphericalHarmonicsDegree").Get() or 0
        sh = np.asarray(prim.GetAttribute("radiance:sphericalHarmonicsCoefficients").Get(), np.float64)
        rgb = 0.5 + 0.28209479177387814 * sh.reshape(n, (deg + 1) ** 2, 3)[:, 0, :]
    opac = prim.GetAttribute("opacities").Get() if prim.GetAttribute("opacities") else None
    opac = np.ones(n) if opac is None or len(opac) != n else np.asarray(opac, np.float64)

    layer = Sdf.Layer.CreateAnonymous("splats.usdc")
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(st))
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.GetStageMetersPerUnit(st))
    stage.SetTimeCodesPerSecond(st.GetTimeCodesPerSecond())
    stage.SetFramesPerSecond(st.GetFramesPerSecond())
    if times:
        stage.SetStartTimeCode(min(times))
        stage.SetEndTimeCode(max(times))
    pts = UsdGeom.Points.Define(stage, "/Splats")   # a root prim: one object in Blender
    stage.SetDefaultPrim(pts.GetPrim())
    f3 = lambda a: Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    f1 = lambda a: Vt.FloatArray.FromNumpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    pa, wa = pts.GetPointsAttr(), pts.GetWidthsAttr()
    pa.Set(f3(np.asarray(rest, np.float32).reshape(n, 3)))
    rest_scales = scl_attr.Get(Usd.TimeCode.Default()) if scl_attr else None
    if rest_scales is None and scl_attr:
        rest_scales = scl_attr.Get(times[0] if times else 0)
    if rest_scales is None or len(rest_scales) != n:
        rest_scales = np.full((n, 3), 0.005)
    wa.Set(f1(2.0 * splat_radius(np.asarray(rest_scales, np.float64).reshape(n, 3))))
    pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    for t in times:
        pa.Set(f3(np.asarray(pos_attr.Get(t), np.float32).reshape(n, 3)), Usd.TimeCode(t))
        if t in scl_times:
            wa.Set(f1(2.0 * splat_radius(np.asarray(scl_attr.Get(t), np.float64).reshape(n, 3))), Usd.TimeCode(t))
    pv = UsdGeom.PrimvarsAPI(pts)
    pv.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex).Set(
        f3(srgb_to_linear(rgb)))
    pv.CreatePrimvar("opacity", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(f1(opac))
    layer.customLayerData = {MARK: {"kind": "splatPoints", "source": str(Path(path).resolve()),
                                    "radius": f"{SPLAT_RADIUS} x sqrt of the two largest scales",
                                    "colour": "displayColor: the splats' colour, sRGB -> linear"}}
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}.usdc")
    try:
        if not layer.Export(str(tmp)):
            raise StageError(f"{out}: could not be written")
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    reloaded = Sdf.Layer.Find(str(out))
    if reloaded is not None:
        reloaded.Reload()
    return out


def dumps(obj) -> str:
    return json.dumps(obj, separators=(",", ":"))
