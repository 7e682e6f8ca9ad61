"""Grid nodes that a particle's quadratic stencil only grazes (weight ~1e-13) carry a vanishing
mass; velocity = momentum / mass there has an adjoint ~1/mass that overflowed to inf * 0 = NaN in
float32 and poisoned every gradient of a fit. The solver leaves such nodes empty."""

import numpy as np
import torch

from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel


def _rollout(m_eps=None):
    dx = 0.04
    # particles on a lattice whose outer layer sits 1e-6 dx past a half-cell: the next node out
    # gets a B-spline weight 0.5 (1e-6)^2 from them and nothing from anyone else
    idx = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(6), indexing="ij"), -1).reshape(-1, 3)
    x0 = (idx * 0.5 + 5.5 + 1e-6) * dx
    P = len(x0)
    grid = GridSpec((0.0, 0.0, 0.0), dx, (20, 20, 20))
    m = SimModel.create(x0, (0.5 * dx) ** 3, 150.0, 1e4, 0.3, grid=grid, fps=20, substeps=30, E_max=2e4)
    top = np.where(x0[:, 1] > x0[:, 1].max() - 1e-9)[0]
    side = np.where(x0[:, 0] < x0[:, 0].min() + 1e-9)[0]
    side = np.setdiff1d(side, top)
    T = 4
    traj = x0[side].mean(0) + np.outer(np.linspace(0, 1, T + 1), [0.02, 0.01, 0.0])
    ctrl = Control([Contact("fixed", indices=top), Contact("pointAdherent", indices=side, trajectory=traj)], n_frames=T)
    ro = Rollout(m, ctrl)
    if m_eps is not None:
        ro.solver.m_eps = m_eps
    E = torch.full((P,), 1e4, requires_grad=True)
    nu = torch.full((P,), 0.3, requires_grad=True)
    x, F = ro(E, nu)
    (x[-1].sum() + F[-1].sum()).backward()
    return E.grad, nu.grad


def test_grazing_nodes_keep_gradients_finite():
    gE, gnu = _rollout()
    assert torch.isfinite(gE).all() and torch.isfinite(gnu).all()
    assert gE.abs().max() > 0


def test_without_the_mass_floor_they_would_not_be():
    """The same rollout with the floor switched off: the failure the floor prevents is real here."""
    gE, gnu = _rollout(m_eps=0.0)
    assert not (torch.isfinite(gE).all() and torch.isfinite(gnu).all())
