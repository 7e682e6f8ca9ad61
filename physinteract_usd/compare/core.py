"""The comparison of a model's animation with the measurements: arrays in, a `Comparison` out.

    result = compare(model, meas, scene)   # per-frame metrics, tracks, residuals, floor, verdict

`ModelAnimation`: the model's Gaussians per frame; `Measurements`: the video, its silhouettes and
hand masks, and point tracks measured on it (`tracks.GaussianTracks`, from
`extract.track.measure_tracks`) for the Gaussians the video shows at frame 0 (`track_start`); `SceneInfo`: camera, fps, contacts (for the phases), the
rest particles (for the residual map), gravity. No USD here."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import metrics as M
from .noise import NoiseFloor, noise_floor
from .phases import PHASES, frame_phases
from .residuals import autocorrelation, cross_correlation, nan_rms, particle_map
from .tracks import (GaussianTracks, contact_normal, lift_to_metres, model_visible, project_tracks, split_residual, unit,
                     velocities, visible_gaussians)
from .verdict import frame_failures, headline, how_it_fails


@dataclass
class ModelAnimation:
    means: np.ndarray        # (T, N, 3) Gaussian centres per frame
    covs: np.ndarray         # (T, N, 3, 3) world covariances per frame
    colors: np.ndarray       # (N, 3) RGB (or (N, K, 3) SH)
    opacities: np.ndarray    # (N,)


@dataclass
class Measurements:
    frames: np.ndarray                    # (T, H, W, 3) float in [0, 1]
    masks: np.ndarray | None              # (T, H, W) bool silhouettes (None: the model's own)
    hand_masks: np.ndarray | None         # (T, H, W) bool pixels no model of the object explains
    tracks: GaussianTracks                # measured on the video from the Gaussians seen at frame 0


@dataclass
class SceneInfo:
    camera: object                        # camera.Camera
    fps: float
    contacts: list                        # contacts.ContactSet (supports included)
    trajectories: dict                    # {contact name: (T, 3)} the model's (fitted) hand paths
    particles_rest: np.ndarray            # (P, 3)
    spacing: float                        # particle spacing (depth tolerance of visibility tests)
    gravity: tuple = (0.0, -9.81, 0.0)


@dataclass
class Comparison:
    frames: list                          # per-frame dicts (frame, phase, psnr, ..., fails)
    summary: dict                         # means over frames (psnr, psnr_masked, ssim, iou, track_error_px)
    phases: list
    floor: NoiseFloor
    verdict: dict                         # verdict, headline, failing_frames, reason
    split: dict                           # per frame mean signed components (m): velocity, gravity, contact_normal, total
    whiteness: dict
    input_correlation: dict
    gaussian_residual: dict               # phase | "all" -> (n,) RMS residual per tracked Gaussian (m)
    particle_residual: dict               # phase | "all" -> (P,) per particle (m)
    renders: dict = field(repr=False, default_factory=dict)   # rgb (T, H, W, 3), alpha (T, H, W)
    tracks: dict = field(repr=False, default_factory=dict)    # model_uv, measured_uv, valid, uv0
    mm_per_px: float = float("nan")

    def to_dict(self) -> dict:
        """The JSON-ready part (no arrays but short per-frame lists)."""
        return {**self.summary, "frames": self.frames, "verdict": self.verdict["verdict"],
                "headline": self.verdict["headline"], "failing_frames": self.verdict["failing_frames"],
                "first_failing_frame": self.verdict["first_failing_frame"],
                "failing_phases": self.verdict["failing_phases"], "reason": self.verdict.get("reason"),
                "noise_floor": self.floor.to_dict(), "residual_split_m": self.split,
                "whiteness": self.whiteness, "input_correlation": self.input_correlation,
                "residual_by_phase_m": {p: _stat(v) for p, v in self.particle_residual.items()},
                "mm_per_px": self.mm_per_px}


def _stat(v) -> dict:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"mean": None, "p90": None, "max": None}
    return {"mean": float(v.mean()), "p90": float(np.percentile(v, 90)), "max": float(v.max())}


def _f(x):
    return None if x is None or not np.isfinite(x) else float(x)


# ----------------------------------------------------------------------------------- rendering
def render_frames(anim: ModelAnimation, camera, background, *, device="cpu", progress=None) -> dict:
    """The model's frames: rgb (T, H, W, 3) over `background`, alpha and depth (T, H, W)."""
    import torch

    from ..devices import torch_device
    from ..render import render

    dev = torch_device(device)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)  # noqa: E731
    col, op, bg = t(anim.colors), t(anim.opacities), t(background)
    rgb, alpha, depth = [], [], []
    ks = range(len(anim.means))
    for k in (progress(ks) if progress else ks):
        with torch.no_grad():
            out = render(t(anim.means[k]), t(anim.covs[k]), col, op, camera.at(k), background=bg)
        rgb.append(out["rgb"].cpu().numpy())
        alpha.append(out["alpha"].cpu().numpy())
        depth.append(out["depth"].cpu().numpy())
    return {"rgb": np.stack(rgb), "alpha": np.stack(alpha), "depth": np.stack(depth)}


def track_start(means0, alpha0, depth0, camera, spacing: float, *, silhouette=None, hand=None,
                max_points: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """(ids, uv0): the Gaussians the video shows at frame 0 (the model at rest, rendered: alpha0,
    depth0) and their projections, where the measured tracks start."""
    uv0, z0 = camera.at(0).project(np.asarray(means0, float))
    ids = visible_gaussians(uv0, z0, alpha0, depth0, depth_tolerance=2.0 * spacing, silhouette=silhouette,
                            hand=hand, max_points=max_points)
    return ids, uv0[ids]


# ----------------------------------------------------------------------------------- compare
def compare(anim: ModelAnimation, meas: Measurements, scene: SceneInfo, *, renders: dict | None = None,
            background=None, device="cpu", progress=None) -> Comparison:
    """Everything the report shows (see the package doc). `renders`: the model's frames if already
    rendered (`render_frames`), else rendered here over `background` (default: the video's
    median)."""
    frames = np.asarray(meas.frames, np.float32)
    T = min(len(frames), len(anim.means))
    frames = frames[:T]
    if renders is None:
        bg = np.median(frames, axis=0) if background is None else background
        renders = render_frames(anim, scene.camera, bg, device=device, progress=progress)
    rgb, alpha, depth = renders["rgb"][:T], renders["alpha"][:T], renders["depth"][:T]
    hands = None if meas.hand_masks is None else np.asarray(meas.hand_masks[:T], bool)
    sil_true = None if meas.masks is None else np.asarray(meas.masks[:T], bool)

    # ---- image metrics per frame
    phases = frame_phases(scene.contacts, T, scene.fps, scene.trajectories)
    per = []
    for k in range(T):
        sil = alpha[k] > 0.5
        d = M.frame_metrics(rgb[k], frames[k], sil, sil if sil_true is None else sil_true[k],
                            None if hands is None else hands[k])
        per.append(d)
    mse = np.array([10 ** (-min(d["psnr_masked"], 100) / 10) if np.isfinite(d["psnr_masked"]) else np.nan
                    for d in per])

    # ---- tracks: the model's Gaussians projected vs the measured tracks
    tr = meas.tracks
    ids = np.asarray(tr.ids, np.int64)
    mu = np.asarray(anim.means[:T], float)[:, ids]
    model_uv, z = project_tracks(mu, scene.camera)
    vis = model_visible(model_uv, z, alpha, depth, 2.0 * scene.spacing)
    valid = np.asarray(tr.valid[:T], bool) & vis
    res_px = np.where(valid[..., None], np.asarray(tr.uv[:T], float) - model_uv, np.nan)
    err_px = np.linalg.norm(res_px, axis=-1)
    n_tracks = valid.sum(1)
    track_error = np.array([float(np.nanmean(err_px[k])) if n_tracks[k] else np.nan for k in range(T)])

    # ---- the tracker's bias on this motion and texture: the same tracker run on the model's rendered
    # frames, against the model's known projections (what a perfect model's plain track error would
    # be); and the track error with that bias removed: the video's tracks against the model's video's
    # tracks (same tracker, same start points: what the verdict judges)
    from ..extract.track import measure_tracks

    calib = measure_tracks(rgb, model_uv[0], start=0, stop=hands, progress=progress)
    cvalid = calib.valid & vis
    render_px = np.array([float(np.mean(np.linalg.norm(calib.uv[k][cvalid[k]] - model_uv[k][cvalid[k]], axis=1)))
                          if cvalid[k].sum() >= 3 else np.nan for k in range(T)])
    both = valid & calib.valid
    debiased = np.array([float(np.mean(np.linalg.norm(calib.uv[k][both[k]] - np.asarray(tr.uv[k])[both[k]], axis=1)))
                        if both[k].sum() >= 3 else np.nan for k in range(T)])

    # speeds (px / frame) of the same points in the video and the model's video (same tracker)
    video_speed, model_speed = np.full(T, np.nan), np.full(T, np.nan)
    for k in range(1, T):
        pair = both[k] & both[k - 1]
        if pair.sum() >= 3:
            video_speed[k] = float(np.mean(np.linalg.norm(tr.uv[k][pair] - tr.uv[k - 1][pair], axis=1)))
            model_speed[k] = float(np.mean(np.linalg.norm(calib.uv[k][pair] - calib.uv[k - 1][pair], axis=1)))

    # ---- the noise floor
    rest = [k for k in range(T) if phases[k] == "rest"] or [0]
    cover = alpha > 0.05               # the model's object, the video's silhouette and the hand: not background
    if sil_true is not None:
        cover = cover | sil_true
    if hands is not None:
        cover = cover | hands
    floor = noise_floor(frames, cover, [mse[k] for k in rest], tr.background_uv, tr.background_valid,
                        tr.fb_error[:T] if tr.fb_error is not None else None, np.asarray(tr.valid[:T], bool),
                        render_px=render_px)

    # ---- residual motion in metres, split along physical directions
    # (the video's tracks against the model video's tracks: the tracker's bias removed)
    res_db = np.where(both[..., None], np.asarray(tr.uv[:T], float) - calib.uv, 0.0)
    res_m = lift_to_metres(res_db, z, scene.camera)
    vel = velocities(mu, scene.fps)
    normal = contact_normal(scene.contacts, scene.particles_rest)
    split_tn = split_residual(res_m, both, vel, scene.gravity, normal)
    split = {name: [_f(np.nanmean(v[k])) if np.isfinite(v[k]).any() else None for k in range(T)]
             for name, v in split_tn.items()}
    zf = z[valid]
    mm_per_px = float(np.median(zf) / scene.camera.fx * 1000) if zf.size else float("nan")

    # ---- whiteness and correlation with the input (the hand's motion along its main direction)
    T_keep = np.arange(T) > 0          # frame 0 is zero by construction
    ac = autocorrelation(np.where(T_keep[:, None, None], res_m, 0.0), both & T_keep[:, None], max_lag=min(10, T // 2))
    u, d_hat = _input_signal(scene, T)
    e = np.array([np.nanmean((res_m[k][both[k]] @ d_hat)) if both[k].any() and k > 0 else np.nan
                  for k in range(T)]) if d_hat is not None else np.full(T, np.nan)
    xc = cross_correlation(e, u if u is not None else np.full(T, np.nan), max_lag=min(10, T // 2))
    xc["input"] = "hand velocity along its main direction (m/s)"
    xc["residual"] = "mean residual motion along that direction (m)"

    # ---- the residual map, per phase
    total = split_tn["total"]
    g_res = {"all": nan_rms(np.where(T_keep[:, None], total, np.nan), axis=0)}
    for p in PHASES:
        ks = [k for k in range(T) if phases[k] == p and k > 0]
        if ks:
            g_res[p] = nan_rms(total[ks], axis=0)
    g_rest = np.asarray(anim.means[0], float)[ids]
    p_res = {p: particle_map(v, g_rest, scene.particles_rest) for p, v in g_res.items()}

    # ---- per-frame table and the verdict
    n_both = both.sum(1)
    fail, how = frame_failures(debiased, floor.track_px, n_both, mse, floor.photometric_mse)
    fail[0] = False if phases[0] == "rest" else fail[0]
    for k, d in enumerate(per):
        d.update({"frame": k, "phase": phases[k], "track_error_px": _f(track_error[k]),
                  "track_floor_px": _f(floor.track_px[k]), "tracks": int(n_tracks[k]),
                  "track_error_debiased_px": _f(debiased[k]), "tracker_bias_px": _f(render_px[k]),
                  "model_speed_px": _f(model_speed[k]), "video_speed_px": _f(video_speed[k]),
                  "judged_by": how[k], "fails": bool(fail[k])})
        for key in ("psnr", "psnr_masked", "ssim", "iou"):
            d[key] = _f(min(d[key], 100.0)) if d[key] is not None else None
    code, words = ("", "")
    if fail.any():
        code, words = how_it_fails(fail, model_speed, video_speed, floor.track_px,
                                   {k: np.asarray([np.nan if x is None else x for x in v], float) for k, v in split.items()},
                                   iou=[d["iou"] for d in per])
    verdict = headline(fail, phases, words, track_error=track_error, debiased=debiased, track_floor=floor.track_px,
                       psnr_masked=[d["psnr_masked"] if d["psnr_masked"] is not None else np.nan for d in per])
    verdict["reason"] = code or None
    summary = M.summarize(per)
    for key, arr in (("track_error_px", track_error), ("track_error_debiased_px", debiased), ("tracker_bias_px", render_px)):
        a = arr[1:] if T > 1 else arr
        summary[key] = _f(np.nanmean(a)) if np.isfinite(a).any() else None
    return Comparison(per, summary, phases, floor, verdict, split, ac, xc, g_res, p_res,
                      renders={"rgb": rgb, "alpha": alpha},
                      tracks={"model_uv": model_uv, "measured_uv": np.asarray(tr.uv[:T], float),
                              "valid": valid, "uv0": model_uv[0], "ids": ids, "model_video_uv": calib.uv,
                              "both": both},
                      mm_per_px=mm_per_px)


def _input_signal(scene: SceneInfo, T: int):
    """u (T,): the moving interaction's velocity along its main direction while it acts (0 after
    release), and that direction; (None, None) without one."""
    best = None
    for c in scene.contacts:
        if not c.is_interaction:
            continue
        tr = scene.trajectories.get(c.name, c.trajectory)
        if tr is None or len(tr) < 2:
            continue
        tr = np.asarray(tr, float)[:T]
        span = float(np.linalg.norm(tr.max(0) - tr.min(0)))
        if best is None or span > best[0]:
            best = (span, c, tr)
    if best is None or best[0] <= 0:
        return None, None
    _, c, tr = best
    centred = tr - tr.mean(0)
    d_hat = unit(np.linalg.svd(centred, full_matrices=False)[2][0])
    u = np.zeros(T)
    u[: len(tr)] = np.gradient(tr @ d_hat) * scene.fps if len(tr) > 1 else 0.0
    u *= np.array([c.active(k) for k in range(T)], float)
    return u, d_hat
