"""The Python API behind every CLI verb (the CLI and the Blender add-on are thin clients of it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .capture import read_capture
from .errors import InputError
from .fill import fill_from_gaussians, fill_from_mesh
from .usd.stage import SimSettings, read_stage, write_init_stage

DEFAULT_GRID = 32
DEFAULT_PADDING = 0.5
DEFAULT_E_RANGE = (1e3, 1e6)
MAX_POISSON = 0.45  # default: the fit keeps nu in (0, max_poisson]: the CFL bound is taken there


def choose_sim_settings(points: np.ndarray, fps: float, grid: int = DEFAULT_GRID,
                        padding: float = DEFAULT_PADDING, youngs_range=DEFAULT_E_RANGE,
                        poisson: float = 0.3, density: float = 1000.0,
                        constitutive_model: str = "fixedCorotated", max_poisson: float = MAX_POISSON,
                        spacing: float | None = None) -> SimSettings:
    """Domain = the object's bounding box padded by `padding` x its extent on every side; `grid`
    cells along the longest side; particle spacing dx / 2; substeps from the CFL bound at the
    largest E allowed."""
    if grid < 8:
        raise InputError("--grid", "must be at least 8 cells")
    if not (0 < youngs_range[0] < youngs_range[1]):
        raise InputError("--youngs-range", "needs 0 < min < max")
    if not (0.0 < max_poisson < 0.5):
        raise InputError("--max-poisson", "must lie in (0, 0.5)")
    if not (0.0 < poisson <= max_poisson):
        raise InputError("--poisson", f"must lie in (0, {max_poisson:g}] (--max-poisson)")
    lo, hi = points.min(0), points.max(0)
    extent = float(np.max(hi - lo))
    if not extent > 0:
        raise InputError("object", "the object has zero extent")
    pad = padding * extent
    dlo, dhi = lo - pad, hi + pad
    dx = float(np.max(dhi - dlo)) / grid
    res = np.maximum(np.ceil((dhi - dlo) / dx).astype(int), 4)
    centre = 0.5 * (dlo + dhi)
    dlo = centre - 0.5 * res * dx
    dhi = dlo + res * dx
    substeps = substeps_per_frame(fps, dx, youngs_range[1], max_poisson, density)
    if spacing is not None and not (0 < spacing):
        raise InputError("--spacing", "must be positive")
    return SimSettings(domain_min=dlo, domain_max=dhi, grid_resolution=tuple(int(r) for r in res),
                       cell_size=dx, particle_spacing=float(spacing or dx / 2.0), substeps=substeps,
                       youngs_min=float(youngs_range[0]), youngs_max=float(youngs_range[1]),
                       poisson_default=float(poisson), poisson_max=float(max_poisson), density=float(density),
                       constitutive_model=constitutive_model)


def substeps_per_frame(fps: float, dx: float, youngs_max: float, poisson_max: float, density: float) -> int:
    """Substeps per video frame from the CFL bound at the stiffest material allowed."""
    from .sim.cfl import substeps_per_frame as cfl_substeps

    return cfl_substeps(fps, dx, youngs_max, poisson_max, density)


def init(stage_path, capture_dir=None, *, object=None, video=None, camera=None, masks=None,
         fps=None, masks_amodal=False, grid=DEFAULT_GRID, padding=DEFAULT_PADDING,
         youngs_range=DEFAULT_E_RANGE, poisson=0.3, density=1000.0,
         constitutive_model="fixedCorotated", max_poisson=MAX_POISSON, spacing=None, force=False):
    """Build a stage from a capture. Returns the LayerPaths written."""
    stage_path = Path(stage_path)
    if stage_path.exists() and not force:
        raise InputError(stage_path, "already exists: `init --force` replaces the generated layers "
                         "and keeps your root layer")
    cap = read_capture(capture_dir, object=object, video=video, camera=camera, masks=masks, fps=fps,
                       masks_amodal=masks_amodal)
    g = cap.object.gaussians
    settings = choose_sim_settings(g.means if cap.object.mesh is None else cap.object.mesh.vertices,
                                   cap.fps, grid, padding, youngs_range, poisson, density,
                                   constitutive_model, max_poisson, spacing)
    try:
        if cap.object.mesh is not None:
            parts = fill_from_mesh(cap.object.mesh, settings.particle_spacing, g, anchor=settings.domain_min)
        else:
            parts = fill_from_gaussians(g, settings.particle_spacing, anchor=settings.domain_min)
    except ValueError as exc:
        raise InputError(cap.object.path, str(exc)) from None
    return write_init_stage(stage_path, cap, parts, settings, force=force)


def info(stage_path) -> dict:
    """A summary of a stage as a dict (the CLI prints it, or its JSON)."""
    sd = read_stage(stage_path)
    cam = sd.camera.at(0)
    d = {
        "stage": str(sd.path),
        "generator": sd.generator,
        "object": {"kind": sd.object_kind, "gaussians": len(sd.gaussians),
                   "sh_degree": sd.gaussians.sh_degree,
                   "bounds": [sd.gaussians.means.min(0).round(4).tolist(), sd.gaussians.means.max(0).round(4).tolist()]},
        "particles": {"count": int(len(sd.particles_positions)), "surface": int(sd.particles_surface.sum()),
                      "spacing_m": sd.settings.particle_spacing,
                      "total_volume_m3": float(sd.particles_volumes.sum()),
                      "mass_kg": float(sd.particles_volumes.sum() * sd.settings.density),
                      "constitutive_model": sd.settings.constitutive_model},
        "frames": {"count": sd.n_frames, "fps": sd.fps, "size": list(sd.image_size),
                   "source": sd.video_asset or (str(Path(sd.frame_assets[0]).parent) if sd.frame_assets else None),
                   "masks": len(sd.mask_assets), "masks_amodal": sd.masks_amodal},
        "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                   "static": sd.camera.is_static, "position": cam.position.round(4).tolist()},
        "simulation": {"grid": list(sd.settings.grid_resolution), "cell_size_m": sd.settings.cell_size,
                       "domain": [sd.settings.domain_min.round(4).tolist(), sd.settings.domain_max.round(4).tolist()],
                       "substeps_per_frame": sd.settings.substeps,
                       "youngs_range_pa": [sd.settings.youngs_min, sd.settings.youngs_max]},
        "effects": sd.effects,
        "contacts": [{"name": c.name, "type": c.contact_type, "particles": int(len(c.particle_indices)),
                      "grasp": c.grasp_time, "release": c.release_time, "source": c.source} for c in sd.contacts],
        "trajectories": [{"name": t.name, "contact": t.contact_set, "stage": t.stage, "samples": int(len(t.frames))}
                         for t in sd.trajectories],
        "fits": [{"version": r["version"], "effects": r["effects"],
                  "psnr": float(np.mean(r["psnr"])) if r["psnr"] else None,
                  "final_loss": r["final_loss"], "runtime_s": r["runtime_s"], "device": r["device"]}
                 for r in sd.reports],
    }
    e = sd.youngs_modulus
    d["material"] = {"youngs_modulus_pa": {"min": float(e.min()), "median": float(np.median(e)), "max": float(e.max())},
                     "poisson_ratio": {"min": float(sd.poisson_ratio.min()), "max": float(sd.poisson_ratio.max())},
                     "fitted": bool(sd.reports)}
    if sd.confidence is not None:
        c = sd.confidence
        d["material"]["confidence"] = {"min": float(c.min()), "mean": float(c.mean()), "max": float(c.max()),
                                       "low_share": float(np.mean(c < 0.5))}
    return d


def format_info(d: dict) -> str:
    o, p, f, c, s, m = d["object"], d["particles"], d["frames"], d["camera"], d["simulation"], d["material"]
    lines = [
        f"stage       {d['stage']}  ({d['generator']})",
        f"object      {o['kind']}: {o['gaussians']} Gaussians, SH degree {o['sh_degree']}, "
        f"bounds {o['bounds'][0]} .. {o['bounds'][1]} m",
        f"particles   {p['count']} ({p['surface']} at the surface), spacing {p['spacing_m'] * 1000:.2f} mm, "
        f"volume {p['total_volume_m3'] * 1e6:.1f} cm^3, mass {p['mass_kg'] * 1000:.1f} g, {p['constitutive_model']}",
        f"frames      {f['count']} at {f['fps']:g} fps, {f['size'][0]}x{f['size'][1]}, from {f['source']}"
        + (f", {f['masks']} masks ({'amodal' if f['masks_amodal'] else 'visible-only'})" if f["masks"] else ", no masks"),
        f"camera      fx {c['fx']:.2f} fy {c['fy']:.2f} cx {c['cx']:.2f} cy {c['cy']:.2f}, "
        f"{'static' if c['static'] else 'moving'}, at {c['position']}",
        f"simulation  grid {'x'.join(map(str, s['grid']))}, dx {s['cell_size_m'] * 1000:.2f} mm, "
        f"{s['substeps_per_frame']} substeps/frame, E in [{s['youngs_range_pa'][0]:.3g}, {s['youngs_range_pa'][1]:.3g}] Pa",
        f"material    E {m['youngs_modulus_pa']['min']:.3g} .. {m['youngs_modulus_pa']['max']:.3g} Pa "
        f"(median {m['youngs_modulus_pa']['median']:.3g}), nu {m['poisson_ratio']['min']:.3f} .. "
        f"{m['poisson_ratio']['max']:.3f}" + ("" if m["fitted"] else "  (not fitted yet)"),
    ]
    if "confidence" in m:
        cf = m["confidence"]
        lines.append(f"confidence  mean {cf['mean']:.2f} (min {cf['min']:.2f}, max {cf['max']:.2f}); "
                     f"{cf['low_share'] * 100:.0f}% of particles below 0.5: the video says little about E there")
    lines.append("effects     " + (", ".join(f"{k} {v}" for k, v in d["effects"].items()) or "none (base model)"))
    if d["contacts"]:
        for ct in d["contacts"]:
            lines.append(f"contact     {ct['name']}: {ct['type']}, {ct['particles']} particles, "
                         + (f"frames {ct['grasp']:g}..{ct['release']:g}" if ct['release'] < 1e7 else f"from frame {ct['grasp']:g} on")
                         + f" ({ct['source']})")
    else:
        lines.append("contact     none yet (`physinteract-usd extract` finds them; `fit` runs it)")
    for t in d["trajectories"]:
        lines.append(f"trajectory  {t['name']}: {t['stage']}, {t['samples']} samples, moves {t['contact']}")
    if d["fits"]:
        for r in d["fits"]:
            psnr = f"PSNR {r['psnr']:.2f} dB, " if r["psnr"] is not None else ""
            lines.append(f"fit v{r['version']}      effects [{', '.join(r['effects']) or 'none'}], {psnr}"
                         f"loss {r['final_loss']:.4g}, {r['runtime_s']:.0f} s on {r['device']}")
    else:
        lines.append("fits        none yet")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ fit
def _cpu_threads(device: str) -> None:
    """On the CPU, Warp runs single-threaded and the fit's torch ops are small: torch's thread
    pool only adds synchronisation (8 ms per op measured on a busy 2-core machine)."""
    if str(device) == "cpu":
        import torch

        torch.set_num_threads(1)


def load_observations(sd):
    """Frames and masks a stage refers to, as arrays (the fit's observations)."""
    from .fit.problem import Observations
    from .frames import ImageSequence, VideoFile, read_mask

    if sd.frame_assets:
        src = ImageSequence([Path(p) for p in sd.frame_assets])
    elif sd.video_asset:
        src = VideoFile(sd.video_asset)
    else:
        raise InputError(sd.path, "the stage names no frames and no video")
    if len(src) < sd.n_frames:
        raise InputError(src.path, f"{len(src)} frames but the stage expects {sd.n_frames}")
    frames = np.stack([src.read(k) for k in range(sd.n_frames)]).astype(np.float32)
    masks = None
    if sd.mask_assets:
        masks = np.stack([read_mask(p) for p in sd.mask_assets[: sd.n_frames]])
    return Observations(frames=frames, masks=masks)


def contacts_from_gt(sd, gt_dir):
    """Contacts, supports and the initial trajectory from a synthetic capture's gt/ (the truth:
    for experiments before extraction exists, `fit --contact-from DIR/gt`)."""
    import dataclasses
    import json

    from .fit.problem import ContactSpec

    gt_dir = Path(gt_dir)
    p = gt_dir / "gt.json"
    if not p.exists():
        raise InputError(p, "file not found (is this a synth capture's gt/ folder?)")
    g = json.loads(p.read_text())
    it = g["interaction"]
    x0 = sd.particles_positions
    traj = np.asarray(it["trajectory"], np.float64)
    if len(traj) != sd.n_frames:
        raise InputError(p, f"trajectory has {len(traj)} frames, the stage {sd.n_frames}")
    contacts = []
    cp = np.asarray(it["contact_point"])
    if it["type"] == "pointAdherent":
        d = np.linalg.norm(x0 - cp, axis=1)
        idx = np.where(d < it["contact_radius"])[0]
        if len(idx) < 3:
            idx = np.argsort(d)[:3]
        contacts.append(ContactSpec("hand", "pointAdherent", idx, it["grasp_frame"], it["release_frame"], traj))
    elif it["type"] == "pointNonAdherent":
        contacts.append(ContactSpec("finger", "pointNonAdherent", np.zeros(0, np.int64), it["grasp_frame"],
                                    it.get("release_frame"), traj, radius=it["collider_radius"],
                                    friction=it.get("friction", 0.5)))
    else:
        contacts.append(ContactSpec("palm", "surfaceNonAdherent", np.zeros(0, np.int64), it["grasp_frame"],
                                    it.get("release_frame"), traj, normal=tuple(it["plane_normal"]),
                                    friction=it.get("friction", 0.5)))
    fixed = np.zeros(len(x0), bool)
    for s in g["supports"]:
        fixed |= np.linalg.norm(x0 - np.asarray(s["centre"]), axis=1) < s["radius"]
    if contacts[0].type == "pointAdherent":
        fixed[contacts[0].indices] = False
    if fixed.any():
        contacts.append(ContactSpec("support", "fixed", np.where(fixed)[0]))
    return [dataclasses.replace(c, source="groundTruth") for c in contacts]


def _hand_masks(sd, n):
    from .frames import read_mask

    if not sd.hand_mask_assets:
        return None
    return np.stack([read_mask(p) for p in sd.hand_mask_assets[:n]])


def stage_contacts(sd):
    """The contact sets and initial trajectories the stage holds (user, extracted or earlier fits)."""
    from .fit.problem import ContactSpec

    init = {t.contact_set: t for t in sd.trajectories if t.stage in ("initial", "user", "groundTruth")}
    out = []
    for c in sd.contacts:
        tr = init.get(c.name)
        traj = None
        if tr is not None:
            traj = np.asarray(tr.positions, float)
            if len(traj) != sd.n_frames:
                raise InputError(sd.path, f"trajectory of {c.name} has {len(traj)} samples for {sd.n_frames} frames")
        if c.contact_type != "fixed" and traj is None:
            raise InputError(sd.path, f"contact set {c.name} ({c.contact_type}) has no initial trajectory")
        out.append(ContactSpec.from_stage(c, traj, sd.n_frames))
    return out


def fit(stage_path, *, iterations=60, joint=True, contact_from=None, device="cpu", seed=0,
        resume=False, progress=True, log=print, settings_overrides=None):
    """Fit the stage's material field and trajectory to its video; write scene.fit.usdc."""
    import dataclasses

    from .fit import FitProblem, FitSettings
    from .fit import fit as run_fit
    from .fit.optimize import select_supports
    from .usd.stage import write_fit_layer

    _cpu_threads(device)
    sd = read_stage(stage_path)
    obs = load_observations(sd)
    source = "extracted"
    if contact_from is not None:
        contacts = contacts_from_gt(sd, contact_from)
        from .frames import read_mask

        hm = Path(contact_from) / "hand_masks"
        if hm.is_dir():
            obs.hand_masks = np.stack([read_mask(hm / f"{k:06d}.png") for k in range(sd.n_frames)])
        source = "groundTruth"
    else:
        contacts = stage_contacts(sd)
        if not contacts:
            from .extract import extract as run_extract

            log("no contact sets on the stage: running extraction first")
            run_extract(stage_path, log=log, device=device)
            sd = read_stage(stage_path)
            contacts = stage_contacts(sd)
        obs.hand_masks = _hand_masks(sd, sd.n_frames)
    effects = {name: {k: v for k, v in params.items() if k != "fit"} for name, params in sd.effects.items()}
    settings = FitSettings(iterations=iterations, joint=joint, seed=seed)
    if settings_overrides:
        settings = dataclasses.replace(settings, **settings_overrides)
    start = None
    if resume:
        if not sd.reports:
            raise InputError(stage_path, "nothing to resume: the stage has no fit yet")
        start = {"youngs": sd.youngs_modulus, "poisson": sd.poisson_ratio,
                 "trajectories": {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}}
    def make_problem(cs):
        try:
            return FitProblem(sd, obs, cs, effects=effects, device=device)
        except ValueError as exc:
            raise InputError(stage_path, str(exc)) from None

    uniform_e = None
    if (settings.select_supports and contact_from is None and start is None and not sd.reports
            and any(c.sized_by_fit for c in contacts)):
        # the first fit of a guessed support (no still region was in view) sizes it by what it
        # renders (a refit keeps the size the fit layer recorded)
        contacts, prob, uniform_e, tried = select_supports(make_problem, contacts, sd.particles_positions,
                                                           sd.settings.particle_spacing, settings, log=log)
        chosen = sum(len(c.indices) for c in contacts if c.type == "fixed")
        if chosen != tried[0][1]:
            log(f"supports: {chosen} particles held ({tried[0][1]} as extracted): the lowest loss of "
                f"{len(tried)} sizes")
    else:
        prob = make_problem(contacts)
    result = run_fit(prob, settings, progress=progress, log=log, start=start, uniform_e=uniform_e)
    info = write_fit_layer(stage_path, sd, result, contacts, source=source)
    return result, info


# ------------------------------------------------------------------------------------- evaluate
def evaluate(stage_path, gt_dir, device="cpu") -> dict:
    """Score a fitted stage against a synthetic capture's ground truth: MA (and the best uniform
    E's MA), PSNR (full and masked), SSIM, IoU from re-rendering the stage's animation, and the
    3D position error of the Gaussians."""
    import torch

    from . import metrics as M
    from .gaussians import Gaussians
    from .render import covariance_from_scales_quats, estimate_background, render
    from .usd.stage import read_splat_animation

    gt_dir = Path(gt_dir)
    for f in ("youngs_modulus.npy", "gaussian_positions.npy"):
        if not (gt_dir / f).exists():
            raise InputError(gt_dir / f, "file not found (is this a synth capture's gt/ folder?)")
    sd = read_stage(stage_path)
    anim = read_splat_animation(stage_path)
    if anim["youngsModulus"] is None or not anim["times"]:
        raise InputError(stage_path, "has no fitted material or animation: run `physinteract-usd fit` first")
    e_gt = np.load(gt_dir / "youngs_modulus.npy").astype(np.float64)
    if len(e_gt) != len(anim["youngsModulus"]):
        raise InputError(gt_dir / "youngs_modulus.npy", f"{len(e_gt)} Gaussians, the stage has {len(anim['youngsModulus'])}")
    obs = load_observations(sd)
    T = min(len(anim["times"]), sd.n_frames)
    hands = None
    if (gt_dir / "hand_masks").is_dir():
        from .frames import read_mask

        hands = [read_mask(gt_dir / "hand_masks" / f"{k:06d}.png") for k in range(T)]
    elif sd.hand_mask_assets:
        hands = list(_hand_masks(sd, T))
    pos_gt = np.load(gt_dir / "gaussian_positions.npy").astype(np.float64)[:T]
    pos = np.stack(anim["positions"][:T])
    cover = obs.masks
    dev = torch.device("cpu" if device == "cpu" else device)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)  # noqa: E731
    bg = t(estimate_background(obs.frames, cover, dilate=2) if cover is not None else np.median(obs.frames, axis=0))
    g0 = sd.gaussians
    col = t(g0.colors)
    op = t(g0.opacities)
    frames = []
    for k in range(T):
        cov = covariance_from_scales_quats(t(anim["scales"][k]), t(anim["quats"][k]))
        with torch.no_grad():
            out = render(t(pos[k]), cov, col, op, sd.camera.at(k), background=bg)
        out = {n: v.cpu() for n, v in out.items()}
        pred = out["rgb"].numpy()
        sil = out["alpha"].numpy() > 0.5
        true_sil = obs.masks[k] if obs.masks is not None else sil
        d = M.frame_metrics(pred, obs.frames[k], sil, true_sil, None if hands is None else hands[k])
        d["frame"] = k
        frames.append(d)
    summary = M.summarize(frames)
    ma_uniform, e_uniform = M.best_uniform_ma(e_gt)
    del Gaussians
    return {"ma": M.material_accuracy(anim["youngsModulus"], e_gt), "ma_best_uniform": ma_uniform,
            "best_uniform_e": e_uniform, "psnr": summary["psnr"], "psnr_masked": summary["psnr_masked"],
            "ssim": summary["ssim"], "iou": summary["iou"], "position_error_m": M.position_error_m(pos, pos_gt),
            "frames": frames}


# ------------------------------------------------------------------------------------- simulate
INTERACTION_DOC = """Interaction spec (JSON) for `simulate`:
{
  "name": "pull_petal",            optional; default: the file's stem
  "frames": 40,                    optional; default: the stage's frame count
  "keep_supports": true,           keep the fitted stage's fixed contact sets (default true)
  "contacts": [
    {"type": "pointAdherent",      pointAdherent | pointNonAdherent | surfaceNonAdherent | fixed
     "select": {"centre": [x, y, z], "radius": 0.03},   which particles (rest positions, metres);
                                   or {"indices": [...]} or {"contact": "hand"} (a stage contact set)
     "grasp_frame": 2, "release_frame": 30,
     "displacement": [0.05, 0.1, 0.0]   moved smoothly over the grasp window; or
     "trajectory": [[x, y, z], ...]     positions per frame (frames entries); or
     "velocity": [vx, vy, vz]           constant while grasped
    },
    {"type": "pointNonAdherent", "radius": 0.02, "trajectory": [[x, y, z], ...]},
    {"type": "surfaceNonAdherent", "normal": [0, -1, 0], "trajectory": [[x, y, z], ...], "friction": 0.5}
  ]
}"""


def _parse_interaction(path, sd):
    import json

    from .fit.problem import ContactSpec

    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        spec = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("contacts"), list) or not spec["contacts"]:
        raise InputError(path, "expected an object with a non-empty 'contacts' list (see `simulate --help`)")
    n = _spec_int(path, "'frames'", spec.get("frames", sd.n_frames))
    if n < 2:
        raise InputError(path, "'frames' must be at least 2")
    x0 = sd.particles_positions
    by_name = {c.name: c for c in sd.contacts}
    out = []
    for i, c in enumerate(spec["contacts"]):
        where = f"contacts[{i}]"
        if not isinstance(c, dict):
            raise InputError(path, f"{where}: expected an object with a 'type'")
        t = c.get("type")
        if t not in ("pointAdherent", "pointNonAdherent", "surfaceNonAdherent", "fixed"):
            raise InputError(path, f"{where}: type must be pointAdherent, pointNonAdherent, surfaceNonAdherent or fixed")
        idx = np.zeros(0, np.int64)
        if t in ("pointAdherent", "fixed"):
            sel = c.get("select")
            if not isinstance(sel, dict):
                raise InputError(path, f"{where}: needs 'select' (centre+radius, indices or contact)")
            if "indices" in sel:
                raw = sel["indices"]
                if not isinstance(raw, list) or not raw or not all(isinstance(v, int) and not isinstance(v, bool) for v in raw):
                    raise InputError(path, f"{where}: 'indices' must be a non-empty list of integers")
                idx = np.asarray(raw, np.int64)
                if idx.min() < 0 or idx.max() >= len(x0):
                    raise InputError(path, f"{where}: indices must lie in [0, {len(x0)})")
            elif "contact" in sel:
                if sel["contact"] not in by_name:
                    raise InputError(path, f"{where}: the stage has no contact set '{sel['contact']}' "
                                     f"(it has {', '.join(by_name) or 'none'})")
                idx = by_name[sel["contact"]].particle_indices
            elif "centre" in sel and "radius" in sel:
                centre = _spec_vec3(path, f"{where}: 'centre'", sel["centre"])
                radius = _spec_float(path, f"{where}: 'radius'", sel["radius"])
                idx = np.where(np.linalg.norm(x0 - centre, axis=1) <= radius)[0]
                if len(idx) == 0:
                    raise InputError(path, f"{where}: no particle within {sel['radius']} m of {sel['centre']}")
            else:
                raise InputError(path, f"{where}: 'select' needs centre+radius, indices or contact")
        g = _spec_int(path, f"{where}: 'grasp_frame'", c.get("grasp_frame", 0))
        r = c.get("release_frame")
        r = None if r is None else _spec_int(path, f"{where}: 'release_frame'", r)
        if not 0 <= g < n - 1:
            raise InputError(path, f"{where}: grasp_frame must lie in [0, {n - 1}) for {n} frames")
        if r is not None and not g < r <= n:
            raise InputError(path, f"{where}: release_frame must lie in ({g}, {n}] (after grasp_frame)")
        traj = None
        if t != "fixed":
            if "trajectory" in c:
                try:
                    traj = np.asarray(c["trajectory"], float)
                except (TypeError, ValueError):
                    traj = None
                if traj is None or traj.shape != (n, 3) or not np.isfinite(traj).all():
                    raise InputError(path, f"{where}: trajectory must be {n} positions [x, y, z]")
            elif "displacement" in c:
                start = x0[idx].mean(0) if len(idx) else np.zeros(3)
                d = _spec_vec3(path, f"{where}: 'displacement'", c["displacement"])
                s = np.clip((np.arange(n) - g) / max((r if r is not None else n - 1) - g, 1), 0, 1)
                s = s * s * (3 - 2 * s)
                traj = start + s[:, None] * d
            elif "velocity" in c:
                start = x0[idx].mean(0) if len(idx) else np.zeros(3)
                v = _spec_vec3(path, f"{where}: 'velocity'", c["velocity"])
                steps = np.clip(np.arange(n) - g, 0, (r if r is not None else n) - g)
                traj = start + steps[:, None] / sd.fps * v
            else:
                raise InputError(path, f"{where}: give a trajectory, a displacement or a velocity")
            if t in ("pointNonAdherent", "surfaceNonAdherent") and "trajectory" not in c:
                raise InputError(path, f"{where}: a {t} collider needs a 'trajectory' (positions per frame)")
        normal = _spec_vec3(path, f"{where}: 'normal'", c.get("normal", (0.0, 1.0, 0.0)))
        if t == "surfaceNonAdherent" and not np.linalg.norm(normal) > 0:
            raise InputError(path, f"{where}: 'normal' must be a non-zero vector")
        out.append(ContactSpec(str(c.get("name", f"{t}{i}")), t, idx, g, r, traj,
                               radius=_spec_float(path, f"{where}: 'radius'", c.get("radius", 0.0)),
                               normal=tuple(normal), friction=_spec_float(path, f"{where}: 'friction'", c.get("friction", 0.5))))
        if t == "pointNonAdherent" and not out[-1].radius > 0:
            raise InputError(path, f"{where}: pointNonAdherent needs a radius > 0")
    pinned = [c for c in out if c.type in ("pointAdherent", "fixed")]
    for a in range(len(pinned)):
        for b in range(a):
            if np.intersect1d(pinned[a].indices, pinned[b].indices).size:
                raise InputError(path, f"contacts '{pinned[b].name}' and '{pinned[a].name}' hold the same "
                                 "particles (each particle follows one contact)")
    if spec.get("keep_supports", True):
        used = set(np.concatenate([c.indices for c in out])) if out else set()
        for c in sd.contacts:
            if c.contact_type == "fixed":
                keep = np.array([i for i in c.particle_indices if i not in used], np.int64)
                if len(keep):
                    out.append(ContactSpec(c.name, "fixed", keep))
    return spec, n, out


def _spec_int(path, what, v) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(path, f"{what} must be an integer, not {_json_repr(v)}")
    return int(v)


def _spec_float(path, what, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise InputError(path, f"{what} must be a number, not {_json_repr(v)}")
    return float(v)


def _spec_vec3(path, what, v) -> np.ndarray:
    if (not isinstance(v, (list, tuple)) or len(v) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in v)):
        raise InputError(path, f"{what} must be three numbers [x, y, z], not {_json_repr(v)}")
    return np.asarray(v, float)


def _json_repr(v) -> str:
    import json

    s = json.dumps(v)
    return s if len(s) <= 40 else s[:37] + "..."


def simulate(stage_path, interaction, *, name=None, device="cpu", log=print) -> dict:
    """Re-simulate the fitted object under a new interaction; writes a new time-sampled layer."""
    import re

    import torch

    from .fit.problem import FitProblem, Observations
    from .usd.stage import write_simulation_layer

    sd = read_stage(stage_path)
    if not sd.reports:
        log("note: the stage has no fit yet; simulating with its current (initial) material")
    spec, n, contacts = _parse_interaction(interaction, sd)
    name = name or spec.get("name") or Path(interaction).stem
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", name):
        raise InputError(name, "simulation name may hold letters, digits, '_' and '-' only")
    # reuse the fit problem's model building (no observations needed: blank frames)
    h, w = sd.image_size[1], sd.image_size[0]
    obs = Observations(frames=np.zeros((n, h, w, 3), np.float32))
    sd_n = _with_frames(sd, n)
    effects = {e: {k: v for k, v in p.items() if k != "fit"} for e, p in sd.effects.items()}
    if sd.reports:
        for e, p in sd.reports[-1].get("effect_parameters", {}).items():
            effects.setdefault(e, {}).update(p)
    try:
        prob = FitProblem(sd_n, obs, contacts, effects=effects, device=device)
    except ValueError as exc:  # what the spec's checks above did not catch (the simulator's own)
        raise InputError(interaction, str(exc)) from None
    E = torch.as_tensor(sd.youngs_modulus, dtype=prob.tdtype)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, sd.settings.poisson_max), dtype=prob.tdtype)
    with torch.no_grad():
        x, F = prob.simulate(E.clamp(sd.settings.youngs_min, sd.settings.youngs_max), nu)
        means, covs = zip(*[prob.gaussians_at(x[k], F[k]) for k in range(n)])
    out = write_simulation_layer(stage_path, sd, name, x.cpu().numpy(), np.stack([m.cpu().numpy() for m in means]),
                                 np.stack([c.cpu().numpy() for c in covs]), sd.fps, spec)
    out["frames"] = n
    return out


def _with_frames(sd, n):
    import dataclasses

    return dataclasses.replace(sd, end_frame=sd.start_frame + n - 1)


# --------------------------------------------------------------------------------------- export
def export(stage_path, out_path, *, ply_sequence=None) -> dict:
    """Flatten the stage into one self-contained USD file; optionally a 3DGS PLY per frame."""
    from .usd.stage import export_stage, read_splat_animation

    if ply_sequence:  # checked before anything is written
        out_dir = Path(ply_sequence)
        if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
            raise InputError(out_dir, "exists and is not empty")
    result = {"usd": export_stage(stage_path, out_path)}
    if ply_sequence:
        from .gaussians import Gaussians, write_ply

        out_dir.mkdir(parents=True, exist_ok=True)
        sd = read_stage(stage_path)
        anim = read_splat_animation(stage_path)
        g0 = sd.gaussians
        for k, t in enumerate(anim["times"]):
            g = Gaussians(anim["positions"][k], anim["scales"][k], anim["quats"][k], g0.opacities, g0.sh)
            write_ply(g, out_dir / f"{int(t):06d}.ply")
        result["ply_frames"] = len(anim["times"])
        result["ply_sequence"] = str(out_dir)
    return result
