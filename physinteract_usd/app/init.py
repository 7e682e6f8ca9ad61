"""`init`: a stage from a capture (the static object, the video, the camera, the masks).

Reads the capture folder, chooses the simulation's domain, grid, particle spacing and substeps,
fills the object with particles, and writes `scene.usda` (the user's root, if absent),
`scene.init.usdc` and an empty `scene.fit.usdc`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..capture import read_capture
from ..errors import InputError
from ..fill import fill_from_gaussians, fill_from_mesh
from ..scene import SimSettings
from ..sim.cfl import substeps_per_frame
from ..usd.layout import LayerPaths
from ..usd.stage import write_init_stage

DEFAULT_GRID = 32
DEFAULT_PADDING = 0.5
DEFAULT_E_RANGE = (1e3, 1e6)
MAX_POISSON = 0.45  # default: the fit keeps nu in (0, max_poisson]: the CFL bound is taken there


def choose_sim_settings(points: np.ndarray, fps: float, grid: int = DEFAULT_GRID,
                        padding: float = DEFAULT_PADDING, youngs_range=DEFAULT_E_RANGE,
                        poisson: float = 0.3, density: float = 1000.0,
                        constitutive_model: str = "fixedCorotated", max_poisson: float = MAX_POISSON,
                        spacing: float | None = None) -> SimSettings:
    """Domain = the object's bounding box padded by `padding` x its extent on every side; `grid`
    cells along the longest side; particle spacing dx / 2; substeps from the CFL bound at the
    largest E allowed."""
    if grid < 8:
        raise InputError("--grid", "must be at least 8 cells")
    if not (0 < youngs_range[0] < youngs_range[1]):
        raise InputError("--youngs-range", "needs 0 < min < max")
    if not (0.0 < max_poisson < 0.5):
        raise InputError("--max-poisson", "must lie in (0, 0.5)")
    if not (0.0 < poisson <= max_poisson):
        raise InputError("--poisson", f"must lie in (0, {max_poisson:g}] (--max-poisson)")
    lo, hi = points.min(0), points.max(0)
    extent = float(np.max(hi - lo))
    if not extent > 0:
        raise InputError("object", "the object has zero extent")
    pad = padding * extent
    dlo, dhi = lo - pad, hi + pad
    dx = float(np.max(dhi - dlo)) / grid
    res = np.maximum(np.ceil((dhi - dlo) / dx).astype(int), 4)
    centre = 0.5 * (dlo + dhi)
    dlo = centre - 0.5 * res * dx
    dhi = dlo + res * dx
    substeps = substeps_per_frame(fps, dx, youngs_range[1], max_poisson, density)
    if spacing is not None and not (0 < spacing):
        raise InputError("--spacing", "must be positive")
    return SimSettings(domain_min=dlo, domain_max=dhi, grid_resolution=tuple(int(r) for r in res),
                       cell_size=dx, particle_spacing=float(spacing or dx / 2.0), substeps=substeps,
                       youngs_min=float(youngs_range[0]), youngs_max=float(youngs_range[1]),
                       poisson_default=float(poisson), poisson_max=float(max_poisson), density=float(density),
                       constitutive_model=constitutive_model)


def init(stage_path, capture_dir=None, *, object=None, video=None, camera=None, masks=None,
         fps=None, masks_amodal=False, grid=DEFAULT_GRID, padding=DEFAULT_PADDING,
         youngs_range=DEFAULT_E_RANGE, poisson=0.3, density=1000.0,
         constitutive_model="fixedCorotated", max_poisson=MAX_POISSON, spacing=None, force=False) -> LayerPaths:
    """Build a stage from a capture. Returns the LayerPaths written."""
    stage_path = Path(stage_path)
    if stage_path.exists() and not force:
        raise InputError(stage_path, "already exists: `init --force` replaces the generated layers "
                         "and keeps your root layer")
    cap = read_capture(capture_dir, object=object, video=video, camera=camera, masks=masks, fps=fps,
                       masks_amodal=masks_amodal)
    g = cap.object.gaussians
    settings = choose_sim_settings(g.means if cap.object.mesh is None else cap.object.mesh.vertices,
                                   cap.fps, grid, padding, youngs_range, poisson, density,
                                   constitutive_model, max_poisson, spacing)
    try:
        if cap.object.mesh is not None:
            parts = fill_from_mesh(cap.object.mesh, settings.particle_spacing, anchor=settings.domain_min)
        else:
            parts = fill_from_gaussians(g, settings.particle_spacing, anchor=settings.domain_min)
    except ValueError as exc:
        raise InputError(cap.object.path, str(exc)) from None
    return write_init_stage(stage_path, cap, parts, settings, force=force)
