"""How thick an object's thinnest part is, from a voxelised solid (numpy / scipy only).

The MPM grid must put a few cells across a part for that part to bend as the continuum does (a
rope one or two cells thick is far too stiff or too soft, whatever E says); `init --grid auto`
chooses its cell from the thickness measured here.

Method, on an occupancy grid of voxel size v (the object's particles filled at a fine spacing),
first closed and opened by a ball of the surface's own detail size when one is given (a fill from
splats is rough at the splats' size: notches and fins that would read as thin parts):
- the Euclidean distance transform with its feature transform (`scipy.ndimage.distance_transform_edt`):
  for every voxel, the nearest empty voxel;
- ridge pairs: two face-adjacent solid voxels whose nearest empty voxels lie on opposite sides
  (the directions to them more than `OPPOSED_DEG` apart). They straddle the medial surface of a
  sheet or the axis of a rod, and the distance across there is |a| + |b| - v (a, b: from the pair's
  midpoint to the two empty voxels; each empty voxel's centre lies half a voxel beyond the
  boundary). The opposed test leaves out the creases of the medial axis that run into convex
  edges and corners (nearest boundaries at ~90 degrees), whose small radii are not thin parts;
- each solid voxel takes the thickness of its nearest ridge voxel when it lies inside that ridge
  voxel's inscribed ball (a local-thickness map);
- the thinnest part: the smallest thickness t such that one connected piece of the material of
  local thickness <= t holds at least `MIN_PART_VOLUME` x t^3, i.e. a part that extends over a few
  thicknesses (a rod at least ~2.5 diameters long); its value is the median thickness of the part
  that piece belongs to (the connected material up to `PART_SLACK` thicker: a voxelised tilted
  slab's or rod's lumps put a tail ~1 voxel below its bulk). A stray Gaussian's blob or a surface bump (volume
  ~ t^3 or less) never qualifies, and unlike a percentile of the whole object a small thin part on
  a big body (a rope on its knot, a stem under a flower) still counts. Where nothing qualifies (a
  compact object: a ball, a cube) the thinnest part is the largest inscribed ball's diameter.

Accuracy: +-0.5 voxel on a voxelised slab or rod; the caller resolves the part by ~10 voxels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

OPPOSED_DEG = 120.0     # ridge pairs: the two nearest boundaries at least this far apart in angle
MIN_PART_VOLUME = 2.0   # a thin part holds at least this many t^3 of material (a rod ~2.5 t long)
MIN_SEPARATION = 4.0    # voxels between a ridge pair's two nearest empty voxels (a lambda-medial axis):
#                         a voxelised surface's staircase steps (1-2 voxels) are no thin parts
LEVEL_STEP = 0.05       # thicknesses are grouped in levels 5% apart
PART_SLACK = 0.35       # the thinnest part: the material up to 35% thicker connected to the first piece


def level_index(t):
    """The thickness level (steps of LEVEL_STEP, upwards) of thicknesses `t` (voxels)."""
    return np.ceil(np.log(np.asarray(t, float)) / np.log1p(LEVEL_STEP) - 1e-9)


def level_value(k) -> float:
    return float(np.exp(k * np.log1p(LEVEL_STEP)))


@dataclass
class Thickness:
    thinnest: float        # metres: the thinnest part (see the module doc)
    median: float          # metres: the median local thickness over the solid's volume
    voxel: float           # metres: the voxel size it was measured at
    ridge_pairs: int       # how many ridge pairs were found
    compact: bool          # no thin part: `thinnest` is the largest inscribed ball's diameter

    def to_dict(self) -> dict:
        return {"thinnest_m": self.thinnest, "median_m": self.median, "voxel_m": self.voxel,
                "ridge_pairs": self.ridge_pairs, "compact": self.compact}


def voxel_index(points: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 3) the voxel of `occupancy`'s grid that holds each point."""
    p = np.asarray(points, np.float64)
    return np.floor((p - p.min(0)) / spacing + 0.5).astype(np.int64) + 1


def occupancy(points: np.ndarray, spacing: float) -> np.ndarray:
    """A boolean grid (one empty voxel of margin on every side) with the voxels holding `points`
    (particles on a lattice of `spacing`, e.g. `fill`'s) set."""
    p = np.asarray(points, np.float64)
    if len(p) == 0:
        raise ValueError("no points to measure")
    idx = voxel_index(p, spacing)
    occ = np.zeros(tuple(idx.max(0) + 2), bool)
    occ[tuple(idx.T)] = True
    return occ


def point_thickness(points: np.ndarray, spacing: float) -> np.ndarray:
    """Each point's local thickness (metres: the diameter of the largest inscribed ball that holds it, `local_thickness`
    on the points' own occupancy). Where no ridge ball covers a point (a lump too small to have a medial axis), the
    nearest covered point's; nan everywhere where none is covered."""
    from scipy.spatial import cKDTree

    x = np.asarray(points, np.float64)
    tmap = local_thickness(occupancy(x, spacing), float(spacing))[0]
    t = tmap[tuple(voxel_index(x, spacing).T)].astype(np.float64)
    ok = np.isfinite(t) & (t > 0)
    if not ok.any():
        return np.full(len(x), np.nan)
    if not ok.all():
        t[~ok] = t[ok][cKDTree(x[ok]).query(x[~ok])[1]]
    return t


def local_thickness(occ: np.ndarray, voxel: float = 1.0, min_thickness: float = 0.0):
    """(thickness map over `occ` in units of `voxel`, inf where no ridge ball covers the voxel;
    ridge pair thicknesses; the distance transform). Ridge pairs thinner than `min_thickness`
    (metres, like `voxel`) are dropped."""
    occ = np.pad(np.asarray(occ, bool), 1)
    dist, feat = ndimage.distance_transform_edt(occ, return_indices=True)
    ridge = np.full(occ.shape, -np.inf)
    cos_max = np.cos(np.radians(OPPOSED_DEG))
    pairs = []
    for ax in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        both = occ[lo] & occ[hi]
        p = np.argwhere(both)
        if not len(p):
            continue
        q = p.copy()
        q[:, ax] += 1
        c = p + 0.5 * (q - p)
        a = feat[(slice(None), *p.T)].T - c
        b = feat[(slice(None), *q.T)].T - c
        na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(na * nb, 1e-12)
        sep = np.linalg.norm(a - b, axis=1)
        keep = (cos <= cos_max) & (sep >= MIN_SEPARATION) & (na + nb - 1.0 >= min_thickness / voxel)
        t = na[keep] + nb[keep] - 1.0
        for v in (p[keep], q[keep]):
            np.maximum.at(ridge, tuple(v.T), t)
        pairs.append(t)
    pairs = np.concatenate(pairs) if pairs else np.zeros(0)
    # Hildebrand's local thickness: each voxel the largest ridge ball that contains it, balls
    # grouped by thickness level (one distance transform per level, cropped to its balls)
    tmap = np.full(occ.shape, -np.inf)
    is_ridge = np.isfinite(ridge)
    if is_ridge.any():
        q = np.full(occ.shape, np.nan)
        q[is_ridge] = level_index(ridge[is_ridge])
        for k in np.unique(q[is_ridge]):
            sel = q == k
            pts = np.argwhere(sel)
            level = float(np.median(ridge[sel]))
            r = 0.5 * float(ridge[sel].max()) + 0.5
            lo = np.maximum(pts.min(0) - int(r) - 1, 0)
            hi = np.minimum(pts.max(0) + int(r) + 2, occ.shape)
            box = tuple(slice(a, b) for a, b in zip(lo, hi))
            d = ndimage.distance_transform_edt(~(q[box] == k))
            sub = tmap[box]
            cover = (d <= r) & occ[box]
            sub[cover] = np.maximum(sub[cover], level)
    tmap[~np.isfinite(tmap)] = np.inf
    crop = (slice(1, -1),) * 3
    return tmap[crop] * voxel, pairs * voxel, dist[crop] * voxel


def smooth(occ: np.ndarray, radius: float) -> np.ndarray:
    """`occ` closed, then opened, by a ball of `radius` voxels (through distance transforms, on a
    grid grown by the radius): notches narrower than 2 radius filled, fins thinner removed."""
    pad = int(np.ceil(radius)) + 2
    a = np.pad(np.asarray(occ, bool), pad)
    dilate = lambda x: ndimage.distance_transform_edt(~x) <= radius  # noqa: E731
    erode = lambda x: ndimage.distance_transform_edt(x) > radius     # noqa: E731
    return dilate(erode(erode(dilate(a))))


def thinnest_part(occ: np.ndarray, voxel: float, min_thickness: float = 0.0, resolution: float = 0.0) -> Thickness:
    """The thinnest part of the solid `occ` (voxels of size `voxel` metres): see the module doc.
    `resolution` (metres): the surface's own detail size (a fill from splats is rough at their
    size: notches and fins): the solid is closed and opened by a ball that size first.
    `min_thickness` (metres): thinner ridges are not parts."""
    occ = np.asarray(occ, bool)
    if not occ.any():
        raise ValueError("the solid is empty")
    if resolution >= voxel:
        occ = smooth(occ, resolution / voxel)
        if not occ.any():
            raise ValueError("the solid is thinner than its surface's resolution everywhere")
    tmap, pairs, dist = local_thickness(occ, voxel, min_thickness)
    # the largest inscribed ball: EDT to the nearest empty voxel centre, half a voxel beyond the boundary
    ball = 2.0 * float(dist.max()) - voxel
    solid = occ & np.isfinite(tmap)
    t = np.sort(tmap[solid])
    median = float(np.median(t)) if len(t) else ball
    # candidate thicknesses in steps of LEVEL_STEP; a level qualifies when one connected piece of
    # the material at most that thick holds MIN_PART_VOLUME x level^3 (in voxels)
    levels = np.unique(level_index(t / voxel)) if len(t) else []
    for lv in levels:
        level = voxel * level_value(lv) * (1 + 1e-9)
        need = MIN_PART_VOLUME * (level / voxel) ** 3
        if np.searchsorted(t, level, side="right") < need:
            continue
        thin = solid & (tmap <= level)
        lab, n = ndimage.label(thin)
        sizes = np.bincount(lab.ravel())[1:]
        if sizes.max() >= need:
            # the part: the connected material up to PART_SLACK thicker that holds this piece (the
            # lowest level's piece is the tail of a lumpy voxelisation; the part is its bulk)
            seed = lab == (1 + int(np.argmax(sizes)))
            lab2, _ = ndimage.label(solid & (tmap <= level * (1 + PART_SLACK)))
            part = lab2 == lab2[tuple(np.argwhere(seed)[0])]
            return Thickness(float(np.median(tmap[part])), median, float(voxel), int(len(pairs)), False)
    return Thickness(max(ball, voxel), median, float(voxel), int(len(pairs)), True)


# `init --grid auto`: MPM's quadratic B-spline spreads a particle over 3 cells, so a part 1-2 cells thick
# has its whole thickness in one kernel footprint: the grid velocity varies too little across it to
# carry the linear strain of bending, and its bending stiffness is off by far more than MA's 20%
# (the suite's ropes at grid 24; the clamped cantilever in tests/test_known_answers.py). Four cells
# across is the fewest that leave two kernel footprints' worth of independent nodes through the
# thickness (docs/init.md has the measured cantilever frequencies).
CELLS_ACROSS = 4
MIN_AUTO_GRID = 24          # never coarser than the synthetic captures' suggestion (motion, contact)
MAX_AUTO_GRID = 128         # cells along the longest side: a GPU's budget (--max-grid lowers it)
MAX_AUTO_PARTICLES = 60_000  # ~1 min per fit iteration on an H100 at 128 cells (--max-particles)


def auto_grid(thick: "Thickness | float", volume: float, extent: float, padding: float = 0.5,
              max_grid: int = MAX_AUTO_GRID, max_particles: int = MAX_AUTO_PARTICLES) -> tuple[int, str | None]:
    """(Cells along the longest side, which cap bound it or None): CELLS_ACROSS cells across the
    thinnest part, at least MIN_AUTO_GRID, at most `max_grid` and about `max_particles` particles
    (a fill at half a cell holds volume / (dx / 2)^3). `thick`: a measured Thickness or the thinnest part in
    metres (a generator that knows its shape's)."""
    side = extent * (1 + 2 * padding)
    thinnest = float(getattr(thick, "thinnest", thick))
    want = max(int(math.ceil(side * CELLS_ACROSS / thinnest - 1e-9)), MIN_AUTO_GRID)
    by_particles = int(math.floor(side / (2.0 * (volume / max_particles) ** (1 / 3))))
    grid = min(want, max_grid, by_particles)
    limit = None if grid >= want else ("grid" if max_grid <= by_particles else "particles")
    return max(grid, 8), limit
