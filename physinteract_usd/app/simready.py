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
    points, unloaded = mesh.points, None
    if st.preload:      # the scan carries its weight: the twin's rest is its unloaded shape (#23)
        points, g, unloaded = _unloaded(sd, mesh, g, tet, w, supports, log)
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
        "restShape": "scan" if unloaded is None else "unloaded (the scan's preload taken off; it settles into the scan "
                                                      "under gravity on its supports)",
    }
    if unloaded is not None:
        info["unloadedShift"] = unloaded
    return SimReadyAsset(points=points, tets=mesh.tets, surface=mesh.surface, youngs=E, poisson=nu, density=rho,
                         region=labels, regions=regions, body_youngs=bE, body_poisson=bnu, body_density=float(st.density),
                         gaussians=g, splat_tet=tet, splat_weights=w, supports=supports, grasps=grasps,
                         effects=effects_with_fitted(sd), fps=sd.fps, n_frames=sd.n_frames, info=info)


def _unloaded(sd, mesh, g, tet, w, supports, log):
    """The mesh and the splats at the object's unloaded rest where the stage's scan is preloaded (`sim.preload`): the
    preload's stretch F0 at the fitted E, nu per particle, carried onto the tetrahedra (`element_values`, its inverse
    per component), the rest solved with the supports' and the ground's vertices where the scan has them
    (`tetmesh.unloaded_points`); the splats moved with their tetrahedra, their shapes unstretched likewise. Without
    this a simulator taking the scan as the rest would let the twin sag under gravity a second time. Returns (points,
    gaussians, {"max_m", "mean_m"} the vertices' shift)."""
    import dataclasses

    import torch

    from ..gaussians import scales_quats_from_covariance
    from ..simulation import build_simulation
    from ..tetmesh import embedded_positions, unloaded_points
    from .adapters import effects_with_fitted

    st = sd.settings
    effects = effects_with_fitted(sd)
    try:
        sim = build_simulation(sd, list(sd.contacts), effects=effects, dtype="float64")
    except (ValueError, InputError) as exc:
        why = exc.problem if isinstance(exc, InputError) else str(exc)
        raise InputError(sd.path, f"the scan is preloaded but its preload cannot be solved for the export: {why}") \
            from None
    E = torch.as_tensor(np.clip(sd.youngs_modulus, st.youngs_min, st.youngs_max), dtype=torch.float64)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, st.poisson_max), dtype=torch.float64)
    with torch.no_grad():
        inv = np.linalg.inv(sim.preload_F(E, nu).cpu().numpy())                      # (P, 3, 3)
    x0 = sd.particles_positions
    G = np.stack([element_values(mesh, x0, inv[:, i, j]) for i in range(3) for j in range(3)], 1).reshape(-1, 3, 3)
    held = np.zeros(len(mesh.points), bool)
    for h in supports:
        held[np.asarray(h.vertices, np.int64)] = True
    if "ground" in effects:           # the bottom layer rests on the ground: it stays where the scan has it
        y = mesh.points[:, 1]
        held |= y <= y.min() + 0.5 * float(st.particle_spacing)
    try:
        pts = unloaded_points(mesh, G, held)
    except ValueError as exc:
        raise InputError(sd.path, f"the scan is preloaded but {exc}") from None
    Gs = G[tet]                                                                        # each splat's tetrahedron
    covs = np.einsum("nij,njk,nlk->nil", Gs, g.covariances(), Gs)
    scales, quats = scales_quats_from_covariance(covs)
    g = dataclasses.replace(g, means=embedded_positions(pts, mesh.tets, tet, w), scales=scales, quats=quats)
    shift = np.linalg.norm(pts - mesh.points, axis=1)
    log(f"the scan is preloaded: the twin's rest is its unloaded shape (vertices moved up to {1e3 * shift.max():.1f} "
        "mm from the scan); under gravity on its supports it settles back into the scan")
    return pts, g, {"max_m": float(shift.max()), "mean_m": float(shift.mean())}


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
