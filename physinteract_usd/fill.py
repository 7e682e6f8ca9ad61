"""Internal filling: turn a surface representation into simulation particles.

3D Gaussian captures and meshes describe a surface; an MPM solid needs its volume. Both paths put
particles on a lattice of spacing ``h`` aligned with the simulation grid (``h = dx / 2`` by default:
8 particles per cell), one particle per lattice cell whose centre is inside the object:

- from Gaussians: clamp runaway scales, densify inside each ellipsoid so the shell has no holes,
  mark the lattice cells the (densified) surface touches, flood-fill the closed interior
  (`scipy.ndimage.binary_fill_holes`), and decide the surface cells by which side of the local
  tangent plane (PCA normals of the surface samples, oriented from the fill) their centre lies on;
- from a watertight mesh: the same shell + flood fill, with the surface cells decided exactly by
  `trimesh`'s inside test (non-watertight meshes fall back to the Gaussian path on surface samples).

Where the flood fill alone does not enclose the object (holes between sparse samples, an unseen
underside), closing or an axis-ray vote adds cells; of those, `open_cavities` removes the ones in
the cavity of an open shell with a wall (a cap, a cup, a bowl) by ray parity on the surface samples,
so such a shell is filled to its wall thickness, not closed into a solid.

Volumes are the lattice cell volume, so the total is the filled volume. (How the Gaussians follow
the particles is the simulation's business: `simulation.build_simulation` binds each to its nearest
few particles.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .gaussians import Gaussians

MIN_OPACITY = 0.1  # Gaussians fainter than this do not define the surface
MAX_SAMPLES_PER_GAUSSIAN = 64
MAX_LATTICE_CELLS = 40_000_000


@dataclass
class SimParticles:
    positions: np.ndarray   # (P, 3) rest positions, metres
    volumes: np.ndarray     # (P,) rest volumes, m^3
    is_surface: np.ndarray  # (P,) bool: the particle's lattice cell touches the surface
    spacing: float          # lattice spacing h, metres

    def __len__(self) -> int:
        return len(self.positions)


@dataclass
class Lattice:
    """Particle lattice aligned with the simulation grid: cell (i,j,k) has centre lo + (ijk + 0.5) h."""

    lo: np.ndarray
    spacing: float
    shape: tuple

    def centres(self, idx: np.ndarray) -> np.ndarray:
        return self.lo + (idx + 0.5) * self.spacing

    def cell_of(self, p: np.ndarray) -> np.ndarray:
        return np.floor((p - self.lo) / self.spacing).astype(np.int64)

    @staticmethod
    def around(bmin, bmax, spacing, anchor=None, pad_cells=3) -> "Lattice":
        """A lattice covering [bmin, bmax] with `pad_cells` of margin, aligned to `anchor`."""
        anchor = np.zeros(3) if anchor is None else np.asarray(anchor, dtype=np.float64)
        lo = anchor + np.floor((np.asarray(bmin) - anchor) / spacing - pad_cells) * spacing
        hi = anchor + np.ceil((np.asarray(bmax) - anchor) / spacing + pad_cells) * spacing
        shape = tuple(int(round(s)) for s in (hi - lo) / spacing)
        if np.prod(shape) > MAX_LATTICE_CELLS:
            raise ValueError(f"particle lattice of {shape} cells is too large: choose a coarser grid")
        return Lattice(lo, float(spacing), shape)


def clamp_scales(g: Gaussians) -> np.ndarray:
    """Scales clamped to a quarter of the object's extent and 20x the median: no runaway radii."""
    extent = float(np.max(np.ptp(g.means, axis=0))) if len(g) > 1 else float(np.max(g.scales))
    med = float(np.median(g.scales.max(axis=1)))
    cap = min(0.25 * extent, 20.0 * med) if med > 0 else 0.25 * extent
    return np.clip(g.scales, 1e-9, max(cap, 1e-9))


def densify(g: Gaussians, spacing: float, rng=None) -> np.ndarray:
    """Surface samples: the Gaussian means plus points drawn inside each (clamped) 1-sigma
    ellipsoid, as many as its footprint needs for samples ~spacing/2 apart (capped per Gaussian)."""
    rng = np.random.default_rng(0) if rng is None else rng
    keep = g.opacities >= MIN_OPACITY
    if keep.sum() < 4:
        keep = np.ones(len(g), bool)
    means, scales, R = g.means[keep], clamp_scales(g)[keep], g.rotations()[keep]
    s_sorted = np.sort(scales, axis=1)
    footprint = np.pi * s_sorted[:, 2] * s_sorted[:, 1]
    counts = np.minimum(np.ceil(footprint / (0.5 * spacing) ** 2), MAX_SAMPLES_PER_GAUSSIAN).astype(int)
    counts[counts <= 1] = 0
    total = int(counts.sum())
    if total == 0:
        return means
    owner = np.repeat(np.arange(len(means)), counts)
    u = rng.normal(size=(total, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u *= rng.random((total, 1)) ** (1.0 / 3.0)  # uniform in the unit ball
    local = u * scales[owner]
    pts = means[owner] + np.einsum("nij,nj->ni", R[owner], local)
    return np.concatenate([means, pts], 0)


def _shell_and_solid(samples: np.ndarray, lat: Lattice, thicken: bool, max_close: int = 4):
    """Cells the surface samples touch (the shell) and the shell with its enclosed cells (solid).

    Cells that the surface only clips at a corner may hold no sample and open a tunnel between
    inside and outside; `thicken` dilates the shell by one cell (26-neighbourhood) to close them.
    Larger holes (sparse Gaussians) are closed morphologically: the shell is dilated by up to
    `max_close` more cells until the flood fill encloses at least half of what axis-ray voting
    calls enclosed, and the filled solid is eroded back by as much. Failing that (a large hole,
    such as an underside no camera saw), the ray vote itself decides."""
    cells = lat.cell_of(samples)
    ok = np.all((cells >= 0) & (cells < np.array(lat.shape)), axis=1)
    shell = np.zeros(lat.shape, bool)
    shell[tuple(cells[ok].T)] = True
    cube = np.ones((3, 3, 3), bool)
    if thicken:
        shell = ndimage.binary_dilation(shell, structure=cube)
    rays = (_ray_votes(shell) >= 5) & ~shell
    enough = max(1, rays.sum() // 2)
    solid = ndimage.binary_fill_holes(shell)
    k = 0
    while (solid & ~shell).sum() < enough and k < max_close:
        k += 1
        closed = ndimage.binary_fill_holes(ndimage.binary_dilation(shell, structure=cube, iterations=k))
        interior = ndimage.binary_erosion(closed, structure=cube, iterations=k, border_value=0) & ~shell
        if interior.sum() > (solid & ~shell).sum():
            solid = shell | interior
    if (solid & ~shell).sum() < enough:
        # a hole too large to close (an unseen underside): a cell is enclosed when rays along at
        # least 5 of the 6 axis directions hit the shell (one open side is tolerated)
        solid = shell | rays
    # what closing or the ray vote added beyond the flood fill is a hole in one sheet (fill it) or
    # the cavity of an open shell with a wall (a cap, a cup: leave it empty): ray parity decides
    added = solid & ~ndimage.binary_fill_holes(shell)
    if added.any():
        solid &= ~open_cavities(samples, lat, added)
    return shell, solid


CAVITY_DIRECTIONS = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], float) - 1.0
CAVITY_DIRECTIONS /= np.linalg.norm(CAVITY_DIRECTIONS, axis=1, keepdims=True)
CAVITY_PROBES = 4000  # at most this many cells are probed; the others follow their nearest probe
_FINE_CELLS = 64_000_000  # the half-spacing surface grid is used up to this many voxels
CAVITY_REACH = 3  # cells
OCC_CLOSE = 2  # fine voxels: holes between samples up to twice this wide are closed
MAX_CROSSING = 8  # fine voxels: a longer run along a ray is a graze, not a crossing


def open_cavities(samples: np.ndarray, lat: Lattice, added: np.ndarray) -> np.ndarray:
    """The cells of `added` (cells that only closing or the ray vote called enclosed) that lie in
    the cavity of an open shell rather than inside the object.

    Ray parity on the surface samples: they are binned on a grid of half the spacing (holes up to
    2 * OCC_CLOSE voxels closed, one voxel of margin); from a probed cell, a ray along each of 26
    directions counts the separate surface layers it crosses (runs of occupied voxels): an odd
    count says inside, an even one (a wall's inner then outer surface) outside; a ray that meets
    nothing (out through the opening) or runs along a surface (a graze, a run over MAX_CROSSING
    voxels) says nothing, and a ray of n layers counts 1/n (each crossing may be misread). A cell
    is in a cavity when the outside votes win; a cell where inside wins by less than 2:1 goes with
    a cavity within CAVITY_REACH cells of it (the grazes under a rim), else it stays (the fill as
    before). A wall thinner than ~2 spacings reads as one layer, so at that resolution an open
    shell is still closed (its wall is not resolved)."""
    drop = np.zeros(added.shape, bool)
    idx = np.argwhere(added)
    if len(idx) == 0:
        return drop
    f = 2 if 8 * np.prod(lat.shape) <= _FINE_CELLS else 1
    fine = Lattice(lat.lo, lat.spacing / f, tuple(f * s for s in lat.shape))
    occ = np.zeros(fine.shape, bool)
    c = fine.cell_of(samples)
    ok = np.all((c >= 0) & (c < np.array(fine.shape)), axis=1)
    occ[tuple(c[ok].T)] = True
    occ = ndimage.binary_dilation(ndimage.binary_closing(occ, iterations=OCC_CLOSE))
    m = max(1, int(np.ceil((len(idx) / CAVITY_PROBES) ** (1 / 3))))
    probes = idx[np.all(idx % m == 0, axis=1)] if m > 1 else idx
    if len(probes) == 0:
        probes = idx[:: max(1, len(idx) // CAVITY_PROBES)]
    shape = np.array(fine.shape)
    t = np.arange(1, int(np.ceil(np.linalg.norm(shape))) + 1, dtype=np.float32)  # steps of one fine voxel
    # a border of empty voxels: a step outside the grid is clipped onto it and reads empty
    flat = np.pad(occ, 1).ravel()
    strides = np.array([(shape[1] + 2) * (shape[2] + 2), shape[2] + 2, 1])
    dirs = CAVITY_DIRECTIONS.astype(np.float32)
    cavity = np.zeros(len(probes), bool)
    unsure = np.zeros(len(probes), bool)
    for s in range(0, len(probes), 128):
        x = ((probes[s:s + 128] + 0.5) * f).astype(np.float32)  # probe centres in fine-voxel units
        flat_idx = np.zeros((len(x), len(dirs), len(t)), np.int64)
        for axis in range(3):
            coord = np.floor(x[:, None, None, axis] + dirs[None, :, None, axis] * t[None, None, :])
            flat_idx += (np.clip(coord, -1, shape[axis]).astype(np.int64) + 1) * strides[axis]
        hit = flat[flat_idx]
        layers = hit[..., 0].astype(int) + (hit[..., 1:] & ~hit[..., :-1]).sum(-1)
        # a ray that runs along a surface for long (a grazing chord that merges two layers) says nothing
        clean = _longest_run(hit) <= MAX_CROSSING
        # each crossing may be misread (a hole, a graze): a ray counts 1 / its layers
        w = np.where(clean & (layers > 0), 1.0 / np.maximum(layers, 1), 0.0)
        odd = (w * (layers % 2 == 1)).sum(1)
        even = (w * (layers % 2 == 0)).sum(1)
        cavity[s:s + 128] = even > odd
        unsure[s:s + 128] = ~cavity[s:s + 128] & (odd < 2 * even)
    if not cavity.any():
        return drop
    if m > 1:
        _, near = cKDTree(probes).query(idx)
        cavity, unsure = cavity[near], unsure[near]
    drop[tuple(idx[cavity].T)] = True
    # a cell with no clear majority (a graze near a rim) goes with a cavity within CAVITY_REACH cells
    maybe = np.zeros(added.shape, bool)
    maybe[tuple(idx[cavity | unsure].T)] = True
    return ndimage.binary_dilation(drop, iterations=CAVITY_REACH, mask=maybe)


def _longest_run(hit: np.ndarray) -> np.ndarray:
    """The longest run of True along the last axis."""
    run = np.zeros(hit.shape[:-1], np.int32)
    best = np.zeros_like(run)
    for k in range(hit.shape[-1]):
        run = np.where(hit[..., k], run + 1, 0)
        np.maximum(best, run, out=best)
    return best


def _ray_votes(shell: np.ndarray) -> np.ndarray:
    """For each cell, in how many of the 6 axis directions a ray from it meets the shell."""
    votes = np.zeros(shell.shape, np.int8)
    for axis in range(3):
        fwd = np.logical_or.accumulate(shell, axis=axis)
        bwd = np.flip(np.logical_or.accumulate(np.flip(shell, axis), axis=axis), axis)
        votes += fwd.astype(np.int8) + bwd.astype(np.int8)
    return votes


def _oriented_normals(samples: np.ndarray, solid: np.ndarray, shell: np.ndarray, lat: Lattice, k=16):
    """PCA normals of the surface samples, oriented outward using the flood fill."""
    tree = cKDTree(samples)
    kk = min(k, len(samples))
    _, nb = tree.query(samples, k=kk)
    nb = nb.reshape(len(samples), kk)
    P = samples[nb] - samples[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", P, P)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]  # smallest eigenvalue
    interior = solid & ~shell

    def lookup(grid, p):
        c = lat.cell_of(p)
        inb = np.all((c >= 0) & (c < np.array(lat.shape)), axis=1)
        out = np.zeros(len(p), bool)
        out[inb] = grid[tuple(c[inb].T)]
        return out

    step = 3.0 * lat.spacing
    out_plus, out_minus = ~lookup(solid, samples + step * n), ~lookup(solid, samples - step * n)
    in_plus, in_minus = lookup(interior, samples + step * n), lookup(interior, samples - step * n)
    flip = (out_minus & ~out_plus) | (in_plus & ~in_minus)
    n[flip] *= -1
    known = out_plus ^ out_minus | in_plus ^ in_minus
    return n, known


def fill_from_gaussians(g: Gaussians, spacing: float, anchor=None) -> SimParticles:
    """Particles filling the volume enclosed by the Gaussians' surface (see module doc)."""
    samples = densify(g, spacing)
    lat = Lattice.around(samples.min(0), samples.max(0), spacing, anchor)
    shell, solid = _shell_and_solid(samples, lat, thicken=True)
    normals, known = _oriented_normals(samples, solid, shell, lat)
    idx_shell = np.argwhere(shell)
    c = lat.centres(idx_shell)
    tree = cKDTree(samples)
    kk = min(8, len(samples))
    _, nb = tree.query(c, k=kk)
    nb = nb.reshape(len(c), kk)
    d = np.einsum("nki,nki->nk", c[:, None, :] - samples[nb], normals[nb])
    dist = np.linalg.norm(c[:, None, :] - samples[nb], axis=2)
    votes = known[nb] & (dist <= 2.0 * spacing)
    # keep a surface cell when its centre is behind the local tangent plane: the signed distances
    # to the planes of the nearby oriented samples, averaged with weights that fall off over half
    # a spacing (the nearest planes dominate, so curved surfaces keep their full volume); cells
    # far from every sample must be behind all known planes (safe at sharp edges); where the
    # surface is too thin to tell a side (a sheet), the cell itself is the material
    w = np.where(votes, np.exp(-0.5 * (dist / (0.5 * spacing)) ** 2), 0.0)
    side = (w * d).sum(1) / np.maximum(w.sum(1), 1e-300)
    behind_all_known = np.where(known[nb], d, -np.inf).max(1) <= 0
    keep_shell = np.where(votes.any(1), side <= -0.05 * spacing,  # a hair inside, to be safe
                          np.where(known[nb].any(1), behind_all_known, dist[:, 0] <= spacing))
    inside = solid & ~shell
    inside[tuple(idx_shell[keep_shell].T)] = True
    return _particles_from_mask(inside, shell, lat)


def fill_from_mesh(mesh, spacing: float, anchor=None) -> SimParticles:
    """Particles filling a mesh's volume. Watertight: exact inside test on the surface cells.
    Otherwise the surface is sampled and filled like Gaussians (a thin open surface becomes a shell)."""
    import trimesh

    if not mesh.is_watertight:
        pts, _ = trimesh.sample.sample_surface_even(mesh, _sample_count(mesh.area, spacing), seed=0)
        g = Gaussians.from_colors(pts, (0.5, 0.5, 0.5), spacing * 0.5)
        return fill_from_gaussians(g, spacing, anchor)
    lat = Lattice.around(mesh.bounds[0], mesh.bounds[1], spacing, anchor)
    pts, _ = trimesh.sample.sample_surface(mesh, _sample_count(mesh.area, spacing), seed=0)
    samples = np.concatenate([pts, mesh.vertices])
    shell, solid = _shell_and_solid(samples, lat, thicken=False)
    if not (solid & ~shell).any():
        shell, solid = _shell_and_solid(samples, lat, thicken=True)
    idx_shell = np.argwhere(shell)
    inside = solid & ~shell
    contained = mesh.contains(lat.centres(idx_shell))
    inside[tuple(idx_shell[contained].T)] = True
    parts = _particles_from_mask(inside, shell, lat)
    parts.volumes *= float(mesh.volume) / parts.volumes.sum()  # the mesh knows its true volume
    return parts


def _sample_count(area: float, spacing: float) -> int:
    return int(min(max(4 * area / (0.5 * spacing) ** 2, 1000), 2_000_000))


def drop_stray_particles(parts: SimParticles) -> SimParticles:
    """`parts` without its stray particles: one none of whose 26 lattice neighbours is filled (a lone lattice point
    the surface's side test left at a thin part's edge or corner, 2+ spacings from the rest). Such a particle shares
    only the far, light nodes of its neighbours' stencils: the MPM holds it to the object by a thread, and a snap (a
    released grasp's recoil) flings it off as a free particle that flies out of the grid (#24: dev_0255 at 15k
    particles, 10 strays, one flung at 10 m/s). All kept when every particle is stray (nothing else to fill).
    init applies it to the simulation's fill only (`app.init.plan_grid`), not to the thickness probe's."""
    x = np.asarray(parts.positions, dtype=np.float64)
    if len(x) < 2:
        return parts
    d, _ = cKDTree(x).query(x, k=2)
    stray = d[:, 1] > 1.01 * np.sqrt(3.0) * parts.spacing
    if not stray.any() or stray.all():
        return parts
    keep = ~stray
    return SimParticles(positions=parts.positions[keep], volumes=parts.volumes[keep],
                        is_surface=parts.is_surface[keep], spacing=parts.spacing)


def _particles_from_mask(inside, shell, lat: Lattice) -> SimParticles:
    idx = np.argwhere(inside)
    if len(idx) == 0:
        raise ValueError("the object encloses no lattice cell at this spacing: use a finer grid")
    pos = lat.centres(idx)
    return SimParticles(positions=pos, volumes=np.full(len(pos), lat.spacing ** 3),
                        is_surface=shell[tuple(idx.T)], spacing=lat.spacing)


def gaussians_from_mesh(mesh, count: int, seed: int = 0) -> Gaussians:
    """Flat Gaussians (surfels) sampled on a mesh surface, coloured from its texture, vertex or face
    colours (grey if none): how a mesh is rendered."""
    import trimesh

    colors = None
    try:
        pts, face, colors = trimesh.sample.sample_surface(mesh, count, sample_color=True, seed=seed)
    except Exception:
        pts, face = trimesh.sample.sample_surface(mesh, count, seed=seed)
    if colors is None or len(colors) != len(pts):
        colors = np.full((len(pts), 3), 0.6)
    else:
        colors = np.asarray(colors, dtype=np.float64)[:, :3]
        if colors.max() > 1.0:
            colors = colors / 255.0
    normals = mesh.face_normals[face]
    # surfel radius so the disks cover the surface: area per sample = pi r^2
    r = np.sqrt(mesh.area / max(len(pts), 1) / np.pi) * 1.2
    scales = np.tile([r, r, 0.1 * r], (len(pts), 1))
    # rotation taking local z to the normal: q = (1 + z.n, z x n), normalised
    quats = np.stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(len(pts))], 1)
    flipped = normals[:, 2] < -0.999999
    quats[flipped] = [0.0, 1.0, 0.0, 0.0]
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    g = Gaussians.from_colors(pts, colors, scales, opacities=np.full(len(pts), 0.95), quats=quats)
    g.normals = normals
    return g
