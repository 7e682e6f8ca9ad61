"""A Gauss-Newton step on the material field's few basis coefficients (opt-in: FitSettings.gn_steps).

Why (#24, docs/benchmarks/fit.md "foam_bar stops short"): Adam moves every coefficient by at most
about its learning rate per iteration, whatever the curvature says. A two-part object whose parts
sit 5x apart needs the soft part's bumps to travel ~1.5 in the field's logit units from the uniform
start; the suite's 20-iteration bumps level (15 iterations at lr 0.1 on a cosine) can travel ~0.8,
so it stops halfway however well the loss is conditioned. With K bumps (8), the Jacobian of the
rendered residuals is K forward simulations: a (damped) Newton step goes the whole way at once.

One step, from the current coefficients theta (the path, nu and effects held where they are):
1. the weighted residuals r0 (RGB and silhouette, per frame 1..T-1) and the total loss L0 (the
   reconstruction loss as the fit counts it, plus the smoothness term);
2. the Jacobian column of every coefficient by a one-sided finite difference (a step down, that
   moves log E by FD_STEP where the bump acts most, at the simulator's current substep: the down
   step never raises the largest E, so the rung holds), and from the same simulations the
   gradient of the reconstruction loss (its finite differences; the smoothness term's exactly);
3. a curvature model of the loss as the fit defines it: the L1 term by iteratively reweighted least
   squares (|r| <= r^2 / (2 |r0|) + |r0| / 2: weight 1 / max(|r0|, L1_FLOOR)), the silhouette's
   squared term exactly, SSIM left to the gradient, the smoothness term's Gauss-Newton matrix;
4. Levenberg-Marquardt: (H + mu diag(H)) d = -g, d capped so that no particle's log E moves by more
   than TRUST_LOG_E, tried on the true loss with mu = 1e-3, 0.1, 10 in turn until a try lowers it
   (then 2 d once, when d was well inside the cap); nothing lowers it: theta stays, "not taken".
Every simulation of a step runs at one pinned substep (the rung of the stiffest E a try may reach).
Cost: K + 2-5 forward simulations and renders, no backward: on the CPU ~3 of Adam's iterations at
K = 8 (a backward costs ~3 forwards); the caller charges it to the level's iteration budget.
Measured (docs/benchmarks/fit.md, "foam_bar stops short"): 3 steps took foam_bar (CPU, grid 24) from
MA 0.215 to 0.71; on the tests' two-part bar no step was taken (the textured residuals are linear
over a few pixels only, the quadratic model overshoots 10-30x). Opt-in; `parts_start` did better.
"""

from __future__ import annotations

import math

import torch

from ..errors import SimulationError
from .substep import pinned_substep

FD_STEP = 0.1           # log E moved by each finite-difference column where its bump acts most
L1_FLOOR = 0.02         # IRLS: residuals below this count as this (an 8-bit image's ~5 levels)
DAMPINGS = (1e-3, 1e-1, 10.0)  # Levenberg-Marquardt: mu x diag(H), raised after a try that did not lower the loss
TRUST_LOG_E = 1.0       # a step moves no particle's log E by more than this (e: 2.7x)


def _frames_residuals(prob, x, F):
    """Per frame 1..T-1: (weighted RGB residual, weighted silhouette residual or None, the frame's
    weight sum, the frame's reconstruction loss)."""
    out = []
    for k in range(1, prob.T):
        o = prob.render_frame(k, x[k], F[k])
        w = prob.weight[k] if prob.weight is not None else torch.ones_like(o["alpha"])
        r = ((o["rgb"] - prob.frames[k]) * w[..., None]).reshape(-1)
        rm = ((o["alpha"] - prob.masks[k]) * w).reshape(-1) if prob.masks is not None else None
        out.append((r, rm, float(w.sum()), float(prob.frame_loss(k, o)["total"])))
    return out


def _simulate_frames(prob, E, nu, trajs, eff):
    with torch.no_grad():
        x, F = prob.simulate(E, nu, trajs, eff)
        return _frames_residuals(prob, x, F)


def gauss_newton_step(prob, mat, nu, trajs, eff, reg_fn, reg_traj: float = 0.0, log=None) -> dict:
    """One damped Gauss-Newton step on `mat.theta` (module doc), every simulation of it at one
    substep: the rung of the stiffest field a try may reach (the adaptive substep's rung, and the
    loss with it, would otherwise move between the base and the tries by more than a step gains)."""
    with torch.no_grad():
        e_top = float(mat.youngs().max()) * math.exp(TRUST_LOG_E)
    e_top = min(e_top, math.exp(mat.hi))
    with pinned_substep(prob, e_top):
        return _step(prob, mat, nu, trajs, eff, reg_fn, reg_traj, log)


def _step(prob, mat, nu, trajs, eff, reg_fn, reg_traj: float = 0.0, log=None) -> dict:
    """One damped Gauss-Newton step on `mat.theta` (in place when it lowers the total loss).
    `reg_fn()`: the smoothness term of the current field (a torch scalar, differentiable in
    mat.theta); `reg_traj`: the path prior's value (constant here). Returns {"loss0", "loss",
    "accepted", "alpha", "forwards", "step_norm"}."""
    theta0 = mat.theta.detach().clone()
    K = int(theta0.numel())
    n_frames = max(prob.T - 1, 1)
    C = 3
    forwards = 0

    def rec_of(res):
        return sum(f[3] for f in res) / n_frames

    def reg_at(theta):
        mat.theta = theta.detach().clone().requires_grad_(True)
        v = reg_fn()
        return mat.theta, v

    def total_at(theta):
        nonlocal forwards
        mat.theta = theta.detach().clone()
        forwards += 1
        try:
            res = _simulate_frames(prob, mat.youngs().detach(), nu, trajs, eff)
        except SimulationError:
            return float("inf")
        with torch.no_grad():
            rg = float(reg_fn()) if reg_fn is not None else 0.0
        return rec_of(res) + rg + reg_traj

    # 1. the base
    with torch.no_grad():
        E0 = mat.youngs().detach()
    substeps = getattr(prob.sim, "substeps", None)
    base = _simulate_frames(prob, E0, nu, trajs, eff)
    forwards += 1
    th, rg0 = reg_at(theta0)
    g_reg = torch.autograd.grad(rg0, th)[0].detach() if rg0.requires_grad else torch.zeros_like(theta0)
    # the smoothness term's Gauss-Newton matrix: rg = sum_p rho_p^2, H = 2 J_rho^T J_rho (J by autograd)
    if rg0.requires_grad and float(rg0.detach()) > 0:
        def rho(t):
            mat.theta = t
            return reg_fn(residuals=True)
        Jr = torch.autograd.functional.jacobian(rho, theta0.clone())
        H_reg = 2.0 * (Jr.T @ Jr)
    else:
        H_reg = torch.zeros(K, K, dtype=theta0.dtype, device=theta0.device)
    L0 = rec_of(base) + float(rg0.detach()) + reg_traj

    # 2. the Jacobian columns and the reconstruction loss' gradient, by finite differences (down)
    with torch.no_grad():
        mat.theta = theta0.clone()
        s_ = torch.sigmoid(mat.u())
        dlog = (mat.hi - mat.lo) * s_ * (1 - s_)
        reach = (mat.B.abs() * dlog[:, None]).amax(0)
    r0 = torch.cat([f[0] for f in base]).double()
    m0 = torch.cat([f[1] for f in base]).double() if base[0][1] is not None else None
    # per-residual curvature weights of the loss (1 / N per frame, IRLS for L1, 2 lambda_mask for the mask)
    w_rgb = torch.cat([torch.full((len(f[0]),), 1.0 / (C * max(f[2], 1e-12) * n_frames), dtype=torch.float64,
                                  device=r0.device) for f in base])
    w_rgb = w_rgb / r0.abs().clamp_min(L1_FLOOR)
    if m0 is not None:
        w_m = torch.cat([torch.full((len(f[1]),), 2.0 * prob.weights.mask / (max(f[2], 1e-12) * n_frames),
                                    dtype=torch.float64, device=r0.device) for f in base])
    J = torch.zeros(len(r0), K, dtype=torch.float64, device=r0.device)
    Jm = torch.zeros(len(m0), K, dtype=torch.float64, device=r0.device) if m0 is not None else None
    g = torch.zeros(K, dtype=torch.float64, device=r0.device)
    try:
        for k in range(K):
            h = float(min(FD_STEP / max(float(reach[k]), 1e-12), 1.0))
            t = theta0.clone()
            t[k] -= h
            mat.theta = t
            forwards += 1
            res = _simulate_frames(prob, mat.youngs().detach(), nu, trajs, eff)
            if getattr(prob.sim, "substeps", None) != substeps:
                raise SimulationError("the substep changed under a finite-difference column")
            J[:, k] = (r0 - torch.cat([f[0] for f in res]).double()) / h
            if Jm is not None:
                Jm[:, k] = (m0 - torch.cat([f[1] for f in res]).double()) / h
            g[k] = (rec_of(base) - rec_of(res)) / h
    except SimulationError as exc:
        mat.theta = theta0.clone().requires_grad_(True)
        if log:
            log(f"Gauss-Newton step skipped: {exc}")
        return {"loss0": L0, "loss": L0, "accepted": False, "alpha": 0.0, "forwards": forwards, "step_norm": 0.0}
    g = g + g_reg.double()
    H = J.T @ (w_rgb[:, None] * J)
    if Jm is not None:
        H = H + Jm.T @ (w_m[:, None] * Jm)
    H = H + H_reg.double()
    # 3.-4. Levenberg-Marquardt: the damped direction, capped to a trust region in log E, tried on
    # the true loss; a failed try raises the damping (towards a scaled gradient step)
    dg = torch.diagonal(H).clamp_min(1e-9 * float(torch.trace(H)) + 1e-30)
    Bd = (mat.B.double() * dlog.double()[:, None])            # d log E_p / d theta_k
    tried = {}
    best = (0.0, L0, None)
    for mu in DAMPINGS:
        try:
            d = -torch.linalg.solve(H + mu * torch.diag(dg), g)
        except RuntimeError:
            continue
        if not bool(torch.isfinite(d).all()):
            continue
        reach_d = float((Bd @ d).abs().max())
        if reach_d > TRUST_LOG_E:
            d = d * (TRUST_LOG_E / reach_d)
        d = d.to(theta0.dtype)
        v = total_at(theta0 + d)
        tried[f"mu{mu:g}"] = v
        if v < best[1]:
            best = (1.0, v, d)
            if reach_d < 0.5 * TRUST_LOG_E:   # room to go further along it
                v2 = total_at(theta0 + 2 * d)
                tried[f"mu{mu:g}x2"] = v2
                if v2 < v:
                    best = (2.0, v2, d)
            break
    accepted = best[2] is not None
    mat.theta = (theta0 + best[0] * best[2] if accepted else theta0).clone().requires_grad_(True)
    step_norm = float(best[2].norm()) * best[0] if accepted else 0.0
    if log:
        log(f"Gauss-Newton step: loss {L0:.5f} -> {best[1]:.5f} (tried {', '.join(f'{k} {v:.5f}' for k, v in tried.items())}; "
            f"{forwards} forwards){'' if accepted else ': not taken'}")
    return {"loss0": L0, "loss": float(best[1]), "accepted": bool(accepted), "alpha": best[0],
            "forwards": forwards, "step_norm": step_norm, "tried": tried}


def forwards_to_iterations(forwards: int, backward_per_forward: float) -> int:
    """The iterations of a gradient loop the same simulations cost (one iteration: a forward and a
    backward)."""
    return max(1, int(math.ceil(forwards / (1.0 + backward_per_forward))))


__all__ = ["gauss_newton_step", "forwards_to_iterations", "FD_STEP", "L1_FLOOR"]
