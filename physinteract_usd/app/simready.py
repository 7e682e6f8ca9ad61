"""`export --sim-ready`: the fitted twin as a tetrahedral soft body that other simulators load (the
AOUSD deformable-physics schemas, see usd/simready.py and docs/simready.md).

From the stage: the particles (the object's volume), the fitted E and nu per particle, the density,
the Gaussians, the supports and the fitted interaction, the effects with their fitted values. It
builds the tetrahedral mesh of the particles' volume (`tetmesh`), carries the field onto the
tetrahedra (and clusters it into a few materials), binds the splats to the tetrahedra, maps the
contacts onto mesh points and writes one self-contained file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..tetmesh import (
    body_material,
    cluster_regions,
    element_values,
    embed_points,
    surface_distances,
    tetmesh_from_particles,
    vertices_held_by,
)
from ..usd.simready import Hold, SimReadyAsset, write_sim_ready
from .adapters import effects_with_fitted, read_scene

FAINT = 0.1  # Gaussians fainter than this do not define the object's surface (as in fill)


def build_sim_ready(sd, *, step: int = 1, log=print) -> SimReadyAsset:
    """The asset for a scene (`SceneData`), without writing it."""
    st = sd.settings
    h = float(st.particle_spacing)
    x0 = sd.particles_positions
    try:
        mesh = tetmesh_from_particles(x0, h, step=step)
    except ValueError as exc:
        raise InputError(sd.path, f"cannot build a tetrahedral mesh of the object: {exc}") from None
    vol = mesh.volumes()
    E = element_values(mesh, x0, np.clip(sd.youngs_modulus, st.youngs_min, st.youngs_max), log=True)
    nu = element_values(mesh, x0, np.clip(sd.poisson_ratio, 1e-3, st.poisson_max))
    rho = np.full(len(mesh.tets), float(st.density))
    labels, regions = cluster_regions(E, nu, vol)
    bE, bnu = body_material(E, nu, vol)
    g = sd.gaussians
    tet, w = embed_points(mesh, g.means)
    shown = g.means[g.opacities >= FAINT] if np.any(g.opacities >= FAINT) else g.means
    d = surface_distances(mesh, shown)
    supports, grasps, skipped = [], [], []
    fitted = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    for c in sd.contacts:
        if c.type not in ("fixed", "pointAdherent"):
            skipped.append(f"{c.name} ({c.type}: a collider, not written)")
            continue
        verts = vertices_held_by(mesh, x0, c.indices, h)
        if len(verts) == 0:
            skipped.append(f"{c.name} ({c.type}: holds no mesh point)")
            continue
        if c.type == "fixed":
            supports.append(Hold(c.name, verts))
        else:
            traj = fitted.get(c.name, c.trajectory)
            grasps.append(Hold(c.name, verts, np.asarray(traj, np.float64), c.grasp_frame, c.release_frame))
    for s in skipped:
        log(f"note: contact {s}")
    particle_volume = float(np.sum(sd.particles_volumes))
    rep = getattr(sd, "current_report", None) or (sd.reports[-1] if sd.reports else None)
    info = {
        "source": str(sd.path),
        "fitVersion": int(rep["version"]) if rep else 0,
        "tetrahedraliser": "TetGen (tetgen package): PLC of the particles' 0.5 occupancy isosurface (marching cubes), "
                           "boundary kept on that surface",
        "particleSpacing": h,
        "surfaceToleranceSpacings": 1.0,
        "surfaceDistanceMax": float(d.max()), "surfaceDistanceP95": float(np.percentile(d, 95)),
        "volumeRatio": float(vol.sum() / particle_volume) if particle_volume > 0 else 0.0,
        "tetCount": int(len(mesh.tets)), "pointCount": int(len(mesh.points)),
        "splatsOutsideMesh": int(np.sum(w.min(1) < -1e-6)),
        "skippedContacts": skipped,
        "elasticModel": f"{st.constitutive_model} (fitted); E, nu are small-strain moduli",
    }
    return SimReadyAsset(points=mesh.points, tets=mesh.tets, surface=mesh.surface, youngs=E, poisson=nu, density=rho,
                         region=labels, regions=regions, body_youngs=bE, body_poisson=bnu, body_density=float(st.density),
                         gaussians=g, splat_tet=tet, splat_weights=w, supports=supports, grasps=grasps,
                         effects=effects_with_fitted(sd), fps=sd.fps, n_frames=sd.n_frames, info=info)


def export_sim_ready(stage_path, out_path, *, step: int = 1, log=print) -> dict:
    """Write the sim-ready asset; returns {"usd", "tetrahedra", "points", "regions",
    "surface_distance_max_m", "particle_spacing_m", "volume_ratio", "supports", "grasps", "unmapped_effects"}."""
    out = Path(out_path)
    if out.suffix.lower() not in (".usd", ".usdc", ".usda", ".usdz"):
        raise InputError(out, "the output must end in .usd, .usdc, .usda or .usdz")
    if not out.parent.is_dir():
        raise InputError(out.parent, "output folder does not exist")
    sd = read_scene(stage_path)
    if not sd.reports:
        log("note: the stage has no fit yet; exporting its current (initial) material")
    a = build_sim_ready(sd, step=step, log=log)
    path = write_sim_ready(out_path, a)
    return {"usd": path, "tetrahedra": int(len(a.tets)), "points": int(len(a.points)), "regions": len(a.regions),
            "surface_distance_max_m": a.info["surfaceDistanceMax"], "particle_spacing_m": a.info["particleSpacing"],
            "volume_ratio": a.info["volumeRatio"], "supports": [h.name for h in a.supports],
            "grasps": [h.name for h in a.grasps],
            "unmapped_effects": sorted(k for k in a.effects if k != "ground")}
