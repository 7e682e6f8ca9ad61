"""Several rollouts of one scene in one: copies of a model side by side on one grid.

MLS-MPM particles interact only through the grid nodes of their 3x3x3 stencils, so copies of a
scene placed on adjacent copies of its grid, each inside its own copy's valid box, never touch:
one rollout of the tiled model is B independent rollouts that share every kernel launch. On a
GPU, where a small scene's substep is bound by launch latency, B probes (a sweep of uniform E, the
starts of a multi-start fit) then cost about one. Each copy has its own per-particle E and nu (the
rollout's inputs are per particle already); effects are shared; the contacts are repeated per copy,
their trajectories shifted with the copy.

    tiled = tile(model, control, copies=8)
    ro = Rollout(tiled.model, tiled.control)
    x, F = ro(tiled.stack(E_b), tiled.stack(nu_b), trajectories=tiled.trajectories(trajs))
    xb = tiled.split(x)             # (B, T+1, P, 3), each copy back in the scene's coordinates

Limits (`TilingError` says which): copies are laid along a horizontal axis (perpendicular to
gravity, so a `ground` plane y = h is the same plane for every copy); a surfaceNonAdherent plane is
infinite, so its normal must be perpendicular to that axis too; colliders per rollout are capped
(kernels.MAX_COLLIDERS), so a scene with colliders takes at most MAX_COLLIDERS // n copies. A copy
whose particles leave its own valid box would leak into its neighbour: `escaped(x)` reports it
(the rollout's own check only knows the whole grid).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from .control import Contact, Control
from .kernels import MAX_COLLIDERS
from .model import GridSpec, SimModel


class TilingError(ValueError):
    """The scene cannot be tiled into independent copies (see the module's limits)."""


def max_copies(control: Control) -> int:
    """How many copies of `control` one rollout can hold (colliders are capped per rollout)."""
    n = len(control.colliders)
    return MAX_COLLIDERS // n if n else 1 << 30


def tiling_axis(model: SimModel, control: Control) -> int:
    """The axis copies are laid along: perpendicular to gravity and to every collider plane's
    normal, the one of those with the fewest grid nodes."""
    g = np.asarray(model.gravity, float)
    ok = []
    for a in range(3):
        if abs(g[a]) > 1e-12 * max(1.0, float(np.linalg.norm(g))):
            continue
        if any(c.type == "surfaceNonAdherent" and abs(float(np.asarray(c.normal, float)[a])) > 1e-9
               for c in control.contacts):
            continue
        ok.append(a)
    if not ok:
        raise TilingError("no axis is perpendicular to gravity and to every contact plane's normal: the copies "
                          "would share a plane")
    return min(ok, key=lambda a: model.grid.resolution[a])


@dataclass(frozen=True)
class Tiled:
    model: SimModel           # the B copies as one model
    control: Control          # the contacts of every copy (copy b's contact i is b * n_contacts + i)
    copies: int
    axis: int
    n_particles: int          # per copy
    n_contacts: int           # per copy
    base: SimModel            # the scene's own model

    @property
    def shift(self) -> float:
        """Distance [m] between neighbouring copies along `axis`."""
        return self.base.grid.resolution[self.axis] * self.base.grid.dx

    def offsets(self, like: torch.Tensor | None = None):
        """(B, 3) the copies' shifts (numpy, or a tensor like `like`)."""
        off = np.zeros((self.copies, 3))
        off[:, self.axis] = np.arange(self.copies) * self.shift
        if like is None:
            return off
        return torch.as_tensor(off, dtype=like.dtype, device=like.device)

    def stack(self, values) -> torch.Tensor:
        """Per-copy per-particle values (B, P) (or (B,) / (P,) broadcast) -> (B * P,)."""
        v = torch.as_tensor(values)
        B, P = self.copies, self.n_particles
        if v.dim() == 0:
            v = v.expand(B, P)
        elif v.dim() == 1 and v.shape[0] == B and B != P:
            v = v[:, None].expand(B, P)
        elif v.dim() == 1:
            v = v[None].expand(B, P)
        if tuple(v.shape) != (B, P):
            raise ValueError(f"expected per-copy values of shape ({B}, {P}), got {tuple(v.shape)}")
        return v.reshape(B * P)

    def trajectories(self, trajectories: dict | None, like: torch.Tensor | None = None) -> dict | None:
        """{contact index: (T+1, 3)} of the scene (shared by the copies, or {i: (B, T+1, 3)} per
        copy) -> the tiled control's {index: (T+1, 3)}, each shifted with its copy."""
        if not trajectories:
            return None
        out = {}
        for i, tr in trajectories.items():
            tr = torch.as_tensor(tr) if like is None else torch.as_tensor(tr, dtype=like.dtype, device=like.device)
            off = self.offsets(tr)
            for b in range(self.copies):
                tb = tr[b] if tr.dim() == 3 else tr
                out[b * self.n_contacts + int(i)] = tb + off[b]
        return out

    def split(self, x: torch.Tensor) -> torch.Tensor:
        """(T+1, B * P, ...) -> (B, T+1, P, ...); positions (last dim 3, not matrices) shifted back."""
        B, P = self.copies, self.n_particles
        y = x.reshape(x.shape[0], B, P, *x.shape[2:]).transpose(0, 1)
        if x.dim() == 3:
            y = y - self.offsets(x)[:, None, None, :]
        return y

    def escaped(self, x_split: torch.Tensor) -> np.ndarray:
        """(B,) True for copies with a particle outside their own valid box at some frame (their
        rollout is not independent of the neighbours': discard it)."""
        lo = torch.as_tensor(self.base.grid.valid_lower, dtype=x_split.dtype, device=x_split.device)
        hi = torch.as_tensor(self.base.grid.valid_upper, dtype=x_split.dtype, device=x_split.device)
        bad = ((x_split < lo) | (x_split >= hi) | ~torch.isfinite(x_split)).flatten(1).any(1)
        return bad.cpu().numpy()


def tile(model: SimModel, control: Control, copies: int, axis: int | None = None) -> Tiled:
    """`copies` copies of (model, control) side by side on adjacent copies of the model's grid."""
    B = int(copies)
    if B < 1:
        raise ValueError("copies must be >= 1")
    if B > max_copies(control):
        raise TilingError(f"{B} copies of {len(control.colliders)} colliders exceed the {MAX_COLLIDERS} colliders "
                          "a rollout holds")
    a = tiling_axis(model, control) if axis is None else int(axis)
    g = model.grid
    res = list(g.resolution)
    shift = res[a] * g.dx
    res[a] *= B
    grid = GridSpec(g.lower, g.dx, tuple(res))
    P = model.n_particles
    off = np.zeros((B, 3))
    off[:, a] = np.arange(B) * shift
    x0 = (model.x0[None] + off[:, None]).reshape(B * P, 3)
    rep = lambda v: np.tile(np.asarray(v), B)  # noqa: E731
    tiled_model = SimModel(
        x0=x0, volume=rep(model.volume), density=model.density, E=rep(model.E), nu=rep(model.nu),
        material=model.material, grid=grid, fps=model.fps, substeps=model.substeps, gravity=model.gravity,
        effects=model.effects, dtype=model.dtype, device=model.device, E_max=model.E_max, nu_max=model.nu_max,
        contact_band=model.contact_band, pin_gain=model.pin_gain, blend_dt=model.blend_dt,
        pin_floor=model.pin_floor, transfer_tau=model.transfer_tau, stencil_check=model.stencil_check,
        ground_contact=model.ground_contact, support_gain=model.support_gain, support_floor=model.support_floor)
    contacts = []
    for b in range(B):
        for c in control.contacts:
            tr = c.trajectory
            if tr is not None:
                tr = (tr.detach().cpu().double().numpy() if torch.is_tensor(tr) else np.asarray(tr, float)) + off[b]
            contacts.append(replace(c, indices=None if c.indices is None else np.asarray(c.indices) + b * P,
                                    trajectory=tr))
    tiled_control = Control(contacts, n_frames=control.n_frames)
    return Tiled(tiled_model, tiled_control, B, a, P, len(control.contacts), model)


__all__ = ["Tiled", "TilingError", "tile", "tiling_axis", "max_copies"]
