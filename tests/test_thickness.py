"""The thinnest-part measurement (physinteract_usd/thickness.py) on shapes with a known answer,
given as lattice points the way `fill` gives particles, and init's grid choice from it."""

from __future__ import annotations

import numpy as np
import pytest

from physinteract_usd.thickness import occupancy, thinnest_part

H = 0.001  # 1 mm voxels


def lattice(mask: np.ndarray, h: float = H) -> np.ndarray:
    """Points at the centres of the set voxels of `mask` (what `fill` returns, shifted)."""
    return (np.argwhere(mask) + 0.5) * h + np.array([0.3, -0.2, 0.1])


def measure(mask, h=H):
    return thinnest_part(occupancy(lattice(mask, h), h), h)


def grid(shape):
    return np.indices(shape).astype(float)


@pytest.mark.parametrize("t", [6, 9, 14])
def test_slab_of_thickness_t(t):
    m = np.zeros((70, 70, 30), bool)
    m[5:65, 5:65, 8:8 + t] = True
    r = measure(m)
    assert not r.compact
    assert abs(r.thinnest / (t * H) - 1) < 0.05, r


def test_tilted_slab_within_a_voxel():
    z, y, x = grid((80, 80, 80))
    d = (z + y) / np.sqrt(2) - 56
    m = (np.abs(d) <= 5) & (x > 5) & (x < 75) & (z > 5) & (z < 75) & (y > 5) & (y < 75)
    true = 10 * H                                  # |d| <= 5 voxels: 10 voxels across, give or take one
    assert abs(measure(m).thinnest - true) <= 1.5 * H


@pytest.mark.parametrize("radius", [4.5, 7.5])
def test_rod_of_radius_r(radius):
    z, y, x = grid((100, 40, 40))
    m = ((y - 20) ** 2 + (x - 20) ** 2 <= radius ** 2) & (z > 5) & (z < 95)
    d_eq = np.sqrt(4 * m[50].sum() / np.pi) * H    # the voxelised disc's equivalent diameter
    r = measure(m)
    assert not r.compact
    assert abs(r.thinnest - d_eq) <= 1.5 * H, (r.thinnest, d_eq)   # a voxelised rod reads ~1 voxel low


def test_rod_on_a_block_is_the_thinnest_part():
    """A rod of diameter ~9 mm on a 50 mm block holding 98% of the volume: the rod, not the block
    (a percentile of the whole object's thickness would give the block)."""
    z, y, x = grid((140, 60, 60))
    m = np.zeros((140, 60, 60), bool)
    m[5:65, 5:55, 5:55] = True
    m[65:110] |= ((y - 30) ** 2 + (x - 30) ** 2 <= 20)[65:110]
    assert m[65:].sum() / m.sum() < 0.03
    r = measure(m)
    assert abs(r.thinnest - 9 * H) <= 1.5 * H, r
    assert r.median > 40 * H


def test_stray_blobs_do_not_dominate():
    """A 10 mm slab with a loose 2-voxel blob and a 2-voxel bump on its face: still 10 mm."""
    m = np.zeros((60, 60, 40), bool)
    m[5:55, 5:55, 5:15] = True
    m[20:22, 20:22, 30:32] = True
    m[40:42, 20:22, 15:17] = True
    assert abs(measure(m).thinnest - 10 * H) < 0.5 * H


@pytest.mark.parametrize("shape", ["cube", "ball"])
def test_compact_object_is_its_own_size(shape):
    z, y, x = grid((50, 50, 50))
    if shape == "cube":
        m = (np.abs(z - 25) < 20) & (np.abs(y - 25) < 20) & (np.abs(x - 25) < 20)
        size = 39 * H
    else:
        m = (z - 25) ** 2 + (y - 25) ** 2 + (x - 25) ** 2 <= 20 ** 2
        size = 41 * H
    r = measure(m)
    assert abs(r.thinnest / size - 1) < 0.08, r


def test_auto_grid_puts_cells_across_the_thinnest_part_and_honours_the_caps():
    from physinteract_usd.app import init as app_init
    from physinteract_usd.thickness import Thickness

    th = Thickness(thinnest=0.03, median=0.05, voxel=0.001, ridge_pairs=100, compact=False)
    extent, pad = 0.4, 0.3
    g, limit = app_init.auto_grid(th, volume=1e-4, extent=extent, padding=pad)
    dx = extent * (1 + 2 * pad) / g
    assert limit is None and app_init.CELLS_ACROSS <= th.thinnest / dx < app_init.CELLS_ACROSS * 1.05
    g2, limit2 = app_init.auto_grid(th, volume=1e-4, extent=extent, padding=pad, max_grid=40)
    assert (g2, limit2) == (40, "grid")
    # particles ~ volume / (dx / 2)^3 kept under the cap
    g3, limit3 = app_init.auto_grid(th, volume=1e-3, extent=extent, padding=pad, max_particles=5_000)
    assert limit3 == "particles"
    assert 1e-3 / (extent * (1 + 2 * pad) / g3 / 2) ** 3 <= 5_000
    # a compact object: the floor
    big = Thickness(thinnest=0.3, median=0.3, voxel=0.003, ridge_pairs=1, compact=True)
    assert app_init.auto_grid(big, volume=1e-3, extent=extent, padding=pad) == (app_init.MIN_AUTO_GRID, None)


def test_a_fill_from_sparse_splats_reads_its_bar():
    """The fit tests' striped bar (50 mm square section, splats of 6 mm on a 10 mm lattice): its fill
    is rough at the splats' size (notches and fins a few mm deep), which alone would read as parts
    ~10 mm thick; smoothed at the splat size, init's measurement gives the bar's section."""
    import fit_scene as fs
    from physinteract_usd.app import init as app_init
    from physinteract_usd.fill import fill_from_gaussians

    g = fs.bar_gaussians()
    th, volume = app_init.measure_thickness(lambda h, anchor=None: fill_from_gaussians(g, h, anchor=anchor),
                                            np.ptp(g.means, 0), app_init.splat_floor(g))
    assert abs(th.thinnest / fs.THICK - 1) < 0.2, th
    assert abs(volume / (fs.LENGTH * fs.THICK ** 2) - 1) < 0.2
