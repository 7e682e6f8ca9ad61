"""Interaction extraction measured on the synthetic suite against its ground truth.

For every scene: `synth` (small) into a work folder, `init` with the capture's suggested settings,
copy gt/ elsewhere and delete it from the capture, `extract`, then compare with the ground truth:

- type: the interaction type (pointAdherent, pointNonAdherent, surfaceNonAdherent) right or not;
- grasp / release: frame errors (release only for pointAdherent: colliders have none);
- contact: pointAdherent: distance between the centroids of the extracted and the true contact
  particles (true: the stage particles within the true contact radius), in particle spacings;
  pointNonAdherent: distance between the collider centres at the true grasp frame; surface: the
  plane's offset error along the true normal at frame 0 (and the normal's angle error);
- supports: recall = share of the true support particles on the stage (within a support's
  radius) that are in an extracted fixed set; precision = share of the extracted fixed particles
  that are true support particles;
- T0: the trajectory's error after aligning it with the truth at the true grasp frame (only
  differences matter for pointAdherent), max over the true grasp window (all frames for
  colliders), in metres (3D, and "lateral": across the camera's rays only, the part a single
  camera sees) and in pixels (both trajectories projected);
- hand IoU: the extracted hand masks against the true ones, over all frames.

Optionally (`--fit a,b`) fits scenes twice, from the extracted contacts and from the ground-truth
contacts (`fit --contact-from gt`), and reports MA for both (`evaluate`).

    python benchmarks/eval_extract.py                       # all scenes, table to stdout
    python benchmarks/eval_extract.py --write docs/benchmarks/extract.md --fit hemp_rope,bow_tie
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

import physinteract_usd  # noqa: F401  (schemas)
from physinteract_usd import api
from physinteract_usd.frames import read_mask

EXTRA = ("balloon_poke",)


def register_variants():
    """Scenes beyond the suite: `balloon_poke`, a pointNonAdherent poke on the hanging balloon (a
    second pointNonAdherent case beside telephone_cable, whose thin coil and fingertip make the
    hand hard to find)."""
    from physinteract_usd.synth import scenes as S

    if "balloon_poke" not in S.SCENES:
        base = S.SCENES["balloon"]
        S.SCENES["balloon_poke"] = dataclasses.replace(
            base, name="balloon_poke", interaction="pointNonAdherent",
            description="a fingertip pokes the hanging balloon's side and withdraws", contact_radius=0.015,
            path=S._press((-0.05, 0.0, -0.02)), hand_dir=(1.0, 0.1, 0.5), phases=(0.1, 0.7))


def machine() -> str:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import os

    return f"{cpu} ({os.cpu_count()} cores), Python {platform.python_version()}"


def prepare(name: str, work: Path, frames: int | None, log, device: str = "cpu",
            size: str = "small") -> tuple[Path, Path, Path, float]:
    """synth + init; gt/ copied to <work>/<name>.gt and removed from the capture."""
    cap, gt, stage = work / name, work / f"{name}.gt", work / f"{name}.stage" / "scene.usda"
    t0 = time.perf_counter()
    if not (gt / "gt.json").exists():
        shutil.rmtree(cap, ignore_errors=True)
        api.synth(name, cap, size=size, frames=frames, device=device, log=lambda *a: None)
        shutil.rmtree(gt, ignore_errors=True)
        shutil.copytree(cap / "gt", gt)
        shutil.rmtree(cap / "gt")
    t_synth = time.perf_counter() - t0
    init_stage(cap, gt, stage)
    return cap, gt, stage, t_synth


def init_stage(cap: Path, gt: Path, stage: Path):
    g = json.loads((gt / "gt.json").read_text())["suggested_init"]
    shutil.rmtree(stage.parent, ignore_errors=True)
    stage.parent.mkdir(parents=True)
    api.init(stage, cap, grid=g["grid"], padding=g["padding"], youngs_range=tuple(g["youngs_range"]),
             max_poisson=g["max_poisson"], density=g["density"])


def compare(stage: Path, gt_dir: Path, result) -> dict:
    sd = api.read_scene(stage)
    gtc = api.true_contacts(sd, gt_dir)
    g = json.loads((gt_dir / "gt.json").read_text())
    it = g["interaction"]
    x0, h = sd.particles_positions, sd.settings.particle_spacing
    cam = sd.camera.at(0)
    true = gtc[0]
    mine = result.interaction[0]
    row = {"type_true": it["type"], "type": result.interaction_type, "type_ok": result.interaction_type == it["type"]}
    gf = int(it["grasp_frame"])
    row["grasp_true"], row["grasp"] = gf, int(result.grasp_frame)
    row["release_true"] = it.get("release_frame")
    row["release"] = result.release_frame if result.interaction_type == "pointAdherent" else None
    row["grasp_err"] = abs(row["grasp"] - gf)
    row["release_err"] = (abs(row["release"] - row["release_true"])
                          if row["release"] is not None and row["release_true"] is not None else None)
    # contact distance
    if it["type"] == "pointAdherent":
        c_true = x0[true.indices].mean(0)
        c_mine = x0[mine.indices].mean(0) if len(mine.indices) else mine.contact_point
        row["contact_dist"] = float(np.linalg.norm(c_true - c_mine) / h)
    elif it["type"] == "pointNonAdherent":
        row["contact_dist"] = float(np.linalg.norm(true.trajectory[gf] - mine.trajectory[gf]) / h)
    else:
        n = np.asarray(it["plane_normal"], float)
        row["contact_dist"] = float(abs(np.dot(true.trajectory[0] - mine.trajectory[0], n)) / h)
        if mine.type == "surfaceNonAdherent":
            row["normal_err_deg"] = float(np.degrees(np.arccos(np.clip(np.dot(n, mine.normal), -1, 1))))
    # supports
    fixed_true = set(gtc[-1].indices.tolist()) if gtc[-1].type == "fixed" else set()
    fixed_mine = set(np.concatenate([c.indices for c in result.supports]).tolist()) if result.supports else set()
    hit = len(fixed_true & fixed_mine)
    row["support_recall"] = hit / len(fixed_true) if fixed_true else None
    row["support_precision"] = hit / len(fixed_mine) if fixed_mine else (None if not fixed_true else 0.0)
    row["support_sets"] = len(result.supports)
    # T0
    T = sd.n_frames
    if it["type"] == "pointAdherent":
        r_true = int(it["release_frame"])
        ks = np.arange(gf, min(r_true, T - 1) + 1)
    else:
        ks = np.arange(T)
    tt = np.asarray(true.trajectory, float)
    tm = np.asarray(mine.trajectory, float)
    aligned = tm - tm[gf] + tt[gf]
    err = np.linalg.norm(aligned[ks] - tt[ks], axis=1)
    row["t0_err_m"] = float(err.max())
    row["t0_err_mean_m"] = float(err.mean())
    # lateral: the error across the camera's rays
    pc_t = cam.world_to_camera(tt[ks])
    pc_m = cam.world_to_camera(aligned[ks])
    lat = []
    for a, b in zip(pc_t, pc_m):
        ray = a / np.linalg.norm(a)
        d = b - a
        lat.append(np.linalg.norm(d - np.dot(d, ray) * ray))
    row["t0_lateral_m"] = float(np.max(lat))
    ut, _ = cam.project(tt[ks])
    um, _ = cam.project(aligned[ks])
    row["t0_err_px"] = float(np.max(np.linalg.norm(ut - um, axis=1)))
    if it["type"] != "pointAdherent":
        row["t0_abs_err_m"] = float(np.max(np.linalg.norm(tm - tt, axis=1)))
    # hand masks
    hm = np.stack([read_mask(gt_dir / "hand_masks" / f"{k:06d}.png") for k in range(T)])
    inter = (hm & result.hand_masks).sum()
    union = (hm | result.hand_masks).sum()
    row["hand_iou"] = float(inter / union) if union else 1.0
    row["spacing_mm"] = h * 1000
    row["particles"] = int(len(x0))
    return row


def fit_pair(name: str, work: Path, cap: Path, gt_dir: Path, stage_ext: Path, iterations: int, log,
             device: str = "cpu", sources=("extracted", "gt"), seed: int = 0, overrides=None) -> dict:
    stage_gt = work / f"{name}.gtfit" / "scene.usda"
    if "gt" in sources:
        init_stage(cap, gt_dir, stage_gt)
    out, ev = {}, {}
    for label, stage, src in (("extracted", stage_ext, None), ("gt", stage_gt, gt_dir)):
        if label not in sources:
            continue
        t0 = time.perf_counter()
        try:
            api.fit(stage, iterations=iterations, contact_from=src, progress=False, log=lambda *a: None,
                    device=device, seed=seed, settings_overrides=overrides)
        except Exception as exc:
            raise RuntimeError(f"fit from {label} contacts: {type(exc).__name__}: {exc}") from exc
        ev = api.evaluate(stage, gt_dir, device=device)
        out[label] = {"ma": ev["ma"], "psnr": ev["psnr"], "psnr_masked": ev["psnr_masked"], "iou": ev["iou"],
                      "position_error_m": ev["position_error_m"], "seconds": time.perf_counter() - t0}
        log(f"  fit from {label} contacts: MA {ev['ma']:.3f}, masked PSNR {ev['psnr_masked']:.2f} "
            f"({out[label]['seconds']:.0f} s)", flush=True)
    out["ma_best_uniform"] = ev.get("ma_best_uniform")
    return out


MIX_PARTS = ("support", "hand", "timing", "trajectory", "masks")


def mixed_contacts(ex: list, gt: list, part: str, x0: np.ndarray) -> list:
    """The extracted contacts with one part taken from the ground truth: `support` (the fixed
    sets), `hand` (the grasped particles, or a collider's radius), `timing` (grasp and release
    frames), `trajectory` (T0 and its timing; a grasp's T0 moved onto the extracted particles).
    Parts joined by `+` are taken one after the other (`hand+trajectory+support`: the whole
    interaction from the truth)."""
    if "+" in part:
        for p in part.split("+"):
            ex = mixed_contacts(ex, gt, p, x0)
        return ex
    ei = [c for c in ex if c.type != "fixed"][0]
    gi = [c for c in gt if c.type != "fixed"][0]
    ef = [c for c in ex if c.type == "fixed"]
    gf = [c for c in gt if c.type == "fixed"]
    adherent = ei.type == "pointAdherent" and len(ei.indices) and len(gi.indices)
    if part == "support":
        taken = set(ei.indices.tolist()) if ei.type == "pointAdherent" else set()
        gf = [dataclasses.replace(c, indices=np.array([i for i in c.indices if int(i) not in taken], np.int64))
              for c in gf]
        return [ei] + [c for c in gf if len(c.indices)]
    if part == "hand":
        if adherent:
            shift = x0[gi.indices].mean(0) - x0[ei.indices].mean(0)
            traj = None if ei.trajectory is None else ei.trajectory + shift
            ei = dataclasses.replace(ei, indices=gi.indices, trajectory=traj)
            ef = [dataclasses.replace(c, indices=np.setdiff1d(c.indices, gi.indices)) for c in ef]
        else:
            ei = dataclasses.replace(ei, radius=gi.radius)
        return [ei] + [c for c in ef if len(c.indices)]
    if part == "timing":
        return [dataclasses.replace(ei, grasp_frame=gi.grasp_frame, release_frame=gi.release_frame)] + ef
    if part == "trajectory":
        traj = gi.trajectory
        if adherent:
            g = gi.grasp_frame
            traj = traj - traj[g] + x0[ei.indices].mean(0)
        return [dataclasses.replace(ei, trajectory=traj, grasp_frame=gi.grasp_frame,
                                    release_frame=gi.release_frame)] + ef
    if part == "masks":
        return list(ex)
    raise ValueError(part)


def fit_mixed(name: str, work: Path, gt_dir: Path, stage_ext: Path, part: str, iterations: int, log,
              device: str = "cpu", seed: int = 0, overrides=None) -> dict:
    """Fit from the extracted contacts with one part from the ground truth (`mixed_contacts`; `masks`:
    the true hand masks in the loss); the stage is a copy of the extracted one."""
    t0 = time.perf_counter()
    d = work / f"{name}.mix-{part}"
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(stage_ext.parent, d)
    stage = d / stage_ext.name
    sd = api.read_scene(stage)
    ex = api.stage_contacts(sd)
    gt = api.true_contacts(sd, gt_dir)
    masks = None
    if "masks" in part.split("+"):
        masks = np.stack([read_mask(gt_dir / "hand_masks" / f"{k:06d}.png") for k in range(sd.n_frames)])
    api.fit(stage, contacts=mixed_contacts(ex, gt, part, sd.particles_positions), hand_masks=masks,
            iterations=iterations, seed=seed, device=device, settings_overrides=overrides, progress=False,
            log=lambda *a: None)
    ev = api.evaluate(stage, gt_dir, device=device)
    out = {"ma": ev["ma"], "psnr": ev["psnr"], "psnr_masked": ev["psnr_masked"], "iou": ev["iou"],
           "position_error_m": ev["position_error_m"], "seconds": time.perf_counter() - t0}
    log(f"  fit from extracted contacts with the true {part}: MA {ev['ma']:.3f}, masked PSNR "
        f"{ev['psnr_masked']:.2f} ({out['seconds']:.0f} s)", flush=True)
    return out


def parse_overrides(text: str) -> dict:
    """`key=value,...` into FitSettings overrides, each value cast to the field's type."""
    from physinteract_usd.fit import FitSettings

    fields = {f.name: f for f in dataclasses.fields(FitSettings)}
    out = {}
    for item in [t for t in text.split(",") if t]:
        k, _, v = item.partition("=")
        if k not in fields:
            raise SystemExit(f"--fit-settings: {k!r} is not a FitSettings field ({', '.join(fields)})")
        d = getattr(FitSettings(), k)
        if d is None:        # a field whose default is resolved later (parts_start, trend_start): a number or a word
            try:
                out[k] = json.loads(v)
            except ValueError:
                out[k] = v
            continue
        out[k] = v if isinstance(d, str) else type(d)(float(v) if isinstance(d, float) else int(v))
    return out


def fmt(v, spec=".2f", none="-"):
    if v is None:
        return none
    if isinstance(v, bool):
        return "yes" if v else "**no**"
    return format(v, spec)


def table(rows: list[dict]) -> str:
    head = ("| scene | type (true) | type | grasp err | release err | contact dist [spacings] | "
            "support recall | support precision | T0 err [mm] | T0 lateral [mm] | T0 err [px] | hand IoU | extract [s] |")
    sep = "|" + "---|" * 13
    lines = [head, sep]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | - | failed: {r['error']} |" + " |" * 10)
            continue
        lines.append(
            f"| {r['scene']} | {r['type_true']} | {r['type'] if r['type_ok'] else '**' + r['type'] + '**'} | "
            f"{r['grasp_err']} | {fmt(r['release_err'], 'd')} | {r['contact_dist']:.1f} | "
            f"{fmt(r['support_recall'])} | {fmt(r['support_precision'])} | {r['t0_err_m'] * 1000:.1f} | "
            f"{r['t0_lateral_m'] * 1000:.1f} | {r['t0_err_px']:.1f} | {r['hand_iou']:.3f} | {r['extract_s']:.1f} |")
    ok = [r for r in rows if "error" not in r]
    if ok:
        acc = np.mean([r["type_ok"] for r in ok])
        rec = [r["support_recall"] for r in ok if r["support_recall"] is not None]
        lines.append(f"| **all ({len(ok)})** | | type accuracy {acc:.2f} | "
                     f"{np.mean([r['grasp_err'] for r in ok]):.2f} | "
                     f"{np.mean([r['release_err'] for r in ok if r['release_err'] is not None] or [np.nan]):.2f} | "
                     f"{np.median([r['contact_dist'] for r in ok]):.1f} (median) | {np.mean(rec):.2f} | "
                     f"{np.mean([r['support_precision'] for r in ok if r['support_precision'] is not None]):.2f} | "
                     f"{np.median([r['t0_err_m'] for r in ok]) * 1000:.1f} (median) | "
                     f"{np.median([r['t0_lateral_m'] for r in ok]) * 1000:.1f} (median) | "
                     f"{np.median([r['t0_err_px'] for r in ok]):.1f} (median) | "
                     f"{np.mean([r['hand_iou'] for r in ok]):.3f} | {np.mean([r['extract_s'] for r in ok]):.1f} |")
    return "\n".join(lines)


def fit_table(rows: list[dict]) -> str:
    lines = ["| scene | MA from extracted contacts | MA from ground-truth contacts | difference | "
             "masked PSNR extracted / gt | fit time extracted / gt [s] |", "|---|---|---|---|---|---|"]
    for r in rows:
        f = r.get("fit")
        if r.get("fit_error"):
            lines.append(f"| {r['scene']} | failed: {r['fit_error']} | | | | |")
            continue
        if not f or "extracted" not in f or "gt" not in f:
            continue
        e, g = f["extracted"], f["gt"]
        lines.append(f"| {r['scene']} | {e['ma']:.3f} | {g['ma']:.3f} | {e['ma'] - g['ma']:+.3f} | "
                     f"{e.get('psnr_masked', e['psnr']):.2f} / {g.get('psnr_masked', g['psnr']):.2f} | "
                     f"{e['seconds']:.0f} / {g['seconds']:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    from physinteract_usd.synth.scenes import SCENES

    register_variants()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", help="comma-separated (default: the suite + balloon_poke)")
    ap.add_argument("--work", help="work folder (default: a temp folder, removed unless --keep); "
                    "captures already there are reused")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--device", default="cpu", help="cpu or cuda: where the ground truth is generated, "
                    "the object's depth rendered for extraction, and the fits run")
    ap.add_argument("--size", default="small", choices=["small", "paper"], help="the synthetic captures' size "
                    "(paper: 448x336, 45 frames; generate it with --device cuda)")
    ap.add_argument("--frames", type=int, default=None, help="frames per scene (default: the small size's 20)")
    ap.add_argument("--fit", default="", help="comma-separated scenes (or 'all') to also fit from extracted and gt contacts")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--fit-sources", default="extracted,gt", help="which fits --fit runs: extracted, gt or both "
                    "(default both)")
    ap.add_argument("--seed", type=int, default=0, help="the fits' seed (their material basis): another seed "
                    "shows how much MA moves between equally good fits")
    ap.add_argument("--mix", default="", help="with --fit: also fit from the extracted contacts with one part "
                    f"from the truth, comma-separated parts of {','.join(MIX_PARTS)} (which part costs the MA)")
    ap.add_argument("--fit-settings", default="", help="FitSettings overrides for every fit, e.g. "
                    "lr_trajectory=1e-3,trajectory_levels=2 (an experiment; the reports name them)")
    ap.add_argument("--no-masks", action="store_true", help="extract from the frames alone (no silhouette "
                    "masks; nothing is written to the stages)")
    ap.add_argument("--write", help="write the markdown report here (e.g. docs/benchmarks/extract.md)")
    ap.add_argument("--append", action="store_true", help="with --write: add this table to the report as a "
                    "further section instead of replacing it")
    ap.add_argument("--json", help="write the rows as JSON here")
    a = ap.parse_args(argv)
    overrides = parse_overrides(a.fit_settings)
    names = a.scenes.split(",") if a.scenes else [*SCENES.keys()]
    for n in EXTRA:
        if not a.scenes and n not in names:
            names.append(n)
    fits = list(names) if a.fit == "all" else [s for s in a.fit.split(",") if s]
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="eval_extract_"))
    # a tuning tool: the world suite's validation split is never read here (synth/splits.py)
    from physinteract_usd.synth.splits import refuse_validation

    refuse_validation(work, "eval_extract.py")
    work.mkdir(parents=True, exist_ok=True)
    log = print
    rows = []
    extract = api.extract

    for name in names:
        row = {"scene": name}
        try:
            cap, gt_dir, stage, t_synth = prepare(name, work, a.frames, log, a.device, a.size)
            t0 = time.perf_counter()
            if a.no_masks:
                # the same capture without its silhouette masks (extraction on the frames alone)
                from physinteract_usd.extract import extract_interaction

                sd = api.read_scene(stage)
                obs = api.load_observations(sd, with_hand_masks=False)
                res = extract_interaction(sd, obs.frames, None, log=lambda *m: None, device=a.device)
            else:
                res = extract(stage, log=lambda *m: None, device=a.device)
            row["extract_s"] = time.perf_counter() - t0
            row.update(compare(stage, gt_dir, res))
            row["synth_s"] = t_synth
            log(f"{name}: {row['type']} ({'ok' if row['type_ok'] else 'WRONG'}), grasp {row['grasp']}/{row['grasp_true']}, "
                f"contact {row['contact_dist']:.1f} spacings, supports R {fmt(row['support_recall'])} "
                f"P {fmt(row['support_precision'])}, T0 {row['t0_err_m'] * 1000:.1f} mm / {row['t0_err_px']:.1f} px, "
                f"hand IoU {row['hand_iou']:.3f} ({row['extract_s']:.1f} s)")
            if name in fits:
                try:
                    row["fit"] = fit_pair(name, work, cap, gt_dir, stage, a.iterations, log, a.device,
                                          tuple(s for s in a.fit_sources.split(",") if s), a.seed, overrides)
                    for part in [p for p in a.mix.split(",") if p]:
                        row["fit"][f"mix_{part}"] = fit_mixed(name, work, gt_dir, stage, part, a.iterations, log,
                                                              a.device, a.seed, overrides)
                        if a.json:  # after every mixed fit too (they are the slow part)
                            Path(a.json).write_text(json.dumps(rows + [row], indent=1, default=float))
                except Exception as exc:  # a failed fit is reported in the fit table
                    row["fit_error"] = str(exc).splitlines()[0][:200]
                    log(f"  fit FAILED {row['fit_error']}")
        except Exception as exc:  # a scene that fails is a row that says so
            row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
            log(f"{name}: FAILED {row['error']}")
            traceback.print_exc(file=sys.stderr)
        rows.append(row)
        if a.json:  # after every scene: a run cut short keeps what it measured
            Path(a.json).write_text(json.dumps(rows, indent=1, default=float))
    md = table(rows)
    print()
    print(md)
    if any("fit" in r or "fit_error" in r for r in rows):
        print()
        print(fit_table(rows))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))
    if a.write:
        write_report(Path(a.write), rows, md, a)
    if not a.work and not a.keep:
        shutil.rmtree(work, ignore_errors=True)
    return rows


def write_report(path: Path, rows, md, a):
    fit_md = fit_table(rows) if any("fit" in r or "fit_error" in r for r in rows) else ""
    cmd = "python benchmarks/eval_extract.py " + " ".join(sys.argv[1:])
    if a.append and path.exists():
        title = "Without silhouette masks" if a.no_masks else "Further run"
        path.write_text(path.read_text().rstrip() + f"\n\n## {title}\n\nCommand: `{cmd}`.\n\n{md}\n"
                        + (f"\n{fit_md}\n" if fit_md else ""))
        print(f"appended to {path}")
        return
    text = f"""# Interaction extraction on the synthetic suite

Measured by `benchmarks/eval_extract.py` on {machine()}, {time.strftime('%Y-%m-%d')}.
Command: `{cmd}`.

Each scene is generated at the small size (128x96, 20 frames, 20 fps), initialised with the
capture's suggested settings (`--grid 18 --padding 0.3`), its `gt/` folder removed before
extraction, then compared with the ground truth (definitions in the script's docstring).
`balloon_poke` is not in the suite: a pointNonAdherent poke on the hanging balloon, a second
pointNonAdherent case beside `telephone_cable` (whose thin coil and small fingertip make the hand
hard to find).

{md}

Columns: grasp / release errors in frames; contact distance in particle spacings of the stage
(pointAdherent: contact-particle centroids; pointNonAdherent: collider centres at the true grasp;
surface: the plane's offset along the true normal); T0 errors are maxima over the true grasp window
(all frames for colliders) after aligning at the true grasp frame; "lateral" leaves out the
component along the camera's rays, which one camera does not see (T0 is lifted at the contact's
depth, so most of the 3D error of the pulls toward or away from the camera is depth).
"""
    if fit_md:
        text += f"""
## Fit from extracted vs ground-truth contacts

`physinteract-usd fit STAGE --iterations {a.iterations}` from the extracted contacts, and on a
second stage from the ground truth (`--contact-from gt`), both scored by `evaluate` (MA: share of
Gaussians with |E - E_gt| / E_gt <= 0.2). The fit is being tuned in parallel: the absolute MA is
provisional; the difference is what this table is for.

{fit_md}
"""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
