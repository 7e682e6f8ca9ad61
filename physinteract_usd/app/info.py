"""`info`: a summary of a stage as a dict (the CLI prints it as text or JSON)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..usd.stage import read_grid_choice
from .adapters import read_scene


def info(stage_path) -> dict:
    sd = read_scene(stage_path)
    cam = sd.camera.at(0)
    d = {
        "stage": str(sd.path),
        "generator": sd.generator,
        "object": {"kind": sd.object_kind, "gaussians": len(sd.gaussians),
                   "sh_degree": sd.gaussians.sh_degree,
                   "bounds": [sd.gaussians.means.min(0).round(4).tolist(), sd.gaussians.means.max(0).round(4).tolist()]},
        "particles": {"count": int(len(sd.particles_positions)), "surface": int(sd.particles_surface.sum()),
                      "spacing_m": sd.settings.particle_spacing,
                      "total_volume_m3": float(sd.particles_volumes.sum()),
                      "mass_kg": float(sd.particles_volumes.sum() * sd.settings.density),
                      "constitutive_model": sd.settings.constitutive_model},
        "frames": {"count": sd.n_frames, "fps": sd.fps, "size": list(sd.image_size),
                   "source": sd.video_asset or (str(Path(sd.frame_assets[0]).parent) if sd.frame_assets else None),
                   "masks": len(sd.mask_assets), "masks_amodal": sd.masks_amodal},
        "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                   "static": sd.camera.is_static, "position": cam.position.round(4).tolist()},
        "simulation": {"grid": list(sd.settings.grid_resolution), "cell_size_m": sd.settings.cell_size,
                       "domain": [sd.settings.domain_min.round(4).tolist(), sd.settings.domain_max.round(4).tolist()],
                       "substeps_per_frame": sd.settings.substeps,
                       "youngs_range_pa": [sd.settings.youngs_min, sd.settings.youngs_max],
                       # the rate transfer's time constant (physinteract:transferTau, SimModel.transfer_tau); 0: APIC
                       "transfer_tau_s": float(getattr(sd.settings, "transfer_tau", 0.0) or 0.0),
                       # the scan carries its weight (physinteract:preload, init --preload; sim.preload)
                       "preload": getattr(sd.settings, "preload", False),
                       # where the current version's fit decided it (fit/preload_choice.py): why
                       "preload_reason": (((sd.current_report or {}).get("settings") or {}).get("preload") or {})
                       .get("reason"),
                       "grid_choice": read_grid_choice(sd.path)},
        "effects": sd.effects,
        "contacts": [{"name": c.name, "type": c.type, "particles": int(len(c.indices)),
                      "grasp": c.grasp_frame, "release": c.release_frame, "source": c.source} for c in sd.contacts],
        "trajectories": [{"name": t.name, "contact": t.contact_set, "stage": t.stage, "samples": int(len(t.frames))}
                         for t in sd.trajectories],
        "fits": [{"version": r["version"], "effects": r["effects"],
                  "psnr": float(np.mean(r["psnr"])) if r["psnr"] else None,
                  "final_loss": r["final_loss"], "runtime_s": r["runtime_s"], "device": r["device"],
                  "status": r.get("status", "complete"), "current": bool(r.get("current")),
                  "restorable": bool(r.get("snapshot"))}
                 for r in sd.reports],
        "current_version": sd.current_version,
    }
    e = sd.youngs_modulus
    d["material"] = {"youngs_modulus_pa": {"min": float(e.min()), "median": float(np.median(e)), "max": float(e.max())},
                     "poisson_ratio": {"min": float(sd.poisson_ratio.min()), "max": float(sd.poisson_ratio.max())},
                     "fitted": bool(sd.reports)}
    if sd.confidence is not None:
        c = sd.confidence
        d["material"]["confidence"] = {"min": float(c.min()), "mean": float(c.mean()), "max": float(c.max()),
                                       "low_share": float(np.mean(c < 0.5))}
    cur = [r for r in sd.reports if r.get("current")] or sd.reports[-1:]
    if cur and cur[-1].get("material_model") is not None:
        # what the current version's fit said about E (fit_summary.identifiability, as `fit` printed it; no torch)
        from ..fit_summary import identifiability, model_summary

        conf = d["material"].get("confidence", {}).get("mean")
        d["material"]["identifiability"] = identifiability(model_summary(cur[-1]["material_model"]), conf,
                                                           float(np.median(e)))
    return d
