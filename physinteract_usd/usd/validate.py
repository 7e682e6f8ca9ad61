"""Checks on what a stage authors, run by `read_stage` before any verb uses it: ranges, finiteness,
counts, camera rotations. A failure is an `InputError` naming the layer that authored the
strongest opinion, the prim and the attribute: `scene.usda: /World/Object/SimParticles.primvars:
physinteract:youngsModulus: 1 value is not finite (NaN) ...`.
"""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdGeom

from ..camera import rotation_problem
from ..errors import InputError

def authoring_layer(attr: Usd.Attribute, fallback: str) -> str:
    """The file of the layer holding the strongest opinion of `attr` (fallback: the root's)."""
    try:
        stack = attr.GetPropertyStack(Usd.TimeCode.Default())
    except Exception:  # noqa: BLE001
        stack = []
    for spec in stack:
        lay = spec.layer
        if lay is not None:
            return lay.realPath or lay.identifier
    return fallback


def _fail(attr: Usd.Attribute, root: str, problem: str):
    where = f"{attr.GetPrim().GetPath()}.{attr.GetName()}"
    raise InputError(authoring_layer(attr, root), f"{where}: {problem}")


def _values(attr: Usd.Attribute):
    v = attr.Get(Usd.TimeCode.Default()) if attr and attr.HasValue() else None
    return None if v is None else np.asarray(v, dtype=np.float64)


def _describe_bad(a: np.ndarray, ok: np.ndarray, what: str) -> str:
    bad = np.flatnonzero(~ok.reshape(len(ok), -1).all(1)) if a.ndim > 1 else np.flatnonzero(~ok)
    first = a[bad[0]]
    shown = np.array2string(np.asarray(first), precision=4) if np.ndim(first) else f"{float(first):g}"
    n = len(bad)
    return f"{n} value{'s' if n != 1 else ''} {'is' if n == 1 else 'are'} {what} (index {bad[0]}: {shown})"


def check_array(attr: Usd.Attribute, root: str, *, count: int | None = None, lo: float | None = None,
                hi: float | None = None, lo_open: bool = False, hi_open: bool = False, range_hint: str = "",
                required: bool = False) -> np.ndarray | None:
    """The attribute's default value as an array, checked: `count` entries, all finite, within
    [lo, hi] (open ends with lo_open / hi_open)."""
    a = _values(attr)
    if a is None:
        if required:
            _fail(attr, root, "has no value")
        return None
    if count is not None and len(a) != count:
        _fail(attr, root, f"{len(a)} values for {count} elements")
    if a.size == 0:
        return a
    fin = np.isfinite(a)
    if not fin.all():
        _fail(attr, root, _describe_bad(a, fin, "not finite (NaN or inf)"))
    if lo is not None:
        ok = a > lo if lo_open else a >= lo
        if not ok.all():
            _fail(attr, root, _describe_bad(a, ok, f"{'<=' if lo_open else 'below'} {lo:g}") + range_hint)
    if hi is not None:
        ok = a < hi if hi_open else a <= hi
        if not ok.all():
            _fail(attr, root, _describe_bad(a, ok, f"{'>=' if hi_open else 'above'} {hi:g}") + range_hint)
    return a


def check_scalar(attr: Usd.Attribute, root: str, *, lo=None, hi=None, lo_open=False, hi_open=False):
    v = _values(attr)
    if v is None:
        _fail(attr, root, "has no value")
    flat = np.atleast_1d(v)
    if not np.isfinite(flat).all():
        _fail(attr, root, f"is not finite ({v.tolist()})")
    if lo is not None and not ((flat > lo).all() if lo_open else (flat >= lo).all()):
        _fail(attr, root, f"must be {'>' if lo_open else '>='} {lo:g}, got {v.tolist()}")
    if hi is not None and not ((flat < hi).all() if hi_open else (flat <= hi).all()):
        _fail(attr, root, f"must be {'<' if hi_open else '<='} {hi:g}, got {v.tolist()}")
    return v


def check_scene_prim(scene: Usd.Prim, root: str) -> None:
    a = lambda n: scene.GetAttribute(f"physinteract:{n}")  # noqa: E731
    check_scalar(a("fps"), root, lo=0, lo_open=True)
    check_scalar(a("startFrame"), root, lo=0)
    start = int(_values(a("startFrame")))
    check_scalar(a("endFrame"), root, lo=start)
    check_scalar(a("imageResolution"), root, lo=1)
    check_scalar(a("gridResolution"), root, lo=1)
    check_scalar(a("cellSize"), root, lo=0, lo_open=True)
    check_scalar(a("particleSpacing"), root, lo=0, lo_open=True)
    check_scalar(a("substeps"), root, lo=1)
    check_scalar(a("transferTau"), root, lo=0)
    lo = check_scalar(a("domainMin"), root)
    hi = check_scalar(a("domainMax"), root)
    if not (np.asarray(hi) > np.asarray(lo)).all():
        _fail(a("domainMax"), root, f"must exceed domainMin {np.asarray(lo).tolist()} on every axis, got "
              f"{np.asarray(hi).tolist()}")
    emin = float(check_scalar(a("youngsModulusMin"), root, lo=0, lo_open=True))
    check_scalar(a("youngsModulusMax"), root, lo=emin, lo_open=True)
    numax = float(check_scalar(a("poissonRatioMax"), root, lo=0, hi=0.5, lo_open=True, hi_open=True))
    check_scalar(a("poissonRatioDefault"), root, lo=0, hi=numax, lo_open=True)
    check_scalar(a("gravity"), root)


def check_material(pprim: Usd.Prim, root: str, n: int, e_range: tuple[float, float], nu_max: float,
                   prefix: str = "primvars:physinteract:") -> None:
    """E, nu (and confidence, volume) on SimParticles or Splats: n values each, finite, in range."""
    tol = 1e-3   # float32 storage of the range's ends
    hint = (f" (the stage's range is [{e_range[0]:g}, {e_range[1]:g}] Pa: youngsModulusMin/Max, "
            "`init --youngs-range`)")
    check_array(pprim.GetAttribute(prefix + "youngsModulus"), root, count=n, lo=e_range[0] * (1 - tol),
                hi=e_range[1] * (1 + tol), range_hint=hint)
    check_array(pprim.GetAttribute(prefix + "poissonRatio"), root, count=n, lo=0.0, hi=nu_max + 1e-4,
                range_hint=f" (Poisson's ratio must lie in [0, poissonRatioMax = {nu_max:g}])")
    check_array(pprim.GetAttribute(prefix + "confidence"), root, count=n, lo=0.0, hi=1.0)


def check_particles(pprim: Usd.Prim, root: str, e_range, nu_max) -> int:
    pts = check_array(UsdGeom.Points(pprim).GetPointsAttr(), root, required=True)
    n = len(pts)
    if n == 0:
        _fail(UsdGeom.Points(pprim).GetPointsAttr(), root, "holds no particles")
    check_material(pprim, root, n, e_range, nu_max)
    check_array(pprim.GetAttribute("primvars:physinteract:volume"), root, count=n, lo=0.0, lo_open=True)
    check_array(pprim.GetAttribute("primvars:physinteract:isSurface"), root, count=n, lo=0, hi=1)
    check_scalar(pprim.GetAttribute("physinteract:density"), root, lo=0, lo_open=True)
    return n


def check_splats(prim: Usd.Prim, root: str, e_range, nu_max) -> None:
    pos = check_array(prim.GetAttribute("positions"), root, required=True)
    n = len(pos)
    check_array(prim.GetAttribute("scales"), root, count=n, lo=0.0)
    check_array(prim.GetAttribute("opacities"), root, count=n, lo=0.0, hi=1.0)
    rot = prim.GetAttribute("orientations")
    if rot and rot.HasValue() and len(rot.Get(Usd.TimeCode.Default())) != n:
        _fail(rot, root, f"{len(rot.Get(Usd.TimeCode.Default()))} values for {n} elements")
    check_material(prim, root, n, e_range, nu_max)


def check_camera_pose(prim: Usd.Prim, root: str, n_frames: int) -> None:
    """The camera's local-to-world rotation is orthonormal (a rigid camera) at every frame."""
    xf = UsdGeom.Xformable(prim)
    times = [Usd.TimeCode(k) for k in range(n_frames)] if xf.TransformMightBeTimeVarying() else [Usd.TimeCode.Default()]
    for t in times:
        m = np.array(xf.ComputeLocalToWorldTransform(t)).T
        problem = rotation_problem(m)
        if problem:
            ops = xf.GetOrderedXformOps()
            attr = ops[0].GetAttr() if ops else prim.GetAttribute("xformOpOrder")
            frame = "" if t.IsDefault() else f" at frame {int(t.GetValue())}"
            _fail(attr, root, f"camera pose{frame}: {problem}")


def check_contact_indices(scene: Usd.Prim, root: str, n_particles: int) -> None:
    for ch in scene.GetChildren():
        if ch.GetTypeName() == "PhysInteractContactSet":
            check_array(ch.GetAttribute("physinteract:particleIndices"), root, lo=0, hi=n_particles - 1,
                        range_hint=f" (SimParticles has {n_particles} particles)")
