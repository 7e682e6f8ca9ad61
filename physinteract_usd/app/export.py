"""`export`: the stage flattened into one self-contained USD file, and optionally one 3DGS PLY per
frame for tools without USD."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..gaussians import Gaussians, write_ply
from ..usd.export import export_stage
from ..usd.fit_io import read_splat_animation
from .adapters import read_scene


def export(stage_path, out_path, *, ply_sequence=None) -> dict:
    """Returns {"usd": path[, "ply_frames", "ply_sequence"]}."""
    if ply_sequence:  # checked before anything is written
        out_dir = Path(ply_sequence)
        if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
            raise InputError(out_dir, "exists and is not empty")
    result = {"usd": export_stage(stage_path, out_path)}
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
