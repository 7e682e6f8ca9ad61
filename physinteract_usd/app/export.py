"""`export`: the stage flattened into one self-contained USD file, and optionally one 3DGS PLY per
frame for tools without USD."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..gaussians import Gaussians, write_ply
from ..usd.export import export_stage, stage_layer_files
from ..usd.layout import check_writable_dir
from ..usd.fit_io import read_splat_animation
from .adapters import read_scene


def check_output(stage_path, out_path, force: bool) -> None:
    """Before anything is written: OUT is a file name in a writable folder, not a layer of the
    stage, and not an existing file unless `force`."""
    out = Path(out_path)
    if out.is_dir():
        raise InputError(out, "is a folder: give the asset's file name, e.g. twin.usdc")
    check_writable_dir(out.parent)
    if out.resolve() in stage_layer_files(stage_path):
        raise InputError(out, "would overwrite a layer of the stage itself")
    if out.exists() and not force:
        raise InputError(out, "already exists: --force replaces it")


def export(stage_path, out_path, *, ply_sequence=None, force=False, capture_paths="drop", sim_ready=False) -> dict:
    """Returns {"usd": path[, "ply_frames", "ply_sequence"][, "sim_ready"]}. The stage is read (and
    checked) first; OUT is refused if it exists, unless `force`; `capture_paths`: "drop" (default:
    the file depends on nothing else) or "absolute" (the capture's frames and masks by absolute
    path). `sim_ready`: OUT is the tetrahedral soft body with the deformable-physics schemas
    (`app.simready`; its summary under "sim_ready") instead of the flattened stage."""
    read_scene(stage_path)   # a stage with bad authored values is refused, not exported
    check_output(stage_path, out_path, force)
    if ply_sequence:  # checked before anything is written
        out_dir = Path(ply_sequence)
        if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
            raise InputError(out_dir, "exists and is not empty")
    if sim_ready:
        from .simready import export_sim_ready

        summary = export_sim_ready(stage_path, out_path)
        result = {"usd": summary["usd"], "sim_ready": summary}
    else:
        result = {"usd": export_stage(stage_path, out_path, capture_paths=capture_paths)}
    if ply_sequence:
        out_dir.mkdir(parents=True, exist_ok=True)
        sd = read_scene(stage_path)
        anim = read_splat_animation(stage_path)
        g0 = sd.gaussians
        for k, t in enumerate(anim["times"]):
            g = Gaussians(anim["positions"][k], anim["scales"][k], anim["quats"][k], g0.opacities, g0.sh)
            write_ply(g, out_dir / f"{int(t):06d}.ply")
        result["ply_frames"] = len(anim["times"])
        result["ply_sequence"] = str(out_dir)
    return result
