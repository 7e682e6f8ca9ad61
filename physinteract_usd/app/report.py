"""`report`: compare the fitted model with the measurements and say where it fails.

Reads the stage (its video, silhouettes, hand masks, contacts, fitted trajectories and the
animation it shows, or with `resimulate` the animation of its material as composed now, e.g. an
E the user authored over the fitted field, simulated under the fitted interaction), measures point
tracks on the video (`adapters.measured_tracks`, cached next to the stage), runs the comparison
(`compare.compare`: per-frame metrics and track error, phases, noise floor, residuals, verdict),
writes the per-particle residual maps into the fit layer (`usd.report_io`), and the outputs asked
for: a self-contained HTML page, an MP4 and PNGs of the side-by-side frames. Returns the report's
JSON (the design's keys, plus the verdict, headline, noise floor, residual split, whiteness...).

Nothing the user wrote is replaced: an output file that exists is overwritten only when this verb
wrote it (recorded in `<stem>.report/outputs.json`) or with `force`."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from .jsonsafe import json_safe
from .. import __version__
from ..compare import Measurements, ModelAnimation, SceneInfo, compare, render_frames
from ..compare import figures
from ..compare.html import page
from ..errors import InputError
from ..render import covariance_from_scales_quats, estimate_background
from ..usd.fit_io import read_splat_animation
from ..usd.layout import LayerPaths
from ..usd.report_io import write_residuals
from .adapters import effects_with_fitted, load_observations, measured_tracks, read_scene, stage_contacts

MAX_HTML_FRAMES = 16

NOTES = {
    "metrics": "Per frame, the fitted model re-rendered against the video. Top: PSNR over the full frame and "
               "inside the union of the true and rendered silhouettes (masked), against the video's noise floor "
               "(its own pixel noise, from the static background's frame-to-frame differences, and the model's "
               "error at rest, where no dynamics are involved). A sub-pixel misalignment of sharp texture costs "
               "many dB, so the verdict judges motion, not pixels. Middle: SSIM and silhouette IoU. Bottom: 2D "
               "track error, the mean distance between point tracks measured on the video (OpenCV DIS flow, "
               "forward-backward checked) and the model's Gaussians projected; the same tracker's error on the "
               "model's own rendered frames (its bias: flow underestimates large motions of fine texture); and the "
               "track error without that bias (the video's tracks against the model video's tracks), which a "
               "frame fails when it exceeds 3x the tracker's noise floor (static background drift, "
               "forward-backward disagreement, at least 0.25 px). Background colours are the phases; red lines "
               "mark failing frames.",
    "split": "The residual motion (video minus model, in the image plane, mm) averaged over the tracked points, "
             "split along the model's own velocity (positive: the video moves further than the model: it lags), "
             "gravity (positive: the video hangs lower: the model sags too little) and the contact normal "
             "(positive: the video is further out). A missing effect leaves a signature here: damping shows "
             "along the velocity after release, a wrong stiffness along gravity while the hand holds it.",
    "residual_map": "Where on the object the model fails, per phase: each tracked point at its frame-0 position, "
                    "coloured by its RMS residual motion over that phase's frames. The same maps are on the "
                    "stage as primvars on SimParticles (physinteract:residual, physinteract:residual_<phase>), so "
                    "Blender colours the point cloud by them.",
    "whiteness": "As System Identification's resid: left, the autocorrelation of the residual motion over time "
                 "(pooled over the tracks); right, its cross-correlation with the input (the hand's velocity "
                 "along its main direction). Inside the 99% band: residuals look like noise (white, unrelated to "
                 "the input). Outside: the model leaves structure unexplained (a slow drift, a swing, a lag).",
    "versions": "Every fit version on the stage: its final loss and mean PSNR, annotated with the effects it "
                "had. Add an effect and refit: the error should fall.",
    "frames": "Each row: the video frame, the model's frame, and the per-pixel error (inferno, the hand grey) with "
              "the track residuals drawn from the model's point to the video's (green).",
}


def _resimulated(sd, device):
    """The stage's material as composed now, simulated under its contacts with the fitted
    trajectories and effects: (means (T, N, 3), covs (T, N, 3, 3))."""
    import torch

    from ..simulation import build_simulation

    fitted = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    contacts = [c.replace(trajectory=np.asarray(fitted[c.name])) if c.name in fitted and c.is_interaction else c
                for c in stage_contacts(sd)]
    try:
        sim = build_simulation(sd, contacts, sd.n_frames, effects=effects_with_fitted(sd), device=device)
    except ValueError as exc:
        raise InputError(sd.path, str(exc)) from None
    st = sd.settings
    E = torch.as_tensor(sd.youngs_modulus, dtype=sim.tdtype).clamp(st.youngs_min, st.youngs_max)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, st.poisson_max), dtype=sim.tdtype)
    with torch.no_grad():
        x, F = sim.simulate(E, nu)
        means, covs = zip(*[sim.gaussians_at(x[k], F[k]) for k in range(sd.n_frames)])
    return np.stack([m.cpu().numpy() for m in means]), np.stack([c.cpu().numpy() for c in covs])


def _stage_animation(stage_path, sd):
    anim = read_splat_animation(stage_path)
    if not anim["times"]:
        raise InputError(stage_path, "has no fitted animation: run `physinteract-usd fit` first "
                         "(or `report --resimulate` to simulate its material under its contacts)")
    import torch

    T = min(len(anim["times"]), sd.n_frames)
    means = np.stack(anim["positions"][:T])
    covs = np.stack([covariance_from_scales_quats(torch.as_tensor(anim["scales"][k]), torch.as_tensor(anim["quats"][k])).numpy()
                     for k in range(T)])
    return means, covs


def versions(sd) -> list[dict]:
    """The design's versions list: {"version", "effects", "psnr" (mean over frames), "loss"} per fit
    version on the stage, plus whether it is the one the stage shows."""
    out = []
    for r in sd.reports:
        ps = [min(float(p), 100.0) for p in r.get("psnr", []) if np.isfinite(p)]
        out.append({"version": int(r["version"]), "effects": list(r.get("effects", [])),
                    "psnr": float(np.mean(ps)) if ps else None,
                    "loss": float(r["final_loss"]) if r.get("final_loss") is not None else None,
                    "current": bool(r.get("current", r is sd.reports[-1]))})
    return out


# ------------------------------------------------------------------------------- outputs
class _Outputs:
    """What this verb wrote before (`<stem>.report/outputs.json`: path -> size, mtime): such a file
    may be replaced; any other existing file only with `force`."""

    def __init__(self, stage_path, force: bool):
        self.path = LayerPaths.of(stage_path).sibling(".report") / "outputs.json"
        self.force = force
        try:
            self.known = json.loads(self.path.read_text())
        except (OSError, ValueError):
            self.known = {}

    def check(self, target: Path) -> None:
        target = Path(target)
        if not target.exists() or self.force:
            return
        rec = self.known.get(str(target.resolve()))
        st = target.stat()
        if target.is_dir():
            ours = set(rec or []) if isinstance(rec, list) else set()
            others = [p.name for p in target.iterdir() if p.name not in ours]
            if others:
                raise InputError(target, f"holds files this report did not write ({others[0]}, ...): "
                                 "choose another folder or use --force")
            return
        if not rec or rec != [st.st_size, st.st_mtime_ns]:
            raise InputError(target, "exists and was not written by `report`: choose another path or use --force")

    def record(self, target: Path, names: list[str] | None = None) -> None:
        target = Path(target)
        st = target.stat()
        self.known[str(target.resolve())] = names if names is not None else [st.st_size, st.st_mtime_ns]

    def save(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(f".outputs.tmp{os.getpid()}.json")
            tmp.write_text(json.dumps(self.known, indent=1))
            tmp.replace(self.path)
        except OSError:
            pass


def _write_video(path: Path, frames_u8: list, fps: float) -> None:
    import cv2

    h, w = frames_u8[0].shape[:2]
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix or '.mp4'}")
    vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w - w % 2, h - h % 2))
    if not vw.isOpened():
        raise InputError(path, "cannot open a video writer for this path (use a .mp4 name)")
    try:
        for f in frames_u8:
            vw.write(np.ascontiguousarray(f[: h - h % 2, : w - w % 2, ::-1]))
    finally:
        vw.release()
    if not tmp.exists() or tmp.stat().st_size == 0:
        raise OSError(f"{path}: the video writer wrote nothing")
    os.replace(tmp, path)


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _check_out_dir(path, what: str) -> Path:
    path = Path(path)
    if not path.parent.exists():
        raise InputError(path, f"the folder for the {what} does not exist")
    return path


# ---------------------------------------------------------------------------------- verb
def report(stage_path, *, html=None, video=None, frames_dir=None, write_stage: bool = True, resimulate: bool = False,
           force: bool = False, device: str = "cpu", progress: bool = True, log=print) -> dict:
    """Compare the stage's model with its video (see the module doc); returns the report's JSON."""
    t0 = time.perf_counter()
    stage_path = Path(stage_path)
    html = None if html is None else _check_out_dir(html, "HTML page")
    video = None if video is None else _check_out_dir(video, "video")
    if frames_dir is not None and not Path(frames_dir).parent.exists():
        raise InputError(frames_dir, "the folder for the frames' folder does not exist")
    outputs = _Outputs(stage_path, force)
    for p in (html, video, frames_dir):
        if p is not None:
            outputs.check(Path(p))
    sd = read_scene(stage_path)
    obs = load_observations(sd)
    if resimulate:
        log("re-simulating the stage's material under its fitted interaction")
        means, covs = _resimulated(sd, device)
    else:
        means, covs = _stage_animation(stage_path, sd)
    T = min(len(means), sd.n_frames)
    bar = _progress(progress)
    g = sd.gaussians
    anim = ModelAnimation(means[:T], covs[:T], g.colors, g.opacities)
    cover = obs.masks
    if obs.hand_masks is not None:
        cover = obs.hand_masks if cover is None else (cover | obs.hand_masks)
    bg = estimate_background(obs.frames, cover, dilate=2) if cover is not None else np.median(obs.frames, axis=0)
    renders = render_frames(anim, sd.camera, bg, device=device, progress=bar("render"))
    tracks = measured_tracks(sd, obs, device=device, progress=bar("tracks"))
    fitted = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    scene = SceneInfo(sd.camera, sd.fps, list(sd.contacts), fitted, sd.particles_positions,
                      sd.settings.particle_spacing, tuple(sd.settings.gravity))
    meas = Measurements(obs.frames[:T], None if obs.masks is None else obs.masks[:T],
                        None if obs.hand_masks is None else obs.hand_masks[:T], tracks)
    cmp = compare(anim, meas, scene, renders=renders, progress=bar("model tracks"))
    data = cmp.to_dict()
    vers = versions(sd)
    current = getattr(sd, "current_version", None)
    if current is None and vers:
        current = next((v["version"] for v in vers if v["current"]), vers[-1]["version"])
    data.update({"versions": vers, "version": current, "resimulated": bool(resimulate), "stage": str(stage_path),
                 "n_frames": T, "tracked_points": int(len(tracks.ids)),
                 "generator": f"physinteract-usd {__version__}", "outputs": {}})

    if write_stage:
        layer = write_residuals(stage_path, sd.fps, sd.n_frames, cmp.particle_residual,
                                summary={"verdict": data["verdict"], "headline": data["headline"],
                                         "version": current if current is not None else 0,
                                         "resimulated": bool(resimulate),
                                         "failingFrames": ",".join(map(str, data["failing_frames"]))})
        data["outputs"]["stage_layer"] = layer
        data["outputs"]["primvars"] = sorted(f"primvars:physinteract:residual{'' if p == 'all' else '_' + p}"
                                             for p in cmp.particle_residual)

    if html is not None or video is not None or frames_dir is not None:
        vmax = figures.heat_scale(cmp, obs.frames)
        sbs = [figures.side_by_side(cmp, obs.frames, obs.hand_masks, k, vmax=vmax)
               for k in bar("frames")(range(T))]
        if frames_dir is not None:
            d = Path(frames_dir)
            d.mkdir(exist_ok=True)
            names = []
            for k, im in enumerate(sbs):
                names.append(f"frame_{k:06d}.png")
                _atomic_write(d / names[-1], figures.png_bytes(im))
            outputs.record(d, names)
            data["outputs"]["frames"] = str(d)
        if video is not None:
            _write_video(Path(video), sbs, sd.fps)
            outputs.record(Path(video))
            data["outputs"]["video"] = str(video)
        if html is not None:
            data["outputs"]["html"] = str(html)
            plots = {"metrics": figures.plot_metrics(cmp), "split": figures.plot_split(cmp),
                     "residual_map": figures.plot_residual_map(cmp, obs.frames[0]),
                     "whiteness": figures.plot_whiteness(cmp), "versions": figures.plot_versions(vers)}
            keep = _html_frames(cmp, T)
            text = page(f"physinteract-usd report: {stage_path.name}", data, plots,
                        [(k, figures.png_bytes(sbs[k])) for k in keep], NOTES)
            _atomic_write(Path(html), text.encode())
            outputs.record(Path(html))
        outputs.save()
    data["runtime_s"] = time.perf_counter() - t0
    return json_safe(data)


def _html_frames(cmp, T: int) -> list[int]:
    """Every frame of a short clip; of a long one, evenly spaced frames plus the failing ones."""
    if T <= MAX_HTML_FRAMES:
        return list(range(T))
    keep = set(np.linspace(0, T - 1, MAX_HTML_FRAMES // 2).astype(int).tolist())
    keep |= set(cmp.verdict["failing_frames"][: MAX_HTML_FRAMES // 2])
    return sorted(keep)


def _progress(enabled: bool):
    """bar(desc) -> a function wrapping an iterable in a tqdm bar (or not)."""
    if not enabled:
        return lambda desc: (lambda it: it)
    from tqdm import tqdm

    return lambda desc: (lambda it: tqdm(it, desc=desc, unit="frame", leave=False, dynamic_ncols=True))
