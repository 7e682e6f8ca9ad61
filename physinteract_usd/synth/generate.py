"""Generate a synthetic capture folder with ground truth (the design's capture format + gt/).

Pipeline: procedural shape -> surface Gaussians (object.ply) -> a finer ground-truth particle
lattice with the scene's E field -> a ground-truth MPM rollout (smaller dt and spacing than the
fit's) under the scene's interaction and unseen supports -> Gaussians deformed by the particles,
plus a skin-coloured hand proxy that occludes what is behind it -> frames over a static
background, silhouette masks, optional sensor noise and motion blur -> gt/ and a contact sheet.

gt/ (never read by init, extract or fit; documented in docs/synth.md):
  gt.json                  scene, material, interaction (contact, trajectory, grasp/release),
                           supports, hidden effect, noise, ground-truth simulation settings
  youngs_modulus.npy       (N,) E per Gaussian, input PLY order [Pa]
  poisson_ratio.npy        (N,) nu per Gaussian
  gaussian_positions.npy   (T, N, 3) Gaussian centres per frame [m]
  particles.npz            rest positions, E, nu, volumes of the ground-truth particles
  hand_masks/, amodal_masks/   per-frame hand pixels and object silhouettes including hidden parts
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..camera import Camera
from ..errors import InputError
from ..frames import write_image, write_mask
from ..gaussians import Gaussians, write_ply
from . import outdir
from .gt import write_ground_truth
from .geometry import Capsule, Ellipsoid, Shape
from .scenes import SCENES, SceneSpec, pattern_color

NOISE_PX = 0.5      # the tracking noise level in pixels that hidden-effect strengths are relative to
SKIN = (0.87, 0.66, 0.54)


@dataclass
class Size:
    name: str
    gaussians: int
    width: int
    height: int
    fps: float
    frames: int
    gt_ratio: float      # ground-truth grid cell = gt_ratio x the suggested fit's cell (particles at half a cell)
    fit_grid: int        # the init --grid the README suggests for this size
    fit_padding: float
    fit_youngs: tuple    # the init --youngs-range suggested
    fit_poisson_max: float = 0.4


SIZES = {
    "small": Size("small", 1500, 128, 96, 20.0, 20, 0.7, 24, 0.3, (1e3, 6e4)),
    "paper": Size("paper", 5000, 448, 336, 30.0, 45, 0.85, 100, 0.3, (1e3, 6e4)),
}


def list_scenes() -> list[tuple[str, str, str, str]]:
    return [(s.name, s.paper_name, s.interaction, s.description) for s in SCENES.values()]


# ------------------------------------------------------------------------------ helpers
def project_to_surface(shape: Shape, p, iters=20) -> np.ndarray:
    p = np.asarray(p, float)[None].copy()
    for _ in range(iters):
        d = shape.sdf(p)
        p -= d[:, None] * shape.normals(p)
    return p[0]


def surface_gaussians(spec: SceneSpec, shape: Shape, n: int, seed: int) -> tuple[Gaussians, np.ndarray]:
    pts, _ = shape.sample_surface(n, seed=seed)
    part = shape.part_of(pts)
    normals = shape.normals(pts)
    col = spec.texture(pts, part)
    area = float(shape.mesh().area) * len(pts) / max(n, 1)  # approx. union area
    r = math.sqrt(area / len(pts) / math.pi) * 1.4
    quats = np.stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(len(pts))], 1)
    quats[normals[:, 2] < -0.999999] = [0.0, 1.0, 0.0, 0.0]
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = np.tile([r, r, 0.15 * r], (len(pts), 1))
    g = Gaussians.from_colors(pts, col, scales, opacities=np.full(len(pts), 0.97), quats=quats)
    g.normals = normals
    return g, part


def hand_shape(kind: str, radius: float) -> Shape:
    """A hand proxy in its local frame: fingertips at the origin, the hand along +z."""
    if kind == "surfaceNonAdherent":
        return Shape([Ellipsoid("palm", (0, 0, 0.0), (0.09, 0.075, 0.014))])
    if kind == "pointNonAdherent":
        r = max(radius, 0.01)
        return Shape([Capsule("finger", (0, 0, 0), (0, 0, 0.09), r),
                      Ellipsoid("palm", (0, 0.015, 0.13), (0.045, 0.02, 0.05))])
    return Shape([Capsule("thumb", (-0.012, -0.01, 0.0), (-0.03, -0.02, 0.06), 0.011),
                  Capsule("index", (0.012, 0.008, 0.0), (0.02, 0.02, 0.07), 0.01),
                  Capsule("middle", (0.028, 0.0, 0.01), (0.04, 0.01, 0.075), 0.01),
                  Ellipsoid("palm", (0.01, 0.0, 0.095), (0.045, 0.018, 0.045))])


def _frame_from(z_dir, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    z = np.asarray(z_dir, float)
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], 1)


def background_image(w: int, h: int, seed: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    p = np.stack([xx / w, yy / h, np.full_like(xx, seed % 97, dtype=float) * 0.13], -1).reshape(-1, 3)
    base = pattern_color(p, (0.62, 0.64, 0.6), (0.5, 0.52, 0.56), 0.18, "noise")
    grad = (0.9 + 0.15 * (1 - yy / h)).reshape(-1, 1)
    return np.clip(base * grad, 0, 1).reshape(h, w, 3).astype(np.float32)


def frame_camera(spec: SceneSpec, gt: "GroundTruth", sz: Size) -> Camera:
    """The scene's oblique static camera, moved along its viewing direction so that the object
    and the interaction's path fill about 80% of the frame."""
    pts = np.concatenate([gt.x0, gt.trajectory])
    centre = 0.5 * (pts.min(0) + pts.max(0))
    target = 0.5 * (centre + np.asarray(spec.camera_target, float))
    view = np.asarray(spec.camera_eye, float) - np.asarray(spec.camera_target, float)
    view /= np.linalg.norm(view)
    # distance so that the points' extent seen across the view direction fills the frame
    probe = Camera.look_at(target + view, target, width=sz.width, height=sz.height, fov_y_deg=spec.fov_y)
    pc = probe.world_to_camera(pts)
    half_h = math.tan(math.radians(spec.fov_y) / 2)
    half_w = half_h * sz.width / sz.height
    need = max(np.max(np.abs(pc[:, 0])) / (0.8 * half_w), np.max(np.abs(pc[:, 1])) / (0.8 * half_h))
    dist = need + float(np.max(np.abs(pc[:, 2] - pc[:, 2].mean())))
    return Camera.look_at(target + view * dist, target, width=sz.width, height=sz.height, fov_y_deg=spec.fov_y)


# ------------------------------------------------------------------------------ ground truth sim
def truth_ground_contact() -> str:
    """Where the ground truth's ground acts (`SimModel.ground_contact`): the environment's PHYSINTERACT_GROUND, the
    fits' own setting (`simulation.GROUND_CONTACT`), read at each call, so that a capture and its fit share it;
    unset: "nodes", every capture made before the 24th session."""
    import os

    from ..simulation import ground_contact

    return ground_contact(os.environ.get("PHYSINTERACT_GROUND"))


def truth_pin_rule() -> tuple[float, float]:
    """The pin rule of the ground truth's simulation (a grid node's blend clamp(gain (pinned share - floor), 0, 1),
    docs/sim.md): the environment's PHYSINTERACT_TRUTH_PIN_RULE ("default", "band" or "GAIN,FLOOR", as
    PHYSINTERACT_PIN_RULE reads), read at each call; unset: (4, 0), every capture made before #24's study. The
    fit's PHYSINTERACT_PIN_RULE never reaches the truth: an A/B of a pin rule in truth AND fit sets both
    (docs/benchmarks/fit.md, "The real A/B: the clamp band in truth and fit")."""
    import os

    from ..simulation import pin_rule

    v = os.environ.get("PHYSINTERACT_TRUTH_PIN_RULE")
    try:
        return pin_rule(v)
    except ValueError as exc:
        raise InputError("PHYSINTERACT_TRUTH_PIN_RULE", str(exc).split(": ", 1)[-1]) from None


class GroundTruth:
    """The ground-truth particles, control and simulator of a scene."""

    def __init__(self, spec: SceneSpec, size: Size, n_frames: int, device: str = "cpu",
                 spacing_scale: float = 1.0):
        from ..sim import Contact, Control, GridSpec, SimModel, stable_dt

        self.spec, self.size = spec, size
        shape = spec.shape()
        self.shape = shape
        lo, hi = shape.bounds()
        ext = float(np.max(hi - lo))
        self.extent = ext
        fit_dx = (1 + 2 * size.fit_padding) * ext / size.fit_grid
        h = 0.5 * size.gt_ratio * fit_dx * spacing_scale
        self.spacing = h
        x0 = shape.lattice(h)
        part = shape.part_of(x0)
        self.x0, self.part = x0, part
        self.E = spec.youngs(x0, part)
        self.nu = np.array([spec.poisson[shape.labels[i]] for i in part])
        self.contact_point = project_to_surface(shape, spec.contact_point)
        T = n_frames - 1  # simulated frames after the rest frame
        g, r = (int(round(f * (n_frames - 1))) for f in spec.phases)
        self.grasp, self.release = max(g, 1), max(r, g + 2)
        s = np.clip((np.arange(T + 1) - self.grasp) / max(self.release - self.grasp, 1), 0, 1)
        disp = spec.path(s)
        contacts = []
        kind = spec.interaction
        self.hand_offset = np.zeros(3)
        if kind == "pointAdherent":
            idx = np.where(np.linalg.norm(x0 - self.contact_point, axis=1) < spec.contact_radius)[0]
            if len(idx) < 3:
                idx = np.argsort(np.linalg.norm(x0 - self.contact_point, axis=1))[:3]
            centroid = x0[idx].mean(0)
            self.trajectory = centroid + disp
            self.hand_offset = self.contact_point - centroid
            contacts.append(Contact("pointAdherent", indices=idx, trajectory=self.trajectory,
                                    grasp_frame=self.grasp, release_frame=self.release))
            self.contact_indices = idx
        elif kind == "pointNonAdherent":
            n = shape.normals(self.contact_point[None])[0]
            start = self.contact_point + n * (spec.contact_radius + 0.004)
            self.trajectory = start + disp
            contacts.append(Contact("pointNonAdherent", trajectory=self.trajectory, shape="sphere",
                                    radius=spec.contact_radius, friction=spec.friction, grasp_frame=0))
            self.contact_indices = np.zeros(0, int)
        elif kind == "surfaceNonAdherent":
            nrm = np.asarray(spec.plane_normal, float)
            start = self.contact_point - nrm * 0.003
            self.trajectory = start + disp
            contacts.append(Contact("surfaceNonAdherent", trajectory=self.trajectory, normal=tuple(nrm),
                                    friction=spec.friction, grasp_frame=0))
            self.contact_indices = np.zeros(0, int)
        else:
            raise ValueError(kind)
        fixed = np.zeros(len(x0), bool)
        for sup in spec.supports:
            fixed |= np.linalg.norm(x0 - np.asarray(sup.centre), axis=1) < sup.radius
        fixed[getattr(self, "contact_indices", np.zeros(0, int))] = False
        if fixed.sum() < 3:
            raise RuntimeError(f"{spec.name}: supports hold {fixed.sum()} particles")
        self.fixed_indices = np.where(fixed)[0]
        contacts.append(Contact("fixed", indices=self.fixed_indices))
        self.control = Control(contacts, n_frames=T)
        # grid: the rest shape, the whole trajectory, and room for the motion
        pts = np.concatenate([x0, self.trajectory])
        dx = 2.0 * h
        self.grid = GridSpec.around(pts, dx=dx, padding=0.35 * ext)
        # fit's dt under the suggested init settings; the ground truth steps at most half of it
        fit_dx = (1 + 2 * size.fit_padding) * ext / size.fit_grid
        fit_dt = stable_dt(fit_dx, size.fit_youngs[1], size.fit_poisson_max, spec.density)
        gt_dt = min(stable_dt(dx, float(self.E.max()) * 2.0, float(self.nu.max()), spec.density, cfl=0.2),
                    0.5 * fit_dt)
        self.substeps = int(math.ceil(1.0 / (size.fps * gt_dt)))
        self.fit_dt = fit_dt
        self.device = device
        self.SimModel = SimModel

    def model(self, effects=None):
        gain, floor = truth_pin_rule()
        return self.SimModel.create(self.x0, self.spacing ** 3, self.spec.density, self.E, self.nu,
                                    grid=self.grid, fps=self.size.fps, substeps=self.substeps,
                                    E_max=float(self.E.max()), effects=effects or {}, device=self.device,
                                    transfer_tau=getattr(self, "transfer_tau", 0.0), pin_gain=gain, pin_floor=floor,
                                    ground_contact=truth_ground_contact(),
                                    # the truth checks its frames' ends only, as before #24: the captures
                                    # generated before regenerate the same (sim/model.py stencil_check)
                                    stencil_check=False)

    def run(self, effects=None):
        """Rollout -> x (T, P, 3), F (T, P, 3, 3) numpy (frame 0 = rest)."""
        from ..sim import Rollout

        m = self.model(effects)
        ro = Rollout(m, self.control)
        dev = "cpu" if self.device == "cpu" else self.device
        with torch.no_grad():
            x, F = ro(torch.tensor(self.E, dtype=torch.float32, device=dev),
                      torch.tensor(self.nu, dtype=torch.float32, device=dev))
        return x.cpu().double().numpy(), F.cpu().double().numpy()


# ------------------------------------------------------------------------------ hidden effects
EFFECT_SEARCH = {
    # effect: (parameter, low, high, log-scale, increasing-with-strength)
    "damping": ("coefficient", 1e-2, 60.0, True, True),
    "plasticity": ("yieldStress", 2e2, 2e5, True, False),
    "viscoelasticity": ("modulus", 1e2, 2e5, True, True),
    "ground": ("height", None, None, False, True),
}


def _pixel_effect(cam: Camera, a: np.ndarray, b: np.ndarray) -> float:
    """RMS over frames and points of the projected distance between two (T, N, 3) motions."""
    ua, _ = cam.project(a.reshape(-1, 3))
    ub, _ = cam.project(b.reshape(-1, 3))
    return float(np.sqrt(np.mean(np.sum((ua - ub) ** 2, axis=1))))


def effect_search(gt: GroundTruth, effect: str, base_x: np.ndarray) -> tuple:
    """Both calibrations' search: (parameter name, low, high, log-scaled, stronger with the value, the effect's
    other parameters held fixed). The ground's bracket is in heights about the lowest point the base motion reaches."""
    name, lo, hi, logscale, increasing = EFFECT_SEARCH[effect]
    extra = {}
    if effect == "ground":
        ymin = min(base_x[..., 1].min(), gt.x0[:, 1].min())
        lo, hi = ymin - 0.02 * gt.extent, ymin + 0.25 * gt.extent
        extra = {"friction": 0.6}
    if effect == "viscoelasticity":
        extra = {"relaxationTime": 0.15}
    return name, lo, hi, logscale, increasing, extra


def calibrate_effect(gt: GroundTruth, cam: Camera, effect: str, strength: float, base_x: np.ndarray,
                     iters: int = 7, log=print) -> tuple[dict, float]:
    """Find the effect parameter whose pixel effect is strength x NOISE_PX (bisection)."""
    target = strength * NOISE_PX
    name, lo, hi, logscale, increasing, extra = effect_search(gt, effect, base_x)
    sub = np.arange(0, base_x.shape[1], max(1, base_x.shape[1] // 400))
    best = None
    for _ in range(iters):
        mid = math.sqrt(lo * hi) if logscale else 0.5 * (lo + hi)
        params = {name: mid, **extra}
        x, _ = gt.run({effect: params})
        px = _pixel_effect(cam, x[:, sub], base_x[:, sub])
        log(f"  {effect} {name}={mid:.4g}: {px:.3f} px (target {target:.3f})")
        if best is None or abs(px - target) < abs(best[1] - target):
            best = (params, px)
        too_strong = px > target
        if too_strong == increasing:
            hi = mid
        else:
            lo = mid
    return best


CALIBRATIONS = ("particles", "frames")
SIGMA_REF = 0.015   # the frame calibration's noise level for a noise-free capture (the suite's 0.015)


def frame_change(a: np.ndarray, b: np.ndarray, hand_a: np.ndarray | None = None, hand_b: np.ndarray | None = None,
                 mask: np.ndarray | None = None) -> float:
    """D^2: the mean squared change between two noise-free renders (T, H, W, 3) over frames 1.. (frame 0 is
    the rest pose, the same in both), every channel, the pixels the hand covers in neither (the loss leaves
    them out); `mask` (T, H, W) bool: only those pixels (e.g. the object's silhouette in either)."""
    d2 = np.mean((np.asarray(a[1:], np.float64) - np.asarray(b[1:], np.float64)) ** 2, axis=-1)
    keep = np.ones(d2.shape, bool)
    for h in (hand_a, hand_b):
        if h is not None:
            keep &= ~np.asarray(h[1:], bool)
    if mask is not None:
        keep &= np.asarray(mask[1:], bool)
    return float(d2[keep].mean()) if keep.any() else 0.0


def calibrate_frames(gt: GroundTruth, render_frames, effect: str, strength: float, base_x: np.ndarray,
                     base_rgb: np.ndarray, base_hand: np.ndarray, sigma_ref: float, iters: int = 12,
                     tol: float = 0.03, log=print) -> tuple[dict, float, dict]:
    """Find the effect parameter whose rendered frames change by D^2 = strength x sigma_ref^2 (issue #22's
    strength 1: adding the effect halves a loss of noise variance sigma_ref^2). `render_frames(x, F)` ->
    (rgb, hand masks), noise-free. Bisection on the particle calibration's bracket (geometric where it is
    log-scaled), then, once the target is bracketed, regula falsi (Illinois) on log D^2; stops within `tol`
    (relative) of the target or after `iters` simulations. Returns (params, D^2 / sigma_ref^2, trace)."""
    target = float(strength)
    name, lo, hi, logscale, increasing, extra = effect_search(gt, effect, base_x)
    u = (lambda v: math.log(v)) if logscale else (lambda v: v)          # noqa: E731
    uinv = (lambda w: math.exp(w)) if logscale else (lambda w: w)       # noqa: E731
    ulo, uhi = u(lo), u(hi)
    weak, strong, side = None, None, None   # (u, log ratio) of the nearest points below / above the target
    best, trace = None, []
    for _ in range(iters):
        if weak is not None and strong is not None:
            (u0, f0), (u1, f1) = weak, strong
            w = u0 - f0 * (u1 - u0) / (f1 - f0) if f1 != f0 else 0.5 * (u0 + u1)
            w = min(max(w, min(u0, u1) + 0.02 * abs(u1 - u0)), max(u0, u1) - 0.02 * abs(u1 - u0))
        else:
            w = 0.5 * (ulo + uhi)
        mid = uinv(w)
        params = {name: mid, **extra}
        x, F = gt.run({effect: params})
        rgb, hand = render_frames(x, F)
        ratio = frame_change(rgb, base_rgb, hand, base_hand) / sigma_ref ** 2
        trace.append((float(mid), float(ratio)))
        log(f"  {effect} {name}={mid:.4g}: D^2 = {ratio:.3f} x sigma^2 (target {target:.3f})")
        if best is None or abs(math.log(max(ratio, 1e-12) / target)) < abs(math.log(max(best[1], 1e-12) / target)):
            best = (params, ratio)
        if abs(ratio / target - 1.0) <= tol:
            break
        f = math.log(max(ratio, 1e-12) / target)
        if f > 0:                      # too strong
            if side == "strong" and weak is not None:
                weak = (weak[0], 0.5 * weak[1])         # Illinois: the end kept twice counts half
            strong, side = (w, f), "strong"
        else:
            if side == "weak" and strong is not None:
                strong = (strong[0], 0.5 * strong[1])
            weak, side = (w, f), "weak"
        if (f > 0) == increasing:
            uhi = w
        else:
            ulo = w
    return best[0], best[1], {"trace": trace}


# ------------------------------------------------------------------------------ render
def _render_all(g: Gaussians, binding, xs, Fs, hand: Gaussians, hand_pos, hand_R, cam: Camera,
                bg: np.ndarray, blur: int, device: str):
    from ..render import covariance_from_scales_quats, render

    dev = torch.device(device)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)  # noqa: E731
    cov0 = covariance_from_scales_quats(t(g.scales), t(g.quats))
    hcov0 = covariance_from_scales_quats(t(hand.scales), t(hand.quats))
    col = t(g.colors)
    hcol = t(hand.colors)
    op = t(g.opacities)
    hop = t(hand.opacities)
    bgt = t(bg)
    frames, amodal, visible, hand_masks, gpos = [], [], [], [], []
    n_obj = len(g)
    for k in range(len(xs)):
        acc = None
        samples = [0.0] if (blur <= 1 or k == 0) else list(np.linspace(-0.5, 0.0, blur))
        for s in samples:
            j0 = k - 1 if s < 0 else k
            w = 1.0 + s if s < 0 else 1.0
            x = xs[k] * w + xs[j0] * (1 - w)
            F = Fs[k] * w + Fs[j0] * (1 - w)
            means, covs = binding.apply(t(x), t(F), cov0)
            R = hand_R
            hm = t(hand.means @ R.T + hand_pos[k])
            hc = t(R) @ hcov0 @ t(R).T
            out = render(torch.cat([means, hm]), torch.cat([covs, hc]), torch.cat([col, hcol]),
                         torch.cat([op, hop]), cam, background=bgt)
            acc = out["rgb"] if acc is None else acc + out["rgb"]
            if s == samples[-1]:
                gpos.append(means.cpu().numpy())
                ind = torch.cat([torch.zeros(n_obj, 3, device=dev), torch.ones(len(hand), 3, device=dev)])
                o2 = render(torch.cat([means, hm]), torch.cat([covs, hc]), ind, torch.cat([op, hop]), cam)
                hand_w = o2["rgb"][..., 0]
                obj_vis = out["alpha"] - hand_w
                o3 = render(means, covs, col, op, cam)
                amodal.append((o3["alpha"] > 0.5).cpu().numpy())
                visible.append((obj_vis > 0.5).cpu().numpy())
                hand_masks.append((hand_w > 0.5).cpu().numpy())
        frames.append((acc / len(samples)).cpu().numpy())
    return (np.stack(frames), np.stack(amodal), np.stack(visible), np.stack(hand_masks), np.stack(gpos))


# ------------------------------------------------------------------------------ sensor noise
def sensor_noise(seed: int, sigma: float, shape) -> np.ndarray:
    """The sensor noise `generate` adds to every frame of a capture (all frames at once, shape
    (T, H, W, 3)): N(0, sigma) per pixel and channel from a generator seeded with seed + 7."""
    return np.random.default_rng(int(seed) + 7).normal(scale=float(sigma), size=tuple(shape))


def noise_free_frames(info: dict, frames: np.ndarray) -> np.ndarray | None:
    """A synth capture's frames (T, H, W, 3) in [0, 1] less the sensor noise `generate` added (gt.json
    `info`: its seed, noise sigma and frame count): the noise-free render to the frames' 8-bit rounding
    (not where the noisy value was clipped at 0 or 1). None for a capture without noise. What a model
    that renders the truth exactly scores against the video is the noise's share of a loss
    (benchmarks/loss_floor.py, docs/benchmarks/fit.md)."""
    sigma = float((info.get("noise") or {}).get("sigma") or 0.0)
    if sigma <= 0:
        return None
    frames = np.asarray(frames, np.float64)
    n = sensor_noise(int(info.get("seed", 0)), sigma, (int(info["n_frames"]), *frames.shape[1:]))
    return np.clip(frames - n[: len(frames)], 0, 1).astype(np.float32)


def _scene_renderer(spec: SceneSpec, gt: GroundTruth, sz: Size, size: str, g: Gaussians, cam: Camera,
                    blur: int, seed: int, device: str):
    """The capture's noise-free frames of a ground-truth motion: render(x, F) -> (rgb, amodal, visible, hand
    masks, Gaussian positions), the object's Gaussians bound to the truth's particles, the hand proxy along
    the interaction, the static background."""
    from ..render import GaussianBinding

    binding = GaussianBinding.knn(g.means, gt.x0, k=4, dtype=torch.float32, device=device)
    # hand proxy
    hs = hand_shape(spec.interaction, spec.contact_radius)
    hp, hpart = hs.sample_surface(500 if size == "small" else 1500, seed=seed + 1)
    hcol = pattern_color(hp * 3.0, SKIN, (0.75, 0.5, 0.4), 0.05, "noise")
    hn = hs.normals(hp)
    r_h = math.sqrt(hs.mesh().area / len(hp) / math.pi) * 1.5
    hq = np.stack([1.0 + hn[:, 2], -hn[:, 1], hn[:, 0], np.zeros(len(hp))], 1)
    hq[hn[:, 2] < -0.999999] = [0, 1, 0, 0]
    hq /= np.linalg.norm(hq, axis=1, keepdims=True)
    hand = Gaussians.from_colors(hp, hcol, np.tile([r_h, r_h, 0.15 * r_h], (len(hp), 1)),
                                 opacities=np.full(len(hp), 0.98), quats=hq)
    hand_dir = np.asarray(spec.hand_dir, float)
    hand_dir /= np.linalg.norm(hand_dir)
    if spec.interaction == "surfaceNonAdherent":
        R = np.eye(3)
        pos = gt.trajectory + np.array([0.0, 0.016, 0.0])
    else:
        R = _frame_from(hand_dir)
        tip = gt.trajectory + gt.hand_offset
        pos = tip.copy()
        # approach before the grasp, retreat after the release (the hand is seen moving)
        k = np.arange(len(tip))
        away = np.clip((gt.grasp - k) / max(gt.grasp, 1), 0, 1)[:, None] * 0.08 * hand_dir
        back = np.clip((k - gt.release) / 4.0, 0, 1)[:, None] * 0.1 * hand_dir
        pos = tip + away + np.where((k >= gt.release)[:, None], back, 0.0)
        if spec.interaction == "pointNonAdherent":
            pos = gt.trajectory.copy()
    bg = background_image(sz.width, sz.height, seed)

    def render_motion(x, F):
        return _render_all(g, binding, x, F, hand, pos, R, cam, bg, blur, device)

    return render_motion


# ------------------------------------------------------------------------------ main entry
def generate(name: str, out_dir, *, size: str = "small", frames: int | None = None,
             hidden: str | None = None, strength: float = 1.0, noise: float | None = None,
             blur: int | None = None, seed: int = 0, device: str = "cpu", force: bool = False,
             log=print, fit_grid: int | None = None, transfer_tau: float = 0.0,
             calibrate: str = "particles") -> dict:
    """Write the capture folder of scene `name` into `out_dir`. Returns gt.json's content.
    `calibrate`: how a hidden effect's `strength` is set (issue #22): "particles" (the default, every capture
    made before it unchanged): the parameter whose RMS projected particle displacement is strength x NOISE_PX;
    "frames": the parameter whose noise-free frames change by D^2 = strength x sigma^2 (mean squared over
    frames 1.. and the pixels the hand leaves; sigma the capture's noise, SIGMA_REF when noise-free): at
    strength 1 adding the effect halves a fit's loss, the issue's definition.
    `fit_grid`: the init grid the capture suggests, instead of the size's (the ground truth is
    simulated on a cell gt_ratio x that grid's: a finer fit grid makes a finer truth). `transfer_tau` [s]: the
    truth's simulation with the rate transfer (SimModel.transfer_tau; 0: APIC, the default)."""
    if name not in SCENES:
        raise InputError(name, "unknown scene; `physinteract-usd synth --list` lists them")
    if size not in SIZES:
        raise InputError(size, "size must be small or paper")
    spec = SCENES[name]
    if hidden is not None and hidden not in EFFECT_SEARCH:
        raise InputError(hidden, "unknown effect (damping, plasticity, ground, viscoelasticity)")
    if calibrate not in CALIBRATIONS:
        raise InputError("--calibrate", f"must be particles or frames, got {calibrate!r}")
    if hidden is not None and not (math.isfinite(float(strength)) and float(strength) > 0):
        raise InputError("--strength", f"must be a positive number, got {strength}")
    out = Path(out_dir)
    outdir.make_room(out, force)
    sz = SIZES[size]
    if fit_grid is not None:
        if int(fit_grid) != fit_grid or fit_grid < 8:
            raise InputError("--fit-grid", f"must be a whole number of cells, at least 8, got {fit_grid}")
        sz = dataclasses.replace(sz, fit_grid=int(fit_grid))
    transfer_tau = float(transfer_tau or 0.0)
    if not (math.isfinite(transfer_tau) and transfer_tau >= 0):
        raise InputError("--transfer-tau", f"must be >= 0 seconds (0: APIC), got {transfer_tau:g}")
    T = int(frames or sz.frames)
    if T < 3:
        raise InputError("--frames", "needs at least 3 frames")
    real = spec.origin == "real"
    noise = (0.015 if real else 0.0) if noise is None else float(noise)
    blur = (3 if real else 1) if blur is None else int(blur)
    t0 = time.perf_counter()

    gt = GroundTruth(spec, sz, T, device=device)
    gt.transfer_tau = transfer_tau
    log(f"{name}: {len(gt.x0)} ground-truth particles (spacing {gt.spacing * 1000:.1f} mm), "
        f"{gt.substeps} substeps/frame, E {gt.E.min():.3g}..{gt.E.max():.3g} Pa")
    g, gpart = surface_gaussians(spec, gt.shape, sz.gaussians, seed)
    cam = frame_camera(spec, gt, sz)

    render_motion = _scene_renderer(spec, gt, sz, size, g, cam, blur, seed, device)
    base_x, base_F = gt.run()
    effect_info = None
    x, F = base_x, base_F
    if hidden is not None and calibrate == "particles":
        log(f"calibrating hidden {hidden} to {strength:g} x {NOISE_PX} px")
        params, px = calibrate_effect(gt, cam, hidden, strength, base_x, log=log)
        x, F = gt.run({hidden: params})
        effect_info = {"name": hidden, "parameters": params, "strength": strength,
                       "noise_px": NOISE_PX, "effect_px": px}
    elif hidden is not None:
        sigma_ref = noise if noise > 0 else SIGMA_REF
        log(f"calibrating hidden {hidden} to frames changed by {strength:g} x sigma^2 (sigma {sigma_ref:g})")
        base = render_motion(base_x, base_F)

        def frames_of(xe, Fe):
            out = render_motion(xe, Fe)
            return out[0], out[3]

        params, ratio, info_c = calibrate_frames(gt, frames_of, hidden, strength, base_x, base[0], base[3],
                                                 sigma_ref, log=log)
        reached = abs(ratio / strength - 1.0) <= 0.1
        if not reached:
            log(f"warning: {hidden} changes the frames by at most {ratio:.3g} x sigma^2 within its search range "
                f"(target {strength:g}): the capture's effect is weaker or stronger than asked")
        x, F = gt.run({hidden: params})
        sub = np.arange(0, base_x.shape[1], max(1, base_x.shape[1] // 400))
        effect_info = {"name": hidden, "parameters": params, "strength": strength, "calibration": "frames",
                       "sigma_ref": sigma_ref, "frames_d2_over_sigma2": ratio, "calibration_reached": reached,
                       "noise_px": NOISE_PX, "effect_px": _pixel_effect(cam, x[:, sub], base_x[:, sub]),
                       "calibration_trace": info_c["trace"]}
    rgb, amodal, visible, hmask, gpos = render_motion(x, F)
    if noise > 0:
        rgb = np.clip(rgb + sensor_noise(seed, noise, rgb.shape), 0, 1)

    # ---- write the capture folder
    outdir.begin(out)
    write_ply(g, out / "object.ply")
    for sub in ("frames", "masks"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for k in range(T):
        write_image(out / "frames" / f"{k:06d}.png", rgb[k])
        write_mask(out / "masks" / f"{k:06d}.png", visible[k])
    (out / "transforms.json").write_text(json.dumps(cam.to_transforms_dict(sz.fps), indent=1))
    e_g = spec.youngs(g.means, gpart)
    nu_g = np.array([spec.poisson[gt.shape.labels[i]] for i in gpart])
    info = {
        "scene": name, "paper_name": spec.paper_name, "origin": spec.origin, "description": spec.description,
        "size": size, "seed": seed, "fps": sz.fps, "n_frames": T, "density": spec.density,
        "youngs_modulus": {"min": float(e_g.min()), "max": float(e_g.max()),
                           "range": float(e_g.max() / e_g.min())},
        "poisson_ratio": spec.poisson,
        "interaction": {"type": spec.interaction, "contact_point": gt.contact_point.tolist(),
                        "contact_radius": spec.contact_radius, "grasp_frame": gt.grasp,
                        "release_frame": gt.release if spec.interaction == "pointAdherent" else None,
                        "trajectory": gt.trajectory.tolist(),
                        "collider_radius": spec.contact_radius if spec.interaction == "pointNonAdherent" else 0.0,
                        "plane_normal": list(spec.plane_normal) if spec.interaction == "surfaceNonAdherent" else None,
                        "friction": spec.friction},
        "supports": [{"centre": list(s.centre), "radius": s.radius, "label": s.label} for s in spec.supports],
        "hidden_effect": effect_info,
        "noise": {"sigma": noise, "blur_samples": blur},
        "masks": "visible",
        "gt_sim": {"particles": int(len(gt.x0)), "spacing": gt.spacing, "dx": gt.grid.dx,
                   "substeps_per_frame": gt.substeps, "dt": 1.0 / (sz.fps * gt.substeps),
                   "fit_dt_suggested": gt.fit_dt, "transfer_tau": transfer_tau,
                   "pin_rule": list(truth_pin_rule()), "ground_contact": truth_ground_contact()},
        "suggested_init": {"grid": sz.fit_grid, "padding": sz.fit_padding,
                           "youngs_range": list(sz.fit_youngs), "max_poisson": sz.fit_poisson_max,
                           "density": spec.density, **({"transfer_tau": transfer_tau} if transfer_tau else {}),
                           # the truth starts from the scan stress-free (it sags in the video): init --no-preload
                           "preload": False},
        "generation_seconds": time.perf_counter() - t0,
    }
    write_ground_truth(out, info, e_g, nu_g, gpos,
                       dict(rest=gt.x0, E=gt.E, nu=gt.nu, volume=np.full(len(gt.x0), gt.spacing ** 3),
                            positions=x.astype(np.float32)), hmask, amodal)
    ys = sz.fit_youngs
    (out / "README.txt").write_text(
        f"Synthetic capture '{name}' ({spec.paper_name}): {spec.description}.\n"
        f"Ground truth in gt/ (never read by init, extract or fit).\n\nSuggested:\n"
        f"  physinteract-usd init scene.usda --capture {out.name} --grid {sz.fit_grid} --padding {sz.fit_padding} "
        f"--youngs-range {ys[0]:g},{ys[1]:g} --max-poisson {sz.fit_poisson_max:g} --density {spec.density:g}"
        f"{f' --transfer-tau {transfer_tau:g}' if transfer_tau else ''} --no-preload\n"
        f"  (--no-preload: the object was scanned unloaded and sags in the video; without it the first fit decides)\n")
    from .preview import contact_sheet

    contact_sheet(out, rgb, visible, hmask, cam, gt, out / "preview.png")
    outdir.finish(out)
    log(f"wrote {out} ({T} frames {sz.width}x{sz.height}, {len(g)} Gaussians) in {time.perf_counter() - t0:.1f} s")
    return info
