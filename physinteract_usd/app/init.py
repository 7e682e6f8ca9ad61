"""`init`: a stage from a capture (the static object, the video, the camera, the masks).

Reads the capture folder, chooses the simulation's domain, grid, particle spacing and substeps,
fills the object with particles, and writes `scene.usda` (the user's root, if absent),
`scene.init.usdc` and an empty `scene.fit.usdc`. It never writes over another tool's file, the
user's root (`--force` keeps it and replaces the generated layers) or a fit (`--discard-fits`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..capture import read_capture
from ..errors import InputError
from ..fill import fill_from_gaussians, fill_from_mesh
from ..scene import SimSettings
from ..sim.cfl import substeps_per_frame
from ..usd.layout import LayerPaths, check_our_root, check_owned, check_writable_dir
from ..usd.stage import write_init_stage
from ..usd.versions import discard_versions, fit_history
from . import budget

DEFAULT_GRID = 32
DEFAULT_PADDING = 0.5
DEFAULT_E_RANGE = (1e3, 1e6)
MAX_POISSON = 0.45  # default: the fit keeps nu in (0, max_poisson]: the CFL bound is taken there


FLOAT32_MAX = 3.4e38


def check_youngs_range(youngs_range) -> None:
    lo, hi = (float(x) for x in youngs_range)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError("--youngs-range", f"must be finite numbers in Pa, got {lo:g},{hi:g}")
    if not (0 < lo < hi):
        raise InputError("--youngs-range", f"needs 0 < MIN < MAX, got {lo:g},{hi:g}")
    if hi >= FLOAT32_MAX:
        raise InputError("--youngs-range", f"MAX {hi:g} Pa does not fit the stage's 32-bit floats (< 3.4e38)")


def check_target(stage_path: Path, force: bool, discard_fits: bool) -> None:
    """Before anything is read or written: the root layer's folder is writable, and nothing init
    would write over is another tool's file, the user's root (without --force) or a fit (without
    --discard-fits). A stage whose root is gone but whose generated layers remain is refused too:
    they hold what init would replace."""
    lp = LayerPaths.of(stage_path)
    if lp.root.suffix.lower() not in (".usda", ".usd"):
        raise InputError(lp.root, "the stage's root layer must be a .usda (or .usd) file")
    if lp.root.is_dir():
        raise InputError(lp.root, "is a folder: give the stage's root layer file, e.g. scene.usda")
    check_writable_dir(lp.root.parent)
    history = fit_history(lp.root)
    leftovers = [p for p in (lp.init, lp.fit, lp.versions) if p.exists()]
    if lp.root.exists():
        if not force:
            raise InputError(lp.root, "already exists: `init --force` replaces the generated layers "
                             f"({lp.init.name}) and keeps your root layer")
        check_our_root(lp.root)
    elif leftovers and not force:
        raise InputError(leftovers[0], f"exists without its root layer {lp.root.name}: init would replace it; "
                         "use another stage name, or --force" + (" --discard-fits" if history["versions"] else ""))
    for p, kind in ((lp.init, "init"), (lp.fit, "fit")):
        check_owned(p, kind)
    if (history["versions"] or history["checkpoint"]) and not discard_fits:
        n = len(history["versions"])
        what = f"{n} fit version{'s' if n != 1 else ''}" if n else "a stopped fit's checkpoint"
        raise InputError("--force", f"{lp.root.name} has {what} ({lp.fit.name}, {lp.versions.name}/): init would "
                         "discard them; add --discard-fits to do so, or init a new stage name")


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
    check_youngs_range(youngs_range)
    if not (math.isfinite(padding) and padding > 0):
        raise InputError("--padding", f"must be a positive fraction of the object's extent (e.g. 0.5), got {padding:g}")
    if not (math.isfinite(density) and density > 0):
        raise InputError("--density", f"must be positive, got {density:g}")
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
         constitutive_model="fixedCorotated", max_poisson=MAX_POISSON, spacing=None, force=False,
         discard_fits=False, yes=True) -> LayerPaths:
    """Build a stage from a capture. Returns the LayerPaths written. `force`: replace the generated
    layers of an existing stage (the root layer is kept); `discard_fits`: and its fit versions;
    `yes`: go on even when a frame would need more than budget.MAX_SUBSTEPS substeps."""
    stage_path = Path(stage_path)
    check_target(stage_path, force, discard_fits)
    check_youngs_range(youngs_range)
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
    budget.check_substeps(settings.substeps, len(parts), int(np.prod(settings.grid_resolution)), cap.n_frames,
                          flag="--youngs-range", yes=yes,
                          detail=f" (largest E {settings.youngs_max:g} Pa on a {settings.cell_size * 1000:.3g} mm grid "
                                 f"at {cap.fps:g} fps)")
    lp = write_init_stage(stage_path, cap, parts, settings, force=force)
    if discard_fits:
        discard_versions(stage_path)
    return lp
