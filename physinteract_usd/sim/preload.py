"""Preload: the stress a scanned object carries at rest on its supports (#23).

A scan shows the object as it hangs or rests, already sagged under gravity. Simulated from that shape stress-free it
sags again, and a fit stiffens E to stop it (6-21x too stiff on settled captures: docs/benchmarks/world.md). Here the
model starts prestressed instead: at frame 0 every grid node the supports do not hold is in balance, so the scan stays
where it is at any E, and only the interaction moves it.

Two steps:

1. `equilibrium_stress`: the Kirchhoff stress field tau (P, 3, 3) that balances gravity at the scan, on the simulator's
   own discretisation (MLS-MPM: node i's force is -sum_p w_ip V_p (4 / dx^2) tau_p (x_i - x_p)). The balance is
   linear in tau and under-determined; of the stresses that satisfy it the one of least complementary energy
   sum_p V_p (|dev tau_p|^2 / 4 mu + (tr tau_p)^2 / 18 K) is taken: the discrete linear-elastic solution (its Lagrange
   multipliers are the nodes' displacements, and tau = C : sym grad u). It depends on Poisson's ratio only, not on
   E (for a uniform field), so it is solved once.
2. `preload_F`: per particle, the symmetric stretch V with tau(V; E, nu) = tau_p (fixed-corotated: 2 mu (V - I) V
   + lam (J - 1) J I; neo-Hookean: mu (V V^T - I) + lam log J I), solved in tau's eigenbasis by Newton, as a torch
   function of E and nu (the implicit-function gradient: one Newton step taken with gradients at the solution).
   Rotation does not matter: tau(V R) = tau(V).

The rollout takes it as `F0`. What holds the object: the supports (fixed contacts) active at frame 0, at the nodes they
pin fully (the pin rule at weight 1; a grasp from frame 0 carries no weight: the hand took hold of an object at rest)
and, with the ground effect on the grid nodes, nodes at least half a band under the plane (weight 1); colliders do
not hold it. A partly held node must balance (a blend below 1 lets a residual velocity through).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from .control import Control
from .model import MATERIALS, SimModel


@dataclass(frozen=True)
class Prestress:
    """The stress that holds a scan at rest (`equilibrium_stress`)."""

    tau: np.ndarray           # (P, 3, 3) Kirchhoff stress [Pa]
    eigvecs: np.ndarray       # (P, 3, 3) tau's eigenvectors (columns)
    eigvals: np.ndarray       # (P, 3) tau's eigenvalues [Pa]
    residual: float           # the unbalanced force left / the object's weight (0: exact balance)
    held_nodes: int           # grid nodes the supports hold
    free_nodes: int           # grid nodes that had to balance
    nu: float                 # the Poisson ratio the least-energy stress was weighted with

    @property
    def peak(self) -> float:
        """The largest principal stress magnitude [Pa]."""
        return float(np.abs(self.eigvals).max()) if self.eigvals.size else 0.0


# an orthonormal (Frobenius) basis of the symmetric 3x3 matrices: 5 deviatoric, then I / sqrt(3)
def _basis() -> np.ndarray:
    s2, s6 = np.sqrt(2.0), np.sqrt(6.0)
    B = np.zeros((6, 3, 3))
    B[0] = np.diag([1.0, -1.0, 0.0]) / s2
    B[1] = np.diag([1.0, 1.0, -2.0]) / s6
    for n, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        B[2 + n, a, b] = B[2 + n, b, a] = 1.0 / s2
    B[5] = np.eye(3) / np.sqrt(3.0)
    return B


_B = _basis()


def _weights(f: np.ndarray):
    """Quadratic B-spline weights (P, 3 axes, 3 nodes) at the fractional offsets f (P, 3) (kernels.bw)."""
    return np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)


def _held_nodes(model: SimModel, control: Control, node: np.ndarray, w: np.ndarray, mass_node: np.ndarray,
                xn_y: np.ndarray) -> np.ndarray:
    """(N,) True where frame 0's supports hold a node outright (the grid update's pin and ground rules at weight 1)."""
    N = mass_node.size
    held = np.zeros(N, bool)
    P = model.n_particles
    pm = np.zeros(N)
    sm = np.zeros(N)
    pinned = np.zeros(P, bool)
    support = np.zeros(P, bool)
    for i in control.pins:
        c = control.contacts[i]
        # a support's (a fixed contact's), not a grasp's: a hand that holds from frame 0 took hold of an object
        # already at rest, and carries none of its weight
        if c.type == "fixed" and c.active_mask(control.n_frames)[0]:
            pinned[c.indices] = True
            support[c.indices] = True
    m = model.mass
    np.add.at(pm, node[pinned].ravel(), (w[pinned] * m[pinned, None]).ravel())
    np.add.at(sm, node[support].ravel(), (w[support] * m[support, None]).ravel())
    sg, sf = model.support_rule
    has = pm > 0
    ks = np.where(has, sm / np.where(has, pm, 1.0), 0.0)
    gain = model.pin_gain + ks * (sg - model.pin_gain)
    floor = model.pin_floor + ks * (sf - model.pin_floor)
    share = np.where(mass_node > 0, pm / np.where(mass_node > 0, mass_node, 1.0), 0.0)
    held |= has & (gain * (share - floor) >= 1.0)
    if "ground" in model.effects:
        if model.ground_contact != "nodes":
            raise ValueError("preload: the ground acts at the grid nodes only (ground_contact 'nodes'), "
                             f"not {model.ground_contact!r}")
        h = model.effects.params["ground"]["height"]
        band = model.contact_band
        held |= (xn_y - h <= -0.5 * band) if band > 0 else (xn_y - h < 0)
    return held


def equilibrium_stress(model: SimModel, control: Control, nu: float | None = None, *, atol: float = 1e-10,
                       iter_lim: int | None = None) -> Prestress:
    """The least-complementary-energy Kirchhoff stress (P, 3, 3) that holds `model`'s particles at rest at their
    positions under gravity, on the supports `control` has at frame 0 (module doc). `nu`: the Poisson ratio the
    energy is weighted with (default: the model's mean). Raises ValueError where nothing holds the object (no node
    held: its weight cannot be balanced)."""
    from scipy.sparse import coo_matrix, identity
    from scipy.sparse.linalg import lsqr, spsolve

    if model.material not in MATERIALS:
        raise ValueError(f"preload: unknown material {model.material!r}")
    g = model.grid
    dx = g.dx
    lo = np.asarray(g.lower)
    res = np.asarray(g.resolution)
    x = np.asarray(model.x0, np.float64)
    P = len(x)
    xp = (x - lo) / dx
    base = np.clip(np.floor(xp - 0.5).astype(np.int64), 0, res - 3)
    f = xp - base
    wa = _weights(f)                                          # (P, 3, 3)
    off = np.stack(np.meshgrid(np.arange(3), np.arange(3), np.arange(3), indexing="ij"), -1).reshape(27, 3)
    w = wa[:, 0, off[:, 0]] * wa[:, 1, off[:, 1]] * wa[:, 2, off[:, 2]]     # (P, 27)
    ijk = base[:, None, :] + off[None]                        # (P, 27, 3)
    node = (ijk[..., 0] * res[1] + ijk[..., 1]) * res[2] + ijk[..., 2]      # the solver's flat index
    d = (off[None].astype(np.float64) - f[:, None, :]) * dx   # (P, 27, 3): x_i - x_p
    m = model.mass
    uniq, inv = np.unique(node.ravel(), return_inverse=True)
    inv = inv.reshape(P, 27)
    N = uniq.size
    mass_node = np.zeros(N)
    np.add.at(mass_node, inv.ravel(), (w * m[:, None]).ravel())
    xn_y = lo[1] + ((uniq // res[2]) % res[1]) * dx
    held = _held_nodes(model, control, inv, w, mass_node, xn_y)
    m_eps = 1e-9 * float(np.min(m))
    free = (~held) & (mass_node > m_eps)
    if not held.any():
        raise ValueError("preload: nothing holds the object at frame 0 (no support, no ground under it): "
                         "its weight cannot be balanced")
    nu_w = float(np.mean(model.nu) if nu is None else nu)
    # the weighting: tau_p = sum_c z_pc s_pc B_c, |z|^2 the complementary energy (mu = 1; only the ratio matters)
    K = 2.0 * (1.0 + nu_w) / (3.0 * (1.0 - 2.0 * nu_w))      # bulk / shear modulus
    s_c = np.array([2.0] * 5 + [np.sqrt(6.0 * K)])
    scale = s_c[None, :] / np.sqrt(model.volume)[:, None]     # (P, 6)
    # node i, axis a: sum_p w V (4/dx^2) (tau_p d)_a = m_i g_a ; (tau d)_a = sum_c z_c s_c (B_c d)_a
    Bd = np.einsum("cab,pkb->pkca", _B, d)                   # (P, 27, 6, 3)
    coef = (w * model.volume[:, None] * 4.0 / dx ** 2)[:, :, None, None] * Bd * scale[:, None, :, None]
    rows_n = np.broadcast_to(inv[:, :, None, None], coef.shape)
    axis = np.broadcast_to(np.arange(3)[None, None, None, :], coef.shape)
    cols = np.broadcast_to((6 * np.arange(P))[:, None, None, None] + np.arange(6)[None, None, :, None], coef.shape)
    keep = free[rows_n] & (coef != 0)
    row_of = -np.ones(N, np.int64)
    row_of[free] = np.arange(int(free.sum()))
    r = 3 * row_of[rows_n[keep]] + axis[keep]
    A = coo_matrix((coef[keep], (r, cols[keep])), shape=(3 * int(free.sum()), 6 * P)).tocsr()
    b = (mass_node[free][:, None] * np.asarray(model.gravity)[None, :]).ravel()
    # the least-norm z = A^T (A A^T)^-1 b: A A^T is the free nodes' stiffness (the multipliers are their displacements),
    # sparse and small (3 per node): a direct solve, damped by 1e-9 of its mean diagonal (a node only a particle's
    # stencil edge reaches can be out of balance: the least-squares balance there, Tikhonov's); lsqr where it fails
    K = (A @ A.T).tocsc()
    K = K + identity(K.shape[0], format="csc") * (1e-9 * float(K.diagonal().mean()))
    zf = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            u = spsolve(K, b)
            zf = A.T @ u if np.all(np.isfinite(u)) else None
        except RuntimeError:
            zf = None
    if zf is None:
        zf = lsqr(A, b, atol=atol, btol=atol, iter_lim=iter_lim or 20 * A.shape[1])[0]
    z = zf.reshape(P, 6)
    tau = np.einsum("pc,cab->pab", z * scale, _B)
    weight = float(m.sum() * np.linalg.norm(model.gravity))
    resid = float(np.linalg.norm((A @ zf - b).reshape(-1, 3), axis=1).sum() / max(weight, 1e-300))
    t, Q = np.linalg.eigh(tau)
    return Prestress(tau=tau, eigvecs=Q, eigvals=t, residual=resid, held_nodes=int(held.sum()),
                     free_nodes=int(free.sum()), nu=nu_w)


def _stress_eigs(s: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, material: str):
    """Kirchhoff principal stresses (P, 3) of principal stretches s (P, 3), and their Jacobian d tau_i / d s_j."""
    J = s.prod(-1, keepdim=True)
    if material == "neoHookean":
        t = mu[:, None] * (s * s - 1.0) + lam[:, None] * torch.log(J)
        diag = 2.0 * mu[:, None] * s
        vol = lam[:, None, None] / s[:, None, :]
    else:
        t = 2.0 * mu[:, None] * (s - 1.0) * s + lam[:, None] * (J - 1.0) * J
        diag = 2.0 * mu[:, None] * (2.0 * s - 1.0)
        vol = (lam[:, None] * (2.0 * J - 1.0) * J)[:, :, None] / s[:, None, :]
    jac = torch.diag_embed(diag) + vol.expand(-1, 3, 3)
    return t, jac


def preload_F(pre: Prestress, E, nu, material: str = "fixedCorotated", *, iters: int = 30) -> torch.Tensor:
    """F0 (P, 3, 3): the symmetric stretch whose Kirchhoff stress at (E, nu) (per particle, tensors: differentiable)
    is `pre.tau`. Where the material cannot carry that stress (a fixed-corotated stretch pressed past half its
    length) the stretch stops at the limit. dtype and device follow E."""
    E = torch.as_tensor(E)
    dt_, dev = E.dtype, E.device
    P = pre.tau.shape[0]
    E = E.expand(P) if E.dim() == 0 else E
    nu = torch.as_tensor(nu, dtype=dt_, device=dev)
    nu = nu.expand(P) if nu.dim() == 0 else nu
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    t = torch.as_tensor(pre.eigvals, dtype=torch.float64, device=dev)
    Q = torch.as_tensor(pre.eigvecs, dtype=dt_, device=dev)
    smin = 0.5 + 1e-3 if material != "neoHookean" else 1e-3
    with torch.no_grad():
        mu_d, lam_d = mu.detach().double(), lam.detach().double()
        # the linear guess: 2 mu eps + lam tr(eps) = t
        eps = (t - (lam_d / (2.0 * mu_d + 3.0 * lam_d))[:, None] * t.sum(-1, keepdim=True)) / (2.0 * mu_d[:, None])
        s = (1.0 + eps).clamp(min=smin)
        for _ in range(iters):
            r, jac = _stress_eigs(s, mu_d, lam_d, material)
            step = torch.linalg.solve(jac, (r - t).unsqueeze(-1)).squeeze(-1)
            s_new = (s - step).clamp(min=smin)
            done = bool((s_new - s).abs().max() < 1e-13)
            s = s_new
            if done:
                break
    # one Newton step with gradients at the solution: ds/d(E, nu) = -jac^-1 d tau / d(E, nu) (implicit function)
    s = s.to(dt_)
    r, jac = _stress_eigs(s, mu, lam, material)
    step = torch.linalg.solve(jac.detach(), (r - t.to(dt_)).unsqueeze(-1)).squeeze(-1)
    s = s - step + step.detach()          # the value stays the solution (or its limit), the gradient the step's
    return Q @ torch.diag_embed(s) @ Q.transpose(-1, -2)
