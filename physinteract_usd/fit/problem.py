"""The analysis-by-synthesis problem: simulator + renderer + observations + the design's loss.

    L_total = L_rec + lambda_reg L_reg
    L_rec   = mean over frames of |I^ - I|_1 + lambda_ssim (1 - SSIM) + lambda_mask |M^ - M|_2
    L_reg   = lambda_smooth |grad log E|^2 + lambda_traj |T - T0|^2 / scale^2

with the hand's pixels left out of every image term (weight 0). No USD here: the fit gets a
`SceneData` and arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..camera import Camera
from ..render import GaussianBinding, covariance_from_scales_quats, estimate_background, render
from ..render.losses import reconstruction_loss
from ..scene import ContactSet, SceneData
from ..sim import Contact, Control, GridSpec, Rollout, SimModel


@dataclass
class Observations:
    frames: np.ndarray                 # (T, H, W, 3) float32 in [0, 1]
    masks: np.ndarray | None = None    # (T, H, W) bool object silhouettes (visible)
    hand_masks: np.ndarray | None = None  # (T, H, W) bool pixels to leave out

    @property
    def n_frames(self) -> int:
        return len(self.frames)


@dataclass
class LossWeights:
    ssim: float = 0.2
    mask: float = 1.0
    smooth: float = 3.0        # edge-aware (see fit.material.pair_weights): strong within a colour part, ~0 across
    smooth_plain: float = 0.02  # with the appearance prior off: edge-blind smoothing blurs material edges, so
                                # it stays weak (0.02 measured best without the prior on foam_bar; x15: worse)
    trajectory: float = 1.0
    depth_prior: float = 0.1   # weight of T0's depth relative to its image-plane position


@dataclass
class ContactSpec:
    """A contact as the fit uses it (from the stage, extraction or synthetic ground truth)."""

    name: str
    type: str
    indices: np.ndarray
    grasp_frame: int = 0
    release_frame: int | None = None
    trajectory: np.ndarray | None = None  # (T, 3) frames 0..T-1 (T0)
    radius: float = 0.0
    normal: tuple = (0.0, 1.0, 0.0)
    friction: float = 0.5
    source: str = "extracted"             # extracted | user | groundTruth (the stage's token)
    guessed: bool = False                 # fixed: no still region was in view (`support_layer` resizes it)

    @property
    def sized_by_fit(self) -> bool:
        """A support the extraction guessed (no still region was in view): the first fit sizes it
        (`support_layer`, `optimize.select_supports`); measured, user and true sets stay as they are."""
        return self.type == "fixed" and self.source == "extracted" and self.guessed

    @staticmethod
    def from_stage(c: ContactSet, trajectory: np.ndarray | None, n_frames: int) -> "ContactSpec":
        rel = None if c.release_time >= 1e8 or c.release_time >= n_frames else int(round(c.release_time))
        return ContactSpec(c.name, c.contact_type, np.asarray(c.particle_indices, np.int64),
                           int(round(c.grasp_time)), rel, trajectory, c.collider_radius, tuple(c.normal), c.friction,
                           str(c.source or "extracted"), bool(c.extent_guessed))


class FitProblem:
    def __init__(self, scene: SceneData, obs: Observations, contacts: list[ContactSpec], *,
                 effects: dict | None = None, device: str = "cpu", dtype: str = "float32",
                 weights: LossWeights | None = None, knn: int = 4):
        self.scene, self.obs = scene, obs
        self.device = device
        self.tdev = torch.device("cpu" if device == "cpu" else device)
        self.tdtype = torch.float32 if dtype == "float32" else torch.float64
        self.weights = weights or LossWeights()
        T = obs.n_frames
        if T < 2:
            raise ValueError("the fit needs at least 2 frames")
        self.T = T
        st = scene.settings
        self.x0 = scene.particles_positions
        self.grid = self._grid_covering(st, [c.trajectory for c in contacts if c.trajectory is not None])
        self.effects = dict(effects or {})
        self.model = SimModel.create(self.x0, scene.particles_volumes, st.density, scene.youngs_modulus.clip(
            st.youngs_min, st.youngs_max), scene.poisson_ratio.clip(1e-3, st.poisson_max), material=st.constitutive_model,
            grid=self.grid, fps=scene.fps, substeps=st.substeps, E_max=st.youngs_max, nu_max=st.poisson_max,
            gravity=st.gravity, effects=self.effects, dtype=dtype, device=device)
        self.contacts = contacts
        sim_contacts = []
        self.traj_slots = []  # (contact index in sim, T0 tensor)
        for c in contacts:
            tr = None
            if c.type != "fixed":
                if c.trajectory is None or len(c.trajectory) != T:
                    raise ValueError(f"contact {c.name}: a ({T}, 3) trajectory is needed")
                tr = np.asarray(c.trajectory, np.float64)
            if c.type in ("pointAdherent", "fixed"):
                sim_contacts.append(Contact(c.type, indices=c.indices, trajectory=tr, grasp_frame=c.grasp_frame,
                                            release_frame=c.release_frame))
            elif c.type == "pointNonAdherent":
                sim_contacts.append(Contact(c.type, trajectory=tr, radius=c.radius, shape="sphere",
                                            friction=c.friction, grasp_frame=c.grasp_frame,
                                            release_frame=c.release_frame))
            else:
                sim_contacts.append(Contact(c.type, trajectory=tr, normal=c.normal, friction=c.friction,
                                            grasp_frame=c.grasp_frame, release_frame=c.release_frame))
            if tr is not None:
                self.traj_slots.append((len(sim_contacts) - 1, torch.as_tensor(tr, dtype=self.tdtype, device=self.tdev)))
        self.control = Control(sim_contacts, n_frames=T - 1)
        self.rollout = Rollout(self.model, self.control)
        # Gaussians follow particles
        g = scene.gaussians
        self.binding = GaussianBinding.knn(g.means, self.x0, k=knn, dtype=self.tdtype, device=self.tdev)
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=self.tdtype, device=self.tdev)  # noqa: E731
        self.cov0 = covariance_from_scales_quats(t(g.scales), t(g.quats))
        self.colors = t(g.colors)
        self.opacities = t(g.opacities)
        # observations
        self.frames = t(obs.frames)
        excl = obs.hand_masks
        self.weight = t(1.0 - excl.astype(np.float32)) if excl is not None else None
        self.masks = t(obs.masks.astype(np.float32)) if obs.masks is not None else None
        cover = None
        if obs.masks is not None:
            cover = obs.masks.copy()
        if excl is not None:
            cover = excl.copy() if cover is None else (cover | excl)
        if cover is None:
            cover = self._silhouettes_at_rest()
        self.background = t(estimate_background(obs.frames, cover, dilate=2))
        self.cameras = [scene.camera.at(k) for k in range(T)]
        scale = float(np.max(np.ptp(self.x0, axis=0)))
        self.traj_scale = max(0.05 * scale, 1e-3)
        self.traj_rays = []
        for _, t0 in self.traj_slots:
            c = np.stack([self.cameras[k].position for k in range(T)])
            r = t0.cpu().numpy() - c
            r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
            self.traj_rays.append(torch.as_tensor(r, dtype=self.tdtype, device=self.tdev))

    def _grid_covering(self, st, trajectories) -> GridSpec:
        """The stage's grid, grown (same dx, same node lattice) to hold the trajectories with a
        margin of half the object's extent: the hand may lead the object out of the init domain."""
        lo = np.asarray(st.domain_min, float)
        hi = lo + np.asarray(st.grid_resolution) * st.cell_size
        if trajectories:
            ext = float(np.max(np.ptp(self.x0, axis=0)))
            pts = np.concatenate([np.asarray(t, float) for t in trajectories])
            need_lo = pts.min(0) - 0.5 * ext - np.array([0.0, 0.3 * ext, 0.0])  # room to sag
            need_hi = pts.max(0) + 0.5 * ext
            lo = lo - np.maximum(np.ceil((lo - need_lo) / st.cell_size), 0) * st.cell_size
            hi = hi + np.maximum(np.ceil((need_hi - hi) / st.cell_size), 0) * st.cell_size
        res = tuple(int(round(r)) for r in (hi - lo) / st.cell_size)
        return GridSpec(tuple(lo), st.cell_size, res)

    def held_particles(self) -> np.ndarray:
        """(P,) True for particles a fixed support holds from the first frame (the video cannot
        see their material)."""
        held = np.zeros(len(self.x0), bool)
        for c in self.contacts:
            if c.type == "fixed" and c.grasp_frame <= 0:
                held[np.asarray(c.indices, np.int64)] = True
        return held

    def particle_appearance(self, k: int = 16) -> np.ndarray:
        """(P, 3) each particle's local mean colour from the stage's Gaussians (the fit's
        appearance prior: material parts tend to differ in colour)."""
        from .material import particle_appearance

        g = self.scene.gaussians
        return particle_appearance(self.x0, g.means, g.colors, k=k)

    def gaussian_appearance(self, k: int = 16) -> np.ndarray:
        """(N, 3) each Gaussian's local mean colour (the same measure as `particle_appearance`)."""
        from .material import particle_appearance

        g = self.scene.gaussians
        return particle_appearance(g.means, g.means, g.colors, k=k)

    def _silhouettes_at_rest(self) -> np.ndarray:
        with torch.no_grad():
            out = render(torch.as_tensor(self.scene.gaussians.means, dtype=self.tdtype, device=self.tdev), self.cov0,
                         self.colors, self.opacities, self.scene.camera.at(0))
        m = out["alpha"].cpu().numpy() > 0.05
        return np.repeat(m[None], self.T, 0)

    # ------------------------------------------------------------------ forward pieces
    def initial_trajectories(self) -> list[torch.Tensor]:
        return [tr.clone() for _, tr in self.traj_slots]

    def simulate(self, E, nu, trajectories=None, effects=None):
        trajs = None
        if trajectories is not None:
            trajs = {slot: tr for (slot, _), tr in zip(self.traj_slots, trajectories)}
        return self.rollout(E.to(self.tdtype), nu.to(self.tdtype), effects=effects, trajectories=trajs)

    def gaussians_at(self, x_k, F_k):
        return self.binding.apply(x_k, F_k, self.cov0)

    def render_frame(self, k, x_k, F_k):
        means, covs = self.gaussians_at(x_k, F_k)
        return render(means, covs, self.colors, self.opacities, self.cameras[k], background=self.background)

    def frame_loss(self, k, out) -> dict:
        w = None if self.weight is None else self.weight[k]
        mask = None if self.masks is None else self.masks[k]
        return reconstruction_loss(out["rgb"], self.frames[k], w, out["alpha"] if mask is not None else None, mask,
                                   lambda_ssim=self.weights.ssim, lambda_mask=self.weights.mask)

    def loss(self, E, nu, trajectories=None, effects=None, frames=None, keep_renders=False) -> dict:
        """The reconstruction loss over `frames` (default: all but the rest frame)."""
        x, F = self.simulate(E, nu, trajectories, effects)
        ks = range(1, self.T) if frames is None else frames
        total = 0.0
        renders = {}
        for k in ks:
            out = self.render_frame(k, x[k], F[k])
            total = total + self.frame_loss(k, out)["total"]
            if keep_renders:
                renders[k] = {n: v.detach() for n, v in out.items()}
        rec = total / max(len(ks), 1)
        reg = 0.0
        if trajectories is not None and self.weights.trajectory > 0:
            for tr, (_, t0), rays in zip(trajectories, self.traj_slots, self.traj_rays):
                d = (tr - t0) / self.traj_scale
                along = (d * rays).sum(-1, keepdim=True)
                across = d - along * rays
                # T0's depth (along the camera ray) is far less certain than its image position
                reg = reg + self.weights.trajectory * ((across ** 2).sum(-1) + self.weights.depth_prior
                                                       * along[..., 0] ** 2).mean()
        return {"rec": rec, "reg_traj": reg, "x": x, "F": F, "renders": renders}


def support_layer(x0: np.ndarray, spacing: float, contacts: list, direction: str) -> list | None:
    """The contact list with every guessed `fixed` set (extracted, `guessed`: no still region was in
    view, e.g. a ball on a stand the camera never sees) one layer of particles larger (`direction`
    "more": the particles within 1.05 spacings of the set that no other contact holds) or smaller
    ("less": less the set's particles within 1.05 spacings of a particle outside it; a set keeps at
    least 3). Measured supports, and sets from the user or the ground truth, stay as they are.
    None when no set changes. The fit tells the sizes apart by what they render
    (`optimize.select_supports`)."""
    import dataclasses

    from scipy.spatial import cKDTree

    if direction not in ("more", "less"):
        raise ValueError(f"direction must be 'more' or 'less', not {direction!r}")
    P = len(x0)
    tree = cKDTree(x0)
    held_by = np.full(P, -1, np.int64)
    for j, c in enumerate(contacts):
        if c.type in ("pointAdherent", "fixed"):
            held_by[np.asarray(c.indices, np.int64)] = j
    out, changed = list(contacts), False
    for j, c in enumerate(contacts):
        if not c.sized_by_fit or len(c.indices) == 0:
            continue
        g = np.asarray(c.indices, np.int64)
        nb = tree.query_ball_point(x0[g], 1.05 * spacing)
        if direction == "more":
            near = np.unique(np.concatenate([np.asarray(n, np.int64) for n in nb]))
            new = near[held_by[near] < 0]
            idx = np.union1d(g, new)          # sorted
        else:
            inside = np.zeros(P, bool)
            inside[g] = True
            edge = np.array([bool((~inside[np.asarray(n, np.int64)]).any()) for n in nb], bool)
            idx = g[~edge] if (~edge).sum() >= 3 else g
        if len(idx) != len(g):
            out[j] = dataclasses.replace(c, indices=np.sort(idx).astype(np.int64))
            held_by[idx] = j                  # a later set does not grow into it
            changed = True
    return out if changed else None
