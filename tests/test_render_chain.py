"""Renderer and a (toy) simulator chained in one autograd graph: gradients of an image loss reach
the simulation parameters, match finite differences, and a few optimiser steps recover them."""

import numpy as np
import pytest
import torch

from physinteract_usd.camera import Camera
from physinteract_usd.render import (GaussianBinding, covariance_from_scales_quats, l1_loss, render,
                                     silhouette_loss, ssim)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


class ToySim(torch.autograd.Function):
    """Stands in for the MPM op: particles move x = X0 + v t and deform F = I + t A, with a
    hand-written backward (as a Warp op would have)."""

    @staticmethod
    def forward(ctx, v, A, X0, t):
        ctx.t = t
        ctx.save_for_backward(X0)
        P = X0.shape[0]
        eye = torch.eye(3, dtype=v.dtype)
        return X0 + v * t, (eye + t * A).expand(P, 3, 3).clone()

    @staticmethod
    def backward(ctx, gx, gF):
        t = ctx.t
        return gx.sum(0) * t, gF.sum(0) * t, None, None


def _scene():
    g = torch.Generator().manual_seed(0)
    X0 = (torch.rand(60, 3, generator=g, dtype=torch.float64) - 0.5) * 0.4
    cols = torch.rand(60, 3, generator=g, dtype=torch.float64)
    cov0 = covariance_from_scales_quats(torch.full((60, 3), 0.03, dtype=torch.float64),
                                        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(60, 4))
    op = torch.full((60,), 0.8, dtype=torch.float64)
    cam = Camera.look_at([0.2, 0.3, 1.6], [0, 0, 0], width=40, height=32, fov_y_deg=45)
    bind = GaussianBinding.from_index(np.arange(60), X0.numpy(), X0.numpy(), dtype=torch.float64)
    return X0, cols, cov0, op, cam, bind


def _frames(v, A, scene, times=(0.5, 1.0)):
    X0, cols, cov0, op, cam, bind = scene
    outs = []
    for t in times:
        x, F = ToySim.apply(v, A, X0, t)
        means, covs = bind.apply(x, F, cov0)
        outs.append(render(means, covs, cols, op, cam, background=torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)))
    return outs


def _loss(v, A, scene, targets):
    total = 0.0
    for o, tg in zip(_frames(v, A, scene), targets):
        total = total + l1_loss(o["rgb"], tg["rgb"]) + 0.2 * (1 - ssim(o["rgb"], tg["rgb"])) \
            + silhouette_loss(o["alpha"], tg["alpha"])
    return total


def test_gradients_reach_simulation_parameters():
    scene = _scene()
    v_true = torch.tensor([0.05, -0.03, 0.02], dtype=torch.float64)
    A_true = torch.tensor([[0.2, 0.05, 0], [0, -0.1, 0], [0, 0, 0.1]], dtype=torch.float64)
    with torch.no_grad():
        targets = [{k: o[k].detach() for k in ("rgb", "alpha")} for o in _frames(v_true, A_true, scene)]
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    A = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    _loss(v, A, scene, targets).backward()
    # central differences on the chained function
    for p, grad in ((v, v.grad), (A, A.grad)):
        flat = p.detach().clone().view(-1)
        for i in range(flat.numel()):
            h = 1e-6
            vals = []
            for s in (h, -h):
                q = flat.clone()
                q[i] += s
                args = (q.view(p.shape), A.detach()) if p is v else (v.detach(), q.view(p.shape))
                with torch.no_grad():
                    vals.append(float(_loss(*args, scene, targets)))
            fd = (vals[0] - vals[1]) / (2 * h)
            assert abs(fd - float(grad.view(-1)[i])) <= 1e-3 * abs(fd) + 1e-6, (i, fd, float(grad.view(-1)[i]))


def test_a_few_adam_steps_recover_the_motion():
    scene = _scene()
    v_true = torch.tensor([0.06, -0.04, 0.0], dtype=torch.float64)
    A0 = torch.zeros(3, 3, dtype=torch.float64)
    with torch.no_grad():
        targets = [{k: o[k].detach() for k in ("rgb", "alpha")} for o in _frames(v_true, A0, scene)]
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([v], lr=0.01)
    first = None
    for _ in range(60):
        opt.zero_grad()
        loss = _loss(v, A0, scene, targets)
        first = first if first is not None else loss.item()
        loss.backward()
        opt.step()
    assert loss.item() < 0.1 * first
    assert float((v.detach() - v_true)[:2].abs().max()) < 0.01
