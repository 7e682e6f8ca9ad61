"""The analysis-by-synthesis problem: simulator + renderer + observations + the design's loss.

    L_total = L_rec + lambda_reg L_reg
    L_rec   = mean over frames of |I^ - I|_1 + lambda_ssim (1 - SSIM) + lambda_mask |M^ - M|_2
    L_reg   = lambda_smooth |grad log E|^2 + lambda_traj L_traj

L_traj is a Gaussian prior of the hand path T about the measured one T0 in the measurement's own
units (`FitProblem.trajectory_prior`): per frame k, across the camera ray sigma_k = sigma_px x
depth_k / focal_px (the path's pixel uncertainty at the contact's depth), along it
sigma_k / sqrt(depth_prior) (the video hardly measures depth).

with the hand's pixels left out of every image term (weight 0); with point tracks in the
observations and `weights.track` > 0, each frame's term also holds lambda_track L_track (the video's
tracks against the projected Gaussians, fit/tracks_loss.py). No USD here: the fit gets a
`SceneData` and arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..contacts import ContactSet
from ..render import estimate_background, render, render_batch
from ..render.losses import reconstruction_loss, reconstruction_loss_batch
from ..scene import SceneData
from ..simulation import build_simulation
from .interaction_check import TRAJ_SIGMA_PX
from .substep import kept_rung

# `FitProblem.loss` renders its frames in few batched passes (`FitProblem.frames_rec`: one rasterizer
# pass and one loss call for all frames, instead of one of each per frame): None (default) on CUDA,
# where each render's launches and host sync cost more than its pixels; one by one on the CPU (the
# same values there, to float rounding; the CPU's time is the simulator's). True / False force it.
BATCH_FRAMES: bool | None = None
# at most this many Gaussians in one rasterizer pass (the images are grouped to fit)
RENDER_PASS_GAUSSIANS = 1 << 22

# The trajectory prior's weight against the reconstruction loss: a path 1 sigma off the measured one
# on every frame costs TRAJ_PRIOR_WEIGHT. Chosen on development data only (the tests' tiny bars,
# tests/diagnose_scene.py, control and hidden damping, noise 0.015): a path 3 sigma off on every frame
# costs 9 x 0.01 = 0.09, more than the whole reconstruction loss of those scenes (0.03-0.08), so no
# gain in the images can pay for moving it that far; the pixels' own hold on the path is weak (moving
# it 1 sigma across the ray raises the tiny bar's reconstruction loss by ~2e-4 of 0.033), so the prior
# decides beyond ~1 sigma and the images within it (docs/diagnose.md, "the trajectory's freedom").
TRAJ_PRIOR_WEIGHT = 1.0e-2


@dataclass
class Observations:
    frames: np.ndarray                 # (T, H, W, 3) float32 in [0, 1]
    masks: np.ndarray | None = None    # (T, H, W) bool object silhouettes (visible)
    hand_masks: np.ndarray | None = None  # (T, H, W) bool pixels to leave out
    tracks: object | None = None       # point tracks measured on the video (ids, uv, valid, fb_error, ...:
                                       # `compare.GaussianTracks`); the track term (fit/tracks_loss.py)

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
    trajectory: float = 1.0    # x TRAJ_PRIOR_WEIGHT: the trajectory prior's weight (FitProblem.trajectory_prior)
    depth_prior: float = 0.1   # weight of T0's depth relative to its image-plane position (sigma along the
                               # camera ray = sigma across / sqrt(depth_prior): 3.2x)
    track: float = 0.0         # the point tracks' term (fit/tracks_loss.py; FitSettings.track_weight sets it)


class FitProblem:
    """The fit's problem: the scene's simulation (`simulation.build_simulation`) under its contacts,
    the observations, the renderer's inputs and the loss."""

    def __init__(self, scene: SceneData, obs: Observations, contacts: list[ContactSet], *,
                 effects: dict | None = None, device: str = "cpu", dtype: str = "float32",
                 weights: LossWeights | None = None, knn: int = 4, traj_sigma_px: float | None = None):
        self.scene, self.obs = scene, obs
        self.weights = weights or LossWeights()
        T = obs.n_frames
        if T < 2:
            raise ValueError("the fit needs at least 2 frames")
        self.T = T
        self.sim = build_simulation(scene, contacts, T, effects=effects, device=device, dtype=dtype, knn=knn)
        sim = self.sim
        self.device, self.tdev, self.tdtype = sim.device, sim.tdev, sim.tdtype
        self.x0, self.effects, self.contacts = sim.x0, sim.effects, sim.contacts
        self.grid, self.control = sim.grid, sim.control
        self.traj_slots, self.binding = sim.traj_slots, sim.binding
        self.cov0, self.colors, self.opacities = sim.cov0, sim.colors, sim.opacities
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=self.tdtype, device=self.tdev)  # noqa: E731
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
        self.tracks = None
        if obs.tracks is not None:
            from .tracks_loss import track_loss_from

            outline = obs.masks[0] if obs.masks is not None else self._silhouettes_at_rest()[0]
            self.tracks = track_loss_from(obs.tracks, self.cameras, scene.gaussians.means, outline=outline,
                                          dtype=self.tdtype, device=self.tdev)
        scale = float(np.max(np.ptp(self.x0, axis=0)))
        self.traj_scale = max(0.05 * scale, 1e-3)   # a length unit (effect parameters in metres, probe steps)
        # the measured path's uncertainty: sigma_px at the contact's depth, per frame (metres across the ray)
        self.traj_sigma_px = float(TRAJ_SIGMA_PX if traj_sigma_px is None else traj_sigma_px)
        if not self.traj_sigma_px > 0:
            raise ValueError(f"the trajectory's pixel uncertainty must be > 0, got {traj_sigma_px!r}")
        self.traj_rays, self.traj_sigma = [], []
        for _, t0 in self.traj_slots:
            p = t0.detach().cpu().numpy().astype(np.float64)
            c = np.stack([self.cameras[k].position for k in range(T)])
            r = p - c
            dist = np.maximum(np.linalg.norm(r, axis=1), 1e-6)
            r /= dist[:, None]
            self.traj_rays.append(torch.as_tensor(r, dtype=self.tdtype, device=self.tdev))
            z = np.array([self.cameras[k].world_to_camera(p[k][None])[0, 2] for k in range(T)])
            z = np.where(z > 1e-6, z, dist)                 # behind the camera: its distance
            f = np.array([math.sqrt(self.cameras[k].fx * self.cameras[k].fy) for k in range(T)])
            self.traj_sigma.append(torch.as_tensor(self.traj_sigma_px * z / f, dtype=self.tdtype,
                                                   device=self.tdev))

    @property
    def model(self):
        """The simulator's model at the current substep (`Simulation.ensure_stable` may rebuild it)."""
        return self.sim.model

    @property
    def rollout(self):
        return self.sim.rollout

    def held_particles(self) -> np.ndarray:
        """(P,) True for particles a fixed support holds from the first frame (the video cannot
        see their material)."""
        return self.sim.held_particles()

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
        return self.sim.initial_trajectories()

    def simulate(self, E, nu, trajectories=None, effects=None):
        return self.sim.simulate(E, nu, trajectories, effects)

    def gaussians_at(self, x_k, F_k):
        return self.sim.gaussians_at(x_k, F_k)

    def render_frame(self, k, x_k, F_k):
        means, covs = self.gaussians_at(x_k, F_k)
        out = render(means, covs, self.colors, self.opacities, self.cameras[k], background=self.background)
        if self.tracks is not None:
            out["means"] = means           # the track term's input
        return out

    def frame_loss(self, k, out) -> dict:
        w = None if self.weight is None else self.weight[k]
        mask = None if self.masks is None else self.masks[k]
        res = reconstruction_loss(out["rgb"], self.frames[k], w, out["alpha"] if mask is not None else None, mask,
                                  lambda_ssim=self.weights.ssim, lambda_mask=self.weights.mask)
        if self.tracks is not None and self.weights.track > 0 and "means" in out:
            res["track"] = self.tracks.frame_term(k, out["means"])
            res["total"] = res["total"] + self.weights.track * res["track"]
        return res

    def loss(self, E, nu, trajectories=None, effects=None, frames=None, keep_renders=False, simulated=None) -> dict:
        """The reconstruction loss over `frames` (default: all but the rest frame). `simulated`:
        (x, F) the simulator already gave for these inputs (not simulated again)."""
        x, F = self.simulate(E, nu, trajectories, effects) if simulated is None else simulated
        ks = range(1, self.T) if frames is None else frames
        total = 0.0
        renders = {}
        if self.batch_frames and len(ks):
            recs, kept = self.frames_rec(x[None], F[None], [0], ks, keep_renders)
            rec, renders = recs[0], kept[0]
        else:
            for k in ks:
                out = self.render_frame(k, x[k], F[k])
                total = total + self.frame_loss(k, out)["total"]
                if keep_renders:
                    renders[k] = {n: v.detach() for n, v in out.items()}
            rec = total / max(len(ks), 1)
        reg = 0.0
        if trajectories is not None and self.weights.trajectory > 0:
            reg = self.trajectory_prior(trajectories)
        return {"rec": rec, "reg_traj": reg, "x": x, "F": F, "renders": renders}

    @property
    def batch_frames(self) -> bool:
        """Whether the frames are rendered and scored in batched passes (`BATCH_FRAMES`; None: on CUDA)."""
        return str(self.tdev).startswith("cuda") if BATCH_FRAMES is None else bool(BATCH_FRAMES)

    def frames_rec(self, x, F, copies, frames=None, keep_renders: bool = False):
        """The reconstruction loss (`loss`'s "rec": the mean over `frames`, default all but the rest
        frame, of `frame_loss`'s total) of the copies `copies` of a batch of states x (B, T, P, 3),
        F (B, T, P, 3, 3), with the renders and loss terms of all their frames in few batched passes
        (`render.render_batch`, `render.reconstruction_loss_batch`; each image bitwise its own
        render, the loss to float rounding). Returns ((len(copies),) tensor, per copy {frame: its
        renders, detached} when `keep_renders`, else empty dicts). Differentiable in x and F."""
        ks = list(range(1, self.T)) if frames is None else [int(k) for k in frames]
        pairs = [(int(b), k) for b in copies for k in ks]
        kept = [{} for _ in copies]
        if not pairs:
            return torch.zeros(len(copies), dtype=self.tdtype, device=self.tdev), kept
        n = int(self.cov0.shape[0])
        per = max(len(ks), RENDER_PASS_GAUSSIANS // max(n, 1))
        w8 = self.weights
        totals = []
        for i0 in range(0, len(pairs), per):
            chunk = pairs[i0:i0 + per]
            bi = torch.as_tensor([b for b, _ in chunk], device=x.device)
            ki = torch.as_tensor([k for _, k in chunk], device=x.device)
            means, covs = self.gaussians_at(x[bi, ki], F[bi, ki])
            out = render_batch(means, covs, self.colors, self.opacities, [self.cameras[k] for _, k in chunk],
                               background=self.background)
            w = None if self.weight is None else self.weight[ki]
            mask = None if self.masks is None else self.masks[ki]
            res = reconstruction_loss_batch(out["rgb"], self.frames[ki], w, out["alpha"] if mask is not None else None,
                                            mask, lambda_ssim=w8.ssim, lambda_mask=w8.mask)
            tot = res["total"]
            if self.tracks is not None and w8.track > 0:
                tot = tot + w8.track * torch.stack([self.tracks.frame_term(k, means[j])
                                                    for j, (_, k) in enumerate(chunk)])
            totals.append(tot)
            if keep_renders:
                if self.tracks is not None:
                    out["means"] = means
                for j, (b, k) in enumerate(chunk):
                    kept[copies.index(b)][k] = {nm: v[j].detach() for nm, v in out.items()}
        rec = torch.cat(totals).reshape(len(copies), len(ks)).sum(1) / max(len(ks), 1)
        return rec, kept

    def trajectory_prior_residual(self, trajectories, reference=None) -> torch.Tensor:
        """The trajectory prior as a residual vector whose sum of squares is `trajectory_prior`: per
        slot and frame k, sqrt(w / T) x (the path's offset from T0 across the camera ray / sigma_k
        (3 components), sqrt(depth_prior) x its offset along the ray / sigma_k), with
        w = weights.trajectory x TRAJ_PRIOR_WEIGHT and sigma_k = traj_sigma_px x depth_k / focal_px
        (`traj_sigma`: the measured path's uncertainty at the contact's depth). The same whether
        T0 was extracted, given by the user or the ground truth: the measurement is the path.
        `reference`: the measured paths (one per slot) where the problem's T0 is another (the
        diagnosis builds its problem at the fitted path)."""
        parts = []
        w = self.weights.trajectory * TRAJ_PRIOR_WEIGHT
        refs = [t0 for _, t0 in self.traj_slots] if reference is None else \
            [torch.as_tensor(np.asarray(r), dtype=self.tdtype, device=self.tdev) for r in reference]
        for tr, t0, rays, sig in zip(trajectories, refs, self.traj_rays, self.traj_sigma):
            d = (tr - t0) / sig[:, None]
            along = (d * rays).sum(-1, keepdim=True)
            across = d - along * rays
            # T0's depth (along the camera ray) is far less certain than its image position
            v = torch.cat([across, math.sqrt(self.weights.depth_prior) * along], -1) * math.sqrt(w / len(tr))
            parts.append(v.reshape(-1))
        if not parts:
            return torch.zeros(0, dtype=self.tdtype, device=self.tdev)
        return torch.cat(parts)

    def trajectory_prior(self, trajectories):
        """L_traj = w x mean over frames of (|offset across the ray|^2 + depth_prior x offset
        along it^2) / sigma_k^2, summed over the trajectory slots (`trajectory_prior_residual`)."""
        r = self.trajectory_prior_residual(trajectories)
        return (r * r).sum() if len(r) else 0.0


    def losses_batch(self, E, nu, trajectories=None, effects=None, frames=None) -> np.ndarray:
        """(B,) reconstruction losses of B material fields E (B, P) (nu (P,) or (B, P)) under the
        same trajectories and effects, simulated as copies side by side in few rollouts
        (`Simulation.simulate_batch`; on a GPU B small probes cost about one). No gradients. A copy
        that went unstable or left its box gets inf. All copies take the substep of the largest E
        among them: a soft copy's loss may differ from its own rollout's (a finer time step) by the
        time discretisation; group the probes by stiffness where that matters, or where the copies
        are many and large (then the batch costs about the sum of its copies, at the finest step).
        Probes: the adaptive substep's rung is restored on return (`substep.kept_rung`)."""
        with torch.no_grad(), kept_rung(self):   # probes: the substep's rung is left as it was found
            x, F, bad = self.sim.simulate_batch(E, nu, trajectories, effects)
            ks = range(1, self.T) if frames is None else frames
            out = np.full(len(x), np.inf)
            good = [b for b in range(len(x)) if not bad[b]]
            if good and len(ks) and self.batch_frames:
                out[good] = self.frames_rec(x, F, good, ks)[0].cpu().numpy()
                good = []
            for b in good:
                total = 0.0
                for k in ks:
                    total = total + self.frame_loss(k, self.render_frame(k, x[b, k], F[b, k]))["total"]
                out[b] = float(total) / max(len(ks), 1)
        out[~np.isfinite(out)] = np.inf
        return out


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
