"""`init`: a stage from a capture (the static object, the video, the camera, the masks).

Reads the capture folder, chooses the simulation's domain, grid, particle spacing and substeps,
fills the object with particles, and writes `scene.usda` (the user's root, if absent),
`scene.init.usdc` and an empty `scene.fit.usdc`. It never writes over another tool's file, the
user's root (`--force` keeps it and replaces the generated layers) or a fit (`--discard-fits`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture import read_capture
from ..errors import InputError
from ..fill import drop_stray_particles, fill_from_gaussians, fill_from_mesh
from ..scene import SimSettings
from ..sim.cfl import substeps_per_frame
from ..thickness import (CELLS_ACROSS, MAX_AUTO_GRID, MAX_AUTO_PARTICLES, MIN_AUTO_GRID, Thickness,  # noqa: F401
                         auto_grid, occupancy, thinnest_part)
from ..usd.layout import LayerPaths, check_our_root, check_owned, check_writable_dir
from ..usd.stage import write_init_stage
from ..usd.versions import discard_versions, fit_history
from . import budget

DEFAULT_GRID = 32
AUTO = "auto"
# `--grid auto`'s rule (CELLS_ACROSS cells across the thinnest part, its floor and caps) lives beside the
# thickness it reads (`thickness.auto_grid`: the synthetic generators make their truths finer than it too)
MEASURE_VOXELS_ACROSS = 10  # the thickness is measured on a fill with ~10 voxels across the thinnest part
MAX_MEASURE_VOXELS = 4_000_000
FIRST_PASS_VOXELS = 96      # the first measurement: the extent in 96 voxels
SPLAT_BUMPS = 1.0           # a fill from splats is rough at their size (notches, fins): the thickness is
#                             measured on the fill closed and opened by a ball of the median splat radius
#                             (largest axis) x this, so parts thinner than ~2 splat radii are not seen
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


@dataclass
class GridChoice:
    """How init chose its grid (recorded on the stage's init layer and printed)."""

    mode: str               # "auto" or "fixed" (the user's --grid N)
    grid: int               # cells along the longest side of the domain
    cell: float             # metres
    thinnest: float         # metres: the thinnest part (thickness.thinnest_part)
    cells_across: float     # thinnest / cell
    particles: int
    limit: str | None       # auto: "grid" or "particles" when a cap kept it from CELLS_ACROSS
    message: str

    def to_dict(self) -> dict:
        return {"mode": self.mode, "grid": self.grid, "cellSize": self.cell, "thinnestPart": self.thinnest,
                "cellsAcross": self.cells_across, "particles": self.particles, "limit": self.limit or "",
                "cellsAcrossWanted": CELLS_ACROSS}


def measure_thickness(fill, bbox_size, resolution: float = 0.0) -> tuple[Thickness, float]:
    """(The thinnest part, the solid's volume in m^3) of the object that `fill(spacing)` fills
    (returns particles on a lattice). Measured on a fill at 1/FIRST_PASS_VOXELS of the extent, then again at a
    tenth of the thinnest part found (at most MAX_MEASURE_VOXELS voxels) when that is finer. Parts
    thinner than ~5 voxels of the first pass (5% of the extent) are not seen (thickness.MIN_SEPARATION),
    nor, with `resolution` (the surface's detail size, init: splat_floor), any thinner than about
    twice that (the solid is closed and opened by a ball of that radius first)."""
    size = np.asarray(bbox_size, float)
    min_thickness = resolution
    floor = lambda: float(np.prod(size) / MAX_MEASURE_VOXELS) ** (1 / 3)  # noqa: E731
    h = max(float(size.max()) / FIRST_PASS_VOXELS, floor())
    parts = fill(h)
    th = thinnest_part(occupancy(parts.positions, h), h, min_thickness, resolution)
    h2 = max(th.thinnest / MEASURE_VOXELS_ACROSS, floor())
    if h2 < 0.8 * h:
        try:
            parts, h = fill(h2), h2
            th = thinnest_part(occupancy(parts.positions, h), h, min_thickness, resolution)
        except ValueError:
            pass  # too fine a lattice: keep the coarse measurement
    return th, float(len(parts)) * h ** 3


def splat_floor(g, mesh=None) -> float:
    """The surface's detail size: SPLAT_BUMPS x the median splat radius (its largest axis) for
    Gaussians; 0 for a mesh (exact)."""
    if mesh is not None or g is None or not len(g):
        return 0.0
    return SPLAT_BUMPS * float(np.median(g.scales.max(axis=1)))


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
         discard_fits=False, yes=True, max_grid=MAX_AUTO_GRID, max_particles=MAX_AUTO_PARTICLES,
         transfer_tau=0.0, preload=None, log=print) -> LayerPaths:
    """Build a stage from a capture. Returns the LayerPaths written. `grid`: cells along the
    longest side, or "auto" (CELLS_ACROSS cells across the thinnest part, within `max_grid` cells
    and about `max_particles` particles); `log` gets one line saying which grid and why. `force`:
    replace the generated layers of an existing stage (the root layer is kept); `discard_fits`: and
    its fit versions; `yes`: go on even when a frame would need more than budget.MAX_SUBSTEPS substeps.
    `transfer_tau` [s]: the simulation's rate transfer (docs/sim.md; 0: APIC, the default). `preload`: True, the scan
    shows the object carrying its weight (hung or resting, sagged): simulations start it prestressed (sim.preload);
    False: stress-free; None (default): left to the first fit, which decides by the frames (fit/preload_choice.py)."""
    stage_path = Path(stage_path)
    auto = check_grid(grid, max_grid, max_particles)
    check_target(stage_path, force, discard_fits)
    check_youngs_range(youngs_range)
    transfer_tau = float(transfer_tau or 0.0)
    if not (np.isfinite(transfer_tau) and transfer_tau >= 0):
        raise InputError("--transfer-tau", f"must be >= 0 seconds (0: APIC), got {transfer_tau:g}")
    cap = read_capture(capture_dir, object=object, video=video, camera=camera, masks=masks, fps=fps,
                       masks_amodal=masks_amodal)
    g = cap.object.gaussians
    points = g.means if cap.object.mesh is None else cap.object.mesh.vertices

    def fill(h, anchor=None):
        try:
            if cap.object.mesh is not None:
                return fill_from_mesh(cap.object.mesh, h, anchor=anchor)
            return fill_from_gaussians(g, h, anchor=anchor)
        except ValueError as exc:
            raise InputError(cap.object.path, str(exc)) from None

    def settings_for(n):
        return choose_sim_settings(points, cap.fps, n, padding, youngs_range, poisson, density,
                                   constitutive_model, max_poisson, spacing)

    extent = float(np.max(points.max(0) - points.min(0))) if len(points) else 0.0
    if not extent > 0:
        settings_for(DEFAULT_GRID)  # the same clear error as a fixed grid gives
    settings, parts, choice = plan_grid(fill, settings_for, points, grid if not auto else AUTO, padding, max_grid,
                                        max_particles, splat_floor(g, cap.object.mesh))
    log(choice.message)
    settings.transfer_tau = transfer_tau
    settings.preload = None if preload is None else bool(preload)
    budget.check_substeps(settings.substeps, len(parts), int(np.prod(settings.grid_resolution)), cap.n_frames,
                          flag="--youngs-range", yes=yes,
                          detail=f" (largest E {settings.youngs_max:g} Pa on a {settings.cell_size * 1000:.3g} mm grid "
                                 f"at {cap.fps:g} fps)")
    lp = write_init_stage(stage_path, cap, parts, settings, force=force, grid_choice=choice.to_dict())
    if discard_fits:
        discard_versions(stage_path)
    return lp


def plan_grid(fill, settings_for, points, grid, padding=DEFAULT_PADDING, max_grid=MAX_AUTO_GRID,
              max_particles=MAX_AUTO_PARTICLES, resolution=0.0):
    """(SimSettings, the particles, GridChoice) for `grid` (cells, or AUTO): the thinnest part
    measured (`fill(spacing, anchor=None)` fills the object), the grid chosen (auto: refilled at a
    coarser grid, at most 3 times, while the fill holds more than 5% over `max_particles`)."""
    auto = grid == AUTO
    size = points.max(0) - points.min(0)
    try:
        thick, volume = measure_thickness(fill, size, resolution)
    except ValueError:  # the object encloses no cell even at the measurement's spacing: say so, go on
        thick, volume = None, 0.0
    if thick is None:
        suggested, limit = DEFAULT_GRID, None
    else:
        suggested, limit = auto_grid(thick, volume, float(size.max()), padding, max_grid, max_particles)
    n = suggested if auto else int(grid)
    for _ in range(3):
        settings = settings_for(n)
        parts = drop_stray_particles(fill(settings.particle_spacing, settings.domain_min))
        if not auto or len(parts) <= 1.05 * max_particles or n <= 8:
            break
        n, limit = max(8, int(n * (max_particles / len(parts)) ** (1 / 3))), "particles"
    if thick is None:
        return settings, parts, GridChoice("auto" if auto else "fixed", int(n), float(settings.cell_size), float("nan"),
                                           float("nan"), len(parts), None,
                                           f"grid {n}{' (auto)' if auto else ''}: the thinnest part could not be "
                                           f"measured (the object fills no cell at 1/{FIRST_PASS_VOXELS} of its extent)")
    choice = grid_choice(auto, n, settings.cell_size, thick.thinnest, len(parts), limit, max_grid, max_particles,
                         suggested)
    return settings, parts, choice


def check_grid(grid, max_grid, max_particles) -> bool:
    """True for `grid` "auto", False for a whole number of cells (>= 8); an InputError otherwise."""
    if isinstance(grid, str):
        if grid.strip().lower() == AUTO:
            auto = True
        else:
            try:
                grid = int(grid)
            except ValueError:
                raise InputError("--grid", f"must be a whole number of cells or 'auto', got {grid!r}") from None
            auto = False
    else:
        auto = False
    if not auto and (int(grid) != grid or grid < 8):
        raise InputError("--grid", f"must be at least 8 cells (or 'auto'), got {grid}")
    if int(max_grid) != max_grid or max_grid < 8:
        raise InputError("--max-grid", f"must be a whole number of cells, at least 8, got {max_grid}")
    if int(max_particles) != max_particles or max_particles < 100:
        raise InputError("--max-particles", f"must be a whole number, at least 100, got {max_particles}")
    return auto


def grid_choice(auto: bool, grid: int, cell: float, thinnest: float, particles: int, limit, max_grid: int,
                max_particles: int, suggested: int) -> GridChoice:
    """The choice and its one-line explanation."""
    across = thinnest / cell
    mm = f"{thinnest * 1000:.3g} mm"
    if auto and limit:
        need = int(math.ceil(grid * CELLS_ACROSS / across))
        cap, flag = ((f"the cap of {max_grid} cells", f"--max-grid {need}") if limit == "grid" else
                     (f"the cap of {max_particles} particles (grid {grid})",
                      f"--max-particles {int(math.ceil(particles * (need / grid) ** 3 / 1000)) * 1000}"
                      + (f" --max-grid {need}" if need > max_grid else "")))
        msg = (f"thinnest part {mm}: {across:.1f} cells across at {cap}; the bending stiffness of thin parts "
               f"will be biased (use a GPU and {flag}, or accept)")
    elif auto:
        floor = grid == MIN_AUTO_GRID and across >= 1.05 * CELLS_ACROSS
        why = f"the floor of {MIN_AUTO_GRID} cells; " if floor else ""
        msg = (f"grid auto: {grid} cells along the longest side ({cell * 1000:.3g} mm cells, {particles} particles): "
               f"{why}{across:.1f} cells across the thinnest part ({mm}; {CELLS_ACROSS} wanted)")
    else:
        msg = f"grid {grid} (fixed): {across:.1f} cells across the thinnest part ({mm}), {particles} particles"
        if across < CELLS_ACROSS:
            msg += (f"; below {CELLS_ACROSS} cells its bending stiffness is biased (--grid auto would choose "
                    f"{suggested})")
    return GridChoice("auto" if auto else "fixed", int(grid), float(cell), float(thinnest), float(across),
                      int(particles), limit if auto else None, msg)
