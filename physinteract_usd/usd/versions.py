"""Fit versions on the stage: every fit is a version, never lost (docs/versions.md).

```
scene.fit.usdc                    every version's PhysInteractFitReport (/World/PhysInteract/FitReport_v<N>),
                                  the current version's content, and physinteract:currentVersion
scene.versions/v<N>.usdc          version N's full snapshot: the same prim paths as the fit layer
                                  (SimParticles and Splats primvars and animation, the contacts it
                                  used and its fitted trajectories, its report)
```
A version's content is what a fit writes: everything under /World/Object, and the contact sets and
trajectories under /World/PhysInteract. Making version N current copies its snapshot's content
into the fit layer (the reports and what extraction wrote stay) and sets currentVersion = N. The
snapshot is written before the fit layer names the version, and the content a version replaces is
snapshotted first if it has no snapshot yet (a stage fitted before versions existed), so no step
loses a fit. Writers hold `<stem>.versions/.lock` while they decide and write.
"""

from __future__ import annotations

import contextlib
import datetime
import math
import os
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd

from ..errors import InputError
from .contacts import CONTACT_TYPE, TRAJECTORY_TYPE, remove_contacts
from .layout import (GENERATOR, OBJECT, PARTICLES, PRIMVAR_E, PRIMVAR_NU, SCENE, LayerPaths, atomic_outputs,
                     check_our_root, check_owned, mark_layer, open_fit_layer, remove_prim_spec, save_layer,
                     set_stage_metadata)
from .reports import REPORT_PREFIX, REPORT_TYPE, read_report, report_versions

CURRENT_ATTR = "physinteract:currentVersion"


def now_utc() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


# ------------------------------------------------------------------------------------- helpers
@contextlib.contextmanager
def versions_lock(lp: LayerPaths):
    """An exclusive lock on the stage's versions (two fits of one stage write one after the other)."""
    lp.versions.mkdir(exist_ok=True)
    with open(lp.versions / ".lock", "w") as fh:
        try:
            import fcntl

            fcntl.flock(fh, fcntl.LOCK_EX)
        except ImportError:  # pragma: no cover (not POSIX)
            pass
        yield


def _report_path(n: int) -> Sdf.Path:
    return SCENE.AppendChild(f"{REPORT_PREFIX}{int(n)}")


def current_in_layer(layer: Sdf.Layer) -> int | None:
    """The version a fit layer shows: its currentVersion; for a layer written before versions
    existed, the newest report's version when the layer holds fitted content; None: no fit shown."""
    spec = layer.GetPrimAtPath(SCENE)
    if spec is not None and CURRENT_ATTR in spec.attributes:
        v = spec.attributes[CURRENT_ATTR].default
        return int(v) if v else None
    vs = report_versions(layer, SCENE)
    if vs and layer.GetPrimAtPath(PARTICLES) is not None:
        return max(vs)
    return None


def _set_current(layer: Sdf.Layer, n: int | None) -> None:
    spec = Sdf.CreatePrimInLayer(layer, SCENE)
    attr = spec.attributes.get(CURRENT_ATTR)
    if attr is None:
        attr = Sdf.AttributeSpec(spec, CURRENT_ATTR, Sdf.ValueTypeNames.Int)
    attr.default = int(n or 0)
    mark_layer(layer, layer="fit", version=int(n or 0))


def _content_children(layer: Sdf.Layer) -> list[str]:
    """Names of the contact sets and trajectories a layer holds under /World/PhysInteract."""
    spec = layer.GetPrimAtPath(SCENE)
    if spec is None:
        return []
    return [c.name for c in spec.nameChildren if c.typeName in (CONTACT_TYPE, TRAJECTORY_TYPE)]


def _copy_content(src: Sdf.Layer, dst: Sdf.Layer) -> None:
    """Replace dst's version content (/World/Object, contact sets, trajectories) with src's."""
    remove_prim_spec(dst, OBJECT)
    remove_contacts(dst, SCENE)
    dspec = dst.GetPrimAtPath(SCENE)
    if dspec is not None:
        for name in [c.name for c in dspec.nameChildren if c.typeName == TRAJECTORY_TYPE]:
            del dspec.nameChildren[name]
    if src.GetPrimAtPath(OBJECT) is not None:
        Sdf.CreatePrimInLayer(dst, OBJECT.GetParentPath())
        if not Sdf.CopySpec(src, OBJECT, dst, OBJECT):
            raise OSError(f"{dst.identifier}: could not copy {OBJECT}")
    names = _content_children(src)
    if names:
        Sdf.CreatePrimInLayer(dst, SCENE)
    _copy_scene_attribute(src, dst, PRELOAD_ATTR)
    for name in names:
        p = SCENE.AppendChild(name)
        if not Sdf.CopySpec(src, p, dst, p):
            raise OSError(f"{dst.identifier}: could not copy {p}")


# the scene's attributes a version carries: whether its fit took the scan preloaded (fit/preload_choice.py)
PRELOAD_ATTR = "physinteract:preload"


def _copy_scene_attribute(src: Sdf.Layer, dst: Sdf.Layer, name: str) -> None:
    """dst's opinion of the scene's attribute `name` replaced by src's (none where src has none)."""
    sspec, dspec = src.GetPrimAtPath(SCENE), dst.GetPrimAtPath(SCENE)
    if dspec is not None and name in dspec.attributes:
        dspec.RemoveProperty(dspec.attributes[name])
    if sspec is None or name not in sspec.attributes:
        return
    dspec = Sdf.CreatePrimInLayer(dst, SCENE)
    if not Sdf.CopySpec(src, SCENE.AppendProperty(name), dst, SCENE.AppendProperty(name)):
        raise OSError(f"{dst.identifier}: could not copy {SCENE}.{name}")


def _copy_report(src: Sdf.Layer, dst: Sdf.Layer, n: int) -> None:
    p = _report_path(n)
    if src.GetPrimAtPath(p) is None:
        return
    Sdf.CreatePrimInLayer(dst, SCENE)
    remove_prim_spec(dst, p)
    if not Sdf.CopySpec(src, p, dst, p):
        raise OSError(f"{dst.identifier}: could not copy {p}")


def new_snapshot_layer(fps: float, n_frames: int, version: int, stage_name: str) -> Sdf.Layer:
    layer = Sdf.Layer.CreateAnonymous("version.usdc")
    set_stage_metadata(layer, fps, 0, n_frames - 1)
    layer.customLayerData = {"physinteract": {"generator": GENERATOR, "layer": "version", "version": int(version),
                                              "stage": stage_name}}
    return layer


def _save_snapshot(layer: Sdf.Layer, path: Path) -> None:
    path.parent.mkdir(exist_ok=True)
    with atomic_outputs(path) as (tmp,):
        if not layer.Export(str(tmp)):
            raise OSError(f"{path}: could not write the version snapshot")


def _snapshot_current(lp: LayerPaths, fit: Sdf.Layer, current: int | None) -> None:
    """Make sure the version the fit layer shows has a snapshot before its content is replaced
    (a stage fitted before versions existed, or one whose versions folder went missing)."""
    if not current or lp.version_layer(current).exists() or fit.GetPrimAtPath(OBJECT) is None:
        return
    snap = new_snapshot_layer(fit.timeCodesPerSecond or 24.0, int(fit.endTimeCode) + 1, current, lp.root.name)
    _copy_content(fit, snap)
    _copy_report(fit, snap, current)
    _save_snapshot(snap, lp.version_layer(current))


def _existing_versions(lp: LayerPaths, fit: Sdf.Layer) -> set[int]:
    vs = set(report_versions(fit, SCENE))
    if lp.versions.is_dir():
        for p in lp.versions.glob("v*.usdc"):
            with contextlib.suppress(ValueError):
                vs.add(int(p.stem[1:]))
    return vs


def _status_loss(layer: Sdf.Layer, n: int) -> tuple[str, float]:
    spec = layer.GetPrimAtPath(_report_path(n))
    if spec is None:
        return "complete", math.inf
    st = spec.attributes.get("physinteract:status")
    loss = spec.attributes.get("physinteract:finalLoss")
    return (str(st.default) if st is not None and st.default else "complete",
            float(loss.default) if loss is not None and loss.default is not None else math.inf)


def choose_current(new: dict, cur: dict | None, keep_best: bool) -> tuple[bool, str]:
    """Whether the new version becomes current, and why. `new`, `cur`: {"version", "status",
    "final_loss"} (cur None: no version is current). An interrupted fit never replaces a complete
    one; with keep_best the lower loss wins."""
    loss = new["final_loss"]
    if not math.isfinite(loss):
        return False, "its loss is not finite"
    if cur is None:
        return True, "no version was current"
    cv, cl = cur["version"], cur["final_loss"]
    if new["status"] != "complete" and cur["status"] == "complete":
        return False, f"it was interrupted and v{cv} is complete (an interrupted fit never replaces a complete one)"
    if not keep_best:
        return True, "--no-keep-best"
    if cur["status"] != "complete" and new["status"] == "complete":
        return True, f"v{cv} was interrupted"
    if loss < cl:
        return True, f"its loss {loss:.6g} is below v{cv}'s {cl:.6g}"
    return False, (f"its loss {loss:.6g} is not below v{cv}'s {cl:.6g} (--keep-best: the lower loss stays "
                   f"current; `versions use {new['version']}` or `fit --no-keep-best` to take the new one)")


# -------------------------------------------------------------------------------------- writing
def commit_version(stage_path, scene, author, *, status: str, final_loss: float, keep_best: bool = True) -> dict:
    """Write a new version: `author(stage, version)` authors its content and report into the
    snapshot's stage; the snapshot goes to `<stem>.versions/v<N>.usdc`, its report into the fit
    layer, and its content too when it becomes current (`choose_current`). Returns {"version",
    "layer", "snapshot", "current" (the version current now), "made_current", "reason"}."""
    lp = LayerPaths.of(stage_path)
    check_our_root(lp.root)
    check_owned(lp.fit, "fit")
    with versions_lock(lp):
        fit = open_fit_layer(lp, scene.fps, scene.n_frames)
        version = max(_existing_versions(lp, fit), default=0) + 1
        snap = new_snapshot_layer(scene.fps, scene.n_frames, version, lp.root.name)
        author(Usd.Stage.Open(snap), version)
        _save_snapshot(snap, lp.version_layer(version))
        cur_v = current_in_layer(fit)
        cur = None
        if cur_v is not None:
            st, loss = _status_loss(fit, cur_v)
            cur = {"version": cur_v, "status": st, "final_loss": loss}
        make, reason = choose_current({"version": version, "status": status, "final_loss": float(final_loss)},
                                      cur, keep_best)
        _copy_report(snap, fit, version)
        if make:
            _snapshot_current(lp, fit, cur_v)
            _copy_content(snap, fit)
            _set_current(fit, version)
        else:
            _set_current(fit, cur_v)
        save_layer(fit, lp.fit)
    return {"version": version, "layer": str(lp.fit), "snapshot": str(lp.version_layer(version)),
            "current": version if make else cur_v, "made_current": make, "reason": reason}


def use_version(stage_path, n: int, fps: float, n_frames: int) -> dict:
    """Make version n current: its snapshot's content into the fit layer (`fps`, `n_frames`: the
    stage's, for a fit layer that has to be made). Returns {"version", "previous", "layer"}."""
    lp = LayerPaths.of(stage_path)
    check_owned(lp.fit, "fit")
    with versions_lock(lp):
        fit = open_fit_layer(lp, fps, n_frames)
        known = _existing_versions(lp, fit)
        if n not in known:
            have = ", ".join(f"v{v}" for v in sorted(known)) or "none"
            raise InputError(stage_path, f"has no fit version {n} (versions: {have})")
        path = lp.version_layer(n)
        if not path.exists():
            raise InputError(path, f"version {n}'s snapshot is missing: only its report remains, it cannot be "
                             "restored")
        snap = open_snapshot(path)
        cur_v = current_in_layer(fit)
        _snapshot_current(lp, fit, cur_v)
        _copy_content(snap, fit)
        _copy_report(snap, fit, n)
        _set_current(fit, n)
        save_layer(fit, lp.fit)
    return {"version": n, "previous": cur_v, "layer": str(lp.fit)}


def open_snapshot(path: Path) -> Sdf.Layer:
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path))
    except Exception:  # noqa: BLE001  (a Tf error)
        layer = None
    if layer is None:
        raise InputError(path, "cannot be opened as a USD layer (a damaged version snapshot)")
    return layer


# -------------------------------------------------------------------------------------- reading
def list_versions(stage_path, fit_layer_reports: list[dict], current: int | None) -> list[dict]:
    """Every version the stage knows (reports in the fit layer, and snapshots whose report the fit
    layer lacks), oldest first, each a report dict plus "current" and "snapshot" (path or None)."""
    lp = LayerPaths.of(stage_path)
    out = {r["version"]: dict(r) for r in fit_layer_reports}
    if lp.versions.is_dir():
        for p in sorted(lp.versions.glob("v*.usdc")):
            try:
                n = int(p.stem[1:])
            except ValueError:
                continue
            if n in out:
                continue
            with contextlib.suppress(InputError):
                st = Usd.Stage.Open(open_snapshot(p))
                prim = st.GetPrimAtPath(_report_path(n))
                if prim and prim.GetTypeName() == REPORT_TYPE:
                    out[n] = read_report(prim)
    for n, r in out.items():
        snap = lp.version_layer(n)
        r["snapshot"] = str(snap) if snap.exists() else None
        r["current"] = n == current
    return [out[n] for n in sorted(out)]


def read_version_start(stage_path, n: int) -> dict:
    """What a resumed fit starts from, out of version n's snapshot: {"youngs", "poisson",
    "trajectories": {contact: (T, 3)}}."""
    path = LayerPaths.of(stage_path).version_layer(n)
    st = Usd.Stage.Open(open_snapshot(path))
    prim = st.GetPrimAtPath(PARTICLES)
    vals = {}
    for key, name in (("youngs", PRIMVAR_E), ("poisson", PRIMVAR_NU)):
        a = prim.GetAttribute(name) if prim else None
        if not a or not a.HasValue():
            raise InputError(path, f"version {n}'s snapshot has no {name} on {PARTICLES}")
        vals[key] = np.asarray(a.Get(), np.float64)
    trajs = {}
    scene = st.GetPrimAtPath(SCENE)
    if scene:
        for ch in scene.GetChildren():
            if ch.GetTypeName() != TRAJECTORY_TYPE or ch.GetAttribute("physinteract:stage").Get() != "fitted":
                continue
            targets = ch.GetRelationship("physinteract:contactSet").GetTargets()
            a = ch.GetAttribute("physinteract:position")
            trajs[targets[0].name if targets else ch.GetName().rsplit("_", 1)[0]] = np.array(
                [a.Get(t) for t in a.GetTimeSamples()], np.float64).reshape(-1, 3)
    vals["trajectories"] = trajs
    return vals


def fit_history(stage_path) -> dict:
    """What fits a stage's files hold, whether or not its root layer exists: {"versions": sorted
    version numbers (fit-layer reports and snapshots), "checkpoint": bool}."""
    lp = LayerPaths.of(stage_path)
    vs = set()
    if lp.fit.is_file():
        try:
            fit = Sdf.Layer.OpenAsAnonymous(str(lp.fit))
        except Exception:  # noqa: BLE001  (not a layer: check_owned reports it)
            fit = None
        if fit is not None:
            vs |= _existing_versions(lp, fit)
    if lp.versions.is_dir():
        for p in lp.versions.glob("v*.usdc"):
            with contextlib.suppress(ValueError):
                vs.add(int(p.stem[1:]))
    return {"versions": sorted(vs), "checkpoint": lp.checkpoint.exists()}


def discard_versions(stage_path) -> None:
    """Remove the versions folder (init --discard-fits)."""
    import shutil

    lp = LayerPaths.of(stage_path)
    if lp.versions.exists():
        tmp = lp.versions.with_name(f".{lp.versions.name}.discard{os.getpid()}")
        os.replace(lp.versions, tmp)
        shutil.rmtree(tmp, ignore_errors=True)
