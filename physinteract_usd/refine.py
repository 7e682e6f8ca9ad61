"""The same scene on a finer grid: what the simulator's own resolution does to a fitted model (#22, #24).

A fit is made at one grid; the video is the continuum (a synthetic truth: a finer grid and substep).
How much of a fitted model's residual is the simulator's discretisation, and not physics it lacks,
is measured by simulating the *same* fitted model on a finer grid and seeing how far its frames move.
`refine_scene` builds that finer scene from the stage's own particles, so nothing is re-extracted:

- the grid's cell and the particle lattice's spacing / `split` (default 2: 8x the particles, 2x the
  substeps, ~16x a forward's cost); the grid's nodes stay where they were (every coarse node is a
  finer one), and the lattice stays aligned with them (`fill.Lattice`: centres at domain_min + (i +
  1/2) h), because each coarse particle's lattice cell is split into split^3 exactly: the same shape
  (the coarse fill's voxels: the dynamics' resolution changes, not the geometry), the same mass and
  centre of mass in every cell. A ratio that does not divide the cell (0.7) puts 2 or 4 finer points in
  a coarse cell unevenly and shifts the mass by up to half a spacing: an error of the refinement
  itself, present at every such level, which Richardson's extrapolation reads as convergence;
- each finer particle takes its coarse parent's values (E, nu, confidence, surface flag) and contact
  membership (a grasp, a support);
- the Gaussians bind to the finer particles as any scene's do (`Simulation`: their k nearest).

Numpy only; no USD, no CLI.
"""

from __future__ import annotations

import dataclasses
import numpy as np

REFINE = 2                # the finer grid: each cell split into REFINE^3 (cell / 2)
MAX_REFINED_PARTICLES = 2_000_000


def refine_scene(sd, split: int = REFINE, contacts=None):
    """(finer SceneData, finer contacts, parent) for `sd` (a `scene.SceneData`): the grid's cell and
    the particle lattice's spacing divided by `split` (module doc), each coarse particle's lattice cell
    split into split^3 particles at the finer lattice's points inside it (the same volume in all, so the
    mass and its centre per cell are the coarse particle's). `contacts`: the contact sets to carry over
    (default `sd.contacts`; their `indices` refer to the coarse particles); `parent[i]`: the coarse
    particle finer particle i came from, to carry any per-particle array over (`E[parent]`)."""
    m = int(split)
    if m != split or not 2 <= m <= 4:
        raise ValueError(f"the refinement must split a cell into 2, 3 or 4 per axis, got {split!r}")
    st = sd.settings
    x = np.asarray(sd.particles_positions, np.float64)
    if len(x) == 0:
        raise ValueError("the scene has no particles to refine")
    if len(x) * m ** 3 > MAX_REFINED_PARTICLES:
        raise ValueError(f"the finer scene would have {len(x) * m ** 3} particles (more than "
                         f"{MAX_REFINED_PARTICLES}): refine a coarser fit")
    h = float(st.particle_spacing)
    o = ((np.arange(m) + 0.5) / m - 0.5) * h
    off = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)          # (m^3, 3)
    pts = (x[:, None, :] + off[None]).reshape(-1, 3)
    parent = np.repeat(np.arange(len(x)), m ** 3)
    vf = np.repeat(np.asarray(sd.particles_volumes, np.float64) / m ** 3, m ** 3)
    pick = lambda arr: None if arr is None else np.asarray(arr)[parent]  # noqa: E731
    cell = float(st.cell_size) / m
    res = tuple(int(r) * m for r in st.grid_resolution)
    fine_st = dataclasses.replace(st, cell_size=cell, particle_spacing=h / m, grid_resolution=res,
                                  substeps=int(st.substeps) * m)
    cs = []
    for c in (sd.contacts if contacts is None else contacts):
        idx = np.asarray(c.indices, np.int64)
        cs.append(c.replace(indices=(idx[:, None] * m ** 3 + np.arange(m ** 3)[None]).reshape(-1)))
    fine = dataclasses.replace(sd, particles_positions=pts, particles_volumes=vf,
                               particles_surface=pick(sd.particles_surface),
                               youngs_modulus=pick(sd.youngs_modulus), poisson_ratio=pick(sd.poisson_ratio),
                               confidence=pick(sd.confidence), settings=fine_st, contacts=cs)
    return fine, cs, parent


__all__ = ["REFINE", "refine_scene"]
