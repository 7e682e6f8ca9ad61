"""The simulation's fill drops stray lattice points (#24: dev_0255 at 15k particles kept 10 particles with no
lattice neighbour; one was flung off at 10 m/s by the released sheet's snap and left the grid at every E)."""

from __future__ import annotations

import numpy as np

from physinteract_usd.app import init as app_init
from physinteract_usd.fill import SimParticles, drop_stray_particles


def sheet(h: float, extra: list) -> SimParticles:
    """A 6 x 6 x 2 lattice sheet of spacing h plus `extra` lattice points (in spacings)."""
    idx = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(2), indexing="ij"), -1).reshape(-1, 3)
    idx = np.concatenate([idx, np.asarray(extra, int).reshape(-1, 3)])
    pos = (idx + 0.5) * h
    return SimParticles(positions=pos, volumes=np.full(len(pos), h ** 3), is_surface=np.zeros(len(pos), bool), spacing=h)


def test_a_stray_lattice_point_is_dropped_a_corner_neighbour_kept():
    h = 0.005
    p = sheet(h, [[7, 2, 1], [6, 6, 2], [9, 9, 0]])       # 2 spacings off the edge; corner-touching; far off
    out = drop_stray_particles(p)
    kept = {tuple(np.round(x / h - 0.5).astype(int)) for x in out.positions}
    assert len(out.positions) == 72 + 1 and (6, 6, 2) in kept and (7, 2, 1) not in kept and (9, 9, 0) not in kept
    assert len(out.volumes) == len(out.is_surface) == len(out.positions)
    assert drop_stray_particles(sheet(h, [])).positions.shape == (72, 3)
    lone = SimParticles(positions=np.array([[0.0, 0, 0], [1.0, 0, 0]]), volumes=np.ones(2), is_surface=np.ones(2, bool),
                        spacing=h)
    assert len(drop_stray_particles(lone).positions) == 2       # every particle stray: nothing else to fill


def test_init_plan_grid_gives_the_simulation_no_stray_particle():
    h_seen = []

    def fill(h, anchor=None):
        h_seen.append(h)
        return sheet(h, [[8, 3, 0]])

    class S:
        particle_spacing, domain_min, cell_size = 0.005, np.zeros(3), 0.01

    pts = np.array([[0.0, 0, 0], [0.03, 0.03, 0.01]])
    settings, parts, choice = app_init.plan_grid(fill, lambda n: S, pts, 16)
    d = np.linalg.norm(parts.positions[:, None] - parts.positions[None], axis=-1) + np.eye(len(parts.positions))
    assert len(parts.positions) == 72 and d.min(1).max() <= np.sqrt(3) * 0.005 + 1e-9
