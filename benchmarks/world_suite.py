"""Extraction measured on the world suite (randomised captures: `physinteract-usd synth --random
SEED` for the dev split, `--validation SEED` for the validation split), against the ground truth.

    python benchmarks/world_suite.py generate --split dev --seeds 0-23 --work data/world_dev
    python benchmarks/world_suite.py extract --split dev --work data/world_dev --json out/world_dev.json
    python benchmarks/world_suite.py generate --split validation --seeds 0-23 --work data/world_val
    python benchmarks/world_suite.py extract --split validation --final --work data/world_val ...

The dev split is for tuning. The validation split is never tuned on: `extract --split dev` refuses
every folder of it (`synth.splits.refuse_validation`), and reading it needs `--split validation
--final`, which logs the read in the folder's VALIDATION_SPLIT marker (so every look at it is on
record). Use it once, for the final table.

Per capture: gt/ moved out of the capture (DIR/<name>.gt), `init` with the capture's suggested
settings (its README: grid 24, padding 0.3, the E range, the density), `extract`, then compared
with the ground truth:

- type: right or not;
- grasp / release: frame errors against gt.json's grasp_frame and release_frame, defined as in
  the named scenes: the last frame before the toucher acts (a hand takes hold when it arrives and
  may rest there a few frames first; a fingertip or a palm may rest on the surface before it
  pushes) and the frame it lets go (a collider: the frame its motion ends and it leaves). A
  release that is never (held to the end) on one side and a frame on the other counts as wrong
  (shown "never/K"). (gt.json's touch_frames, a collider's first and last frames within 0.75
  ground-truth spacings of a particle, are not the truth: a floppy object sags away from a
  fingertip resting on it.) A collider's release counts as right anywhere from the frame after its
  last touch of the object (its surface within one truth grid cell of a particle, from the truth's
  particles) to the end of its motion: a collider that no longer touches acts on nothing (a ball
  that knocks a clamped block away, dev_0012, touches it until frame 5 of a motion that ends at 21);
- contact [cm]: pointAdherent: between the centroids of the extracted and the true held
  particles (the extracted contact point when the type is wrong); pointNonAdherent: between the
  contact points on the surface at rest; surfaceNonAdherent: the plane's offset along its normal;
- supports: recall and precision over the stage's particles (as eval_extract.py); for an object
  that nothing holds (resting on a floor), whether any support was invented, and whether the
  extraction reported the floor;
- hand IoU; and "ok": grasp and release within one frame, contact within 3 cm, no invented support
  (the issue's bar);
- moved before contact (a property of the capture, not of the extraction; from the truth's particles): the largest
  mean particle displacement from the scan's rest up to the toucher's arrival, in % of the object's size, and for a
  grasp the distance between the drawn hand's path and the held particles at its arrival (mm): the generator starts
  its objects unsettled (dev_0534's sheet sags 64 mm before the glove arrives, drawn where the sheet was; #23).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import traceback
from pathlib import Path

import numpy as np

import physinteract_usd  # noqa: F401
from physinteract_usd import api
from physinteract_usd.errors import InputError
from physinteract_usd.frames import read_mask
from physinteract_usd.synth.gt import read_ground_truth
from physinteract_usd.synth.splits import log_validation_read, mark_validation, refuse_validation
from physinteract_usd.cli.init import grid_arg  # N cells or "auto", as init takes it

sys.path.insert(0, str(Path(__file__).resolve().parent))


def parse_seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def name_of(split: str, seed: int) -> str:
    return f"{split}_{seed:04d}"


def captures(work: Path, split: str) -> list[str]:
    if not work.is_dir():
        raise InputError(work, "no such folder of captures (world_suite.py generate writes one)")
    return sorted(p.name for p in work.iterdir() if p.is_dir() and p.name.startswith(f"{split}_")
                  and "." not in p.name)


def guard(work: Path, split: str, final: bool, tool: str) -> None:
    """The dev split's tools refuse validation data; the validation split needs --final and is logged."""
    if split == "dev":
        refuse_validation(work, tool)
        for n in captures(work, "dev"):
            refuse_validation(work / n, tool)
            if (work / f"{n}.gt").exists():
                refuse_validation(work / f"{n}.gt", tool)
        if captures(work, "validation"):
            raise InputError(work, f"holds validation captures: {tool} is a tuning tool and never reads them")
    else:
        if not final:
            raise InputError("--split", "validation is read only for the final table: add --final (the read is "
                             "logged in the folder's VALIDATION_SPLIT marker); tune on the dev split")
        mark_validation(work)


def made_for(gt_json: Path):
    """The --truth-for-auto cap a generated capture's truth was made for (None: today's default truth)."""
    ft = (read_ground_truth(gt_json.parent).get("gt_sim") or {}).get("finer_than")
    return None if not ft else int(ft["max_particles"])


def generate(work: Path, split: str, seeds: list[int], device: str, log=print, truth_for_auto=None,
             settle: bool | None = None) -> None:
    """synth --random / --validation SEED for each seed into `work` (`settle` None: as each seed draws it)."""
    from physinteract_usd.synth.world import draw_world

    work.mkdir(parents=True, exist_ok=True)
    if split == "validation":
        mark_validation(work)
    else:
        refuse_validation(work, "world_suite.py generate --split dev")
    for s in seeds:
        n = name_of(split, s)
        made = next((p for p in (work / f"{n}.gt" / "gt.json", work / n / "gt" / "gt.json") if p.exists()), None)
        if made is not None:
            was = made_for(made)
            was_settled = bool((read_ground_truth(made.parent).get("world") or {}).get("settle"))
            want = draw_world(s, split)["settle"] if settle is None else bool(settle)
            if was == truth_for_auto and was_settled == want:
                continue
            # a capture this script made for another truth (--truth-for-auto or --settle changed): made again, the
            # stage too
            log(f"{n}: its truth was made for --truth-for-auto {was}{', settled' if was_settled else ''}, not "
                f"{truth_for_auto}{', settled' if want else ''}: made again", flush=True)
            for d in (work / n, work / f"{n}.gt", work / f"{n}.stage"):
                shutil.rmtree(d, ignore_errors=True)
        t0 = time.perf_counter()
        try:
            api.synth(None, work / n, random=s, split=split, device=device, force=True, log=lambda *a: None,
                      truth_for_auto=truth_for_auto, overrides=None if settle is None else {"settle": bool(settle)})
            log(f"{n}: {time.perf_counter() - t0:.0f} s", flush=True)
        except Exception as exc:
            log(f"{n}: FAILED {type(exc).__name__}: {exc}", flush=True)
            traceback.print_exc()


def prepare(work: Path, n: str, grid=None, max_particles=None, preload_hint: bool = False) -> tuple[Path, Path, Path]:
    """gt/ moved out to <n>.gt; the stage initialised with the capture's suggested settings (`grid`:
    init's --grid instead of the suggested one, e.g. "auto"), but for the scan's preload: left to the fit, as a user
    who does not know how the object was scanned leaves it (`preload_hint`: the capture's --preload taken too)."""
    cap, gt, stage = work / n, work / f"{n}.gt", work / f"{n}.stage" / "scene.usda"
    if (cap / "gt").exists():
        shutil.rmtree(gt, ignore_errors=True)
        shutil.move(str(cap / "gt"), str(gt))
    g = json.loads((gt / "gt.json").read_text())["suggested_init"]
    shutil.rmtree(stage.parent, ignore_errors=True)
    stage.parent.mkdir(parents=True)
    caps = {"max_particles": int(max_particles)} if max_particles else {}
    api.init(stage, cap, grid=grid or g["grid"], padding=g["padding"], youngs_range=tuple(g["youngs_range"]),
             max_poisson=g["max_poisson"], density=g["density"],
             preload=bool(g.get("preload", False)) if preload_hint else None, **caps)
    return cap, gt, stage


def compare(stage: Path, gt_dir: Path, result) -> dict:
    sd = api.read_scene(stage)
    g = json.loads((gt_dir / "gt.json").read_text())
    it = g["interaction"]
    w = g.get("world", {})
    gtc = api.true_contacts(sd, gt_dir)
    x0 = sd.particles_positions
    true, mine = gtc[0], result.interaction[0]
    row = {"type_true": it["type"], "type": result.interaction_type, "type_ok": result.interaction_type == it["type"],
           "scenario": w.get("scenario"), "shape": w.get("shape"), "look": w.get("look"),
           "width": sd.camera.width, "fps": sd.fps, "frames": sd.n_frames, "masks": g.get("masks"),
           "encoding": g.get("noise", {}).get("encoding"), "e_max": g["youngs_modulus"]["max"]}
    row["grasp_true"], row["grasp"] = int(it["grasp_frame"]), int(result.grasp_frame)
    row["release_true"] = it.get("release_frame")
    row["release"] = result.release_frame
    row["grasp_err"] = abs(row["grasp"] - row["grasp_true"])
    rt, rm = row["release_true"], row["release"]
    # a collider that no longer touches the object acts on nothing: any release from the frame
    # after its last touch (within one truth grid cell) to the end of its motion is the same
    row["release_true_first"] = collider_left(gt_dir, g) if (rt is not None and it["type"] != "pointAdherent") else rt
    lo = rt if row["release_true_first"] is None else min(rt, row["release_true_first"])
    row["release_err"] = 0 if (rt is None and rm is None) else (
        None if (rt is None) != (rm is None) else (0 if lo <= rm <= rt else min(abs(rm - rt), abs(rm - lo))))
    # contact
    if it["type"] == "pointAdherent":
        c_true = x0[true.indices].mean(0)
        c_mine = x0[mine.indices].mean(0) if (mine.type == "pointAdherent" and len(mine.indices)) else mine.point(x0)
        row["contact_cm"] = float(np.linalg.norm(c_true - c_mine) * 100)
    elif it["type"] == "pointNonAdherent":
        row["contact_cm"] = float(np.linalg.norm(np.asarray(it["contact_point"]) - mine.point(x0)) * 100)
    else:
        n = np.asarray(it["plane_normal"], float)
        gf = min(row["grasp_true"], sd.n_frames - 1)
        p = mine.trajectory[gf] if mine.trajectory is not None else mine.point(x0)
        row["contact_cm"] = float(abs(np.dot(true.trajectory[gf] - p, n)) * 100)
    row.update(path_error(true, mine, row["grasp_true"], rt, sd.n_frames))
    # supports
    fixed_true = set(gtc[-1].indices.tolist()) if gtc[-1].type == "fixed" else set()
    fixed_mine = set(np.concatenate([c.indices for c in result.supports]).tolist()) if result.supports else set()
    hit = len(fixed_true & fixed_mine)
    row["free"] = not fixed_true
    row["support_recall"] = hit / len(fixed_true) if fixed_true else None
    row["support_precision"] = hit / len(fixed_mine) if fixed_mine else (None if not fixed_true else 0.0)
    row["support_sets"] = len(result.supports)
    row["invented_support"] = bool(not fixed_true and fixed_mine)
    row["floor_true"] = g.get("floor") is not None
    row["floor_found"] = bool(result.evidence.get("floor"))
    # hand masks
    T = sd.n_frames
    hm = np.stack([read_mask(gt_dir / "hand_masks" / f"{k:06d}.png") for k in range(T)])
    union = (hm | result.hand_masks).sum()
    row["hand_iou"] = float((hm & result.hand_masks).sum() / union) if union else 1.0
    row["ok_timing"] = row["grasp_err"] <= 1 and row["release_err"] is not None and row["release_err"] <= 1
    row["ok_contact"] = row["contact_cm"] <= 3.0
    row["ok"] = bool(row["ok_timing"] and row["ok_contact"] and not row["invented_support"])
    row["notes"] = list(result.notes)
    row.update(moved_before_contact(gt_dir, g))
    return row


def moved_before_contact(gt_dir: Path, g: dict) -> dict:
    """What the truth's object does before the toucher arrives (`pre_contact_pct`: the largest mean particle
    displacement from rest up to the arrival, % of the object's size) and, for a grasp, how far the drawn hand's path
    is from the held particles (those within gt.json's contact radius of its contact point) at its arrival
    (`drawn_gap_mm`); {} without the truth's particle positions."""
    try:
        d = np.load(gt_dir / "particles.npz")
        X, rest = d["positions"], d["rest"]
    except (OSError, KeyError):
        return {}
    it = g["interaction"]
    a = it.get("arrive_frame")
    a = int(min(it["grasp_frame"] if a is None else a, len(X) - 1))
    size = float(np.ptp(rest, axis=0).max())
    pre = max(float(np.linalg.norm(X[k] - rest, axis=1).mean()) for k in range(a + 1))
    out = {"pre_contact_pct": 100.0 * pre / size if size > 0 else None, "drawn_gap_mm": None}
    if it["type"] == "pointAdherent" and it.get("trajectory") is not None:
        held = np.linalg.norm(rest - np.asarray(it["contact_point"]), axis=1) <= float(it["contact_radius"]) + 1e-9
        if held.any():
            out["drawn_gap_mm"] = 1e3 * float(np.linalg.norm(np.asarray(it["trajectory"])[a] - X[a][held].mean(0)))
    return out


def path_error(true, mine, grasp: int, release, T: int) -> dict:
    """How far the extracted toucher's path strays from the truth's while the truth's toucher acts
    (its grasp frame to its release, or the end): the largest distance between the two paths'
    displacements from that grasp frame (cm; where the contact is is `contact_cm`'s), that distance
    over the truth's largest displacement (`path_rel`), and the truth's and the extraction's height
    change (cm): a lift read as a move toward the camera shows here. Empty where either side has no
    trajectory (a fixed contact)."""
    if true.trajectory is None or mine.trajectory is None:
        return {}
    a = min(int(grasp), T - 1)
    b = T - 1 if release is None else min(int(release), T - 1)
    tt = np.asarray(true.trajectory, float)[a:b + 1]
    tm = np.asarray(mine.trajectory, float)[a:b + 1]
    dt, dm = tt - tt[0], tm - tm[0]
    err = float(np.linalg.norm(dt - dm, axis=1).max())
    span = float(np.linalg.norm(dt, axis=1).max())
    return {"path_cm": err * 100, "path_rel": err / span if span > 0 else None,
            "lift_true_cm": float(dt[:, 1].max() * 100), "lift_cm": float(dm[:, 1].max() * 100),
            "drop_cm": float(-dm[:, 1].min() * 100)}


def collider_left(gt_dir: Path, g: dict) -> int | None:
    """The frame after a collider's last touch of the object in the ground truth (its surface
    within one truth grid cell of a particle, the reach of a grid collider) from its arrival to
    the end of its motion, at least the grasp frame; None without the truth's particles (or, without them, the value kept in
    release_true_first.json). A sphere's distance from its centre
    (gt.json's trajectory; a finger's or a stick's capsule by its tip sphere), a plane's height."""
    it = g["interaction"]
    f = gt_dir / "particles.npz"
    if not f.exists():
        # captures kept without the truth's particles (to save space) carry this value, computed
        # where the particles were (data/world_dev7: on the GPU host); null where it failed there
        kept = gt_dir / "release_true_first.json"
        if kept.exists():
            v = json.loads(kept.read_text()).get("release_true_first")
            return None if v is None else int(v)
        return None
    x = np.load(f)["positions"]
    tr = np.asarray(it["trajectory"], float)
    cell = float(g["gt_sim"]["dx"])
    a, b = int(it["grasp_frame"]), min(int(it["release_frame"]), len(x) - 1)
    last = None
    for k in range(min(a, int(it.get("arrive_frame") or a)), b + 1):
        if it["type"] == "surfaceNonAdherent":
            gap = float(x[k][:, 1].max() - tr[k, 1]) * -1.0
        else:
            gap = float(np.linalg.norm(x[k] - tr[k], axis=1).min() - it["collider_radius"])
        if gap <= cell:
            last = k
    return a if last is None else max(a, last + 1)


def fmt(v, spec=".2f", none="-"):
    if v is None:
        return none
    if isinstance(v, bool):
        return "yes" if v else "no"
    return format(v, spec)


def _rel(r):
    if r.get("release_err") is None:
        return f"**{fmt(r['release'], 'd', 'never')}/{fmt(r['release_true'], 'd', 'never')}**"
    s = str(r["release_err"])
    return s if r["release_err"] <= 1 else f"**{s}**"


def table(rows: list[dict]) -> str:
    head = ("| capture | object | toucher | px, fps | type (true) | type | grasp err | release err | contact [cm] | "
            "path [cm] | "
            "support recall | support precision | free: invented / floor found | hand IoU | ok | MA | masked PSNR | "
            "moved before contact: % of size / drawn grasp gap [mm] |")
    lines = [head, "|" + "---|" * 18]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | failed: {r['error']} |" + " |" * 15
                         + f" {fmt(r.get('pre_contact_pct'), '.1f')} / {fmt(r.get('drawn_gap_mm'), '.0f')} |")
            continue
        typ = r["type"] if r["type_ok"] else f"**{r['type']}**"
        g = str(r["grasp_err"]) if r["grasp_err"] <= 1 else f"**{r['grasp_err']}**"
        c = f"{r['contact_cm']:.1f}" if r["contact_cm"] <= 3 else f"**{r['contact_cm']:.1f}**"
        free = "-" if not r["free"] else (f"{'**yes**' if r['invented_support'] else 'no'} / "
                                          f"{'yes' if r['floor_found'] else 'no'}")
        fit = r.get("fit") or {}
        lines.append(
            f"| {r['scene']} | {r['shape']} {r['scenario']} | {r['look']} | {r['width']}, {r['fps']:g} | "
            f"{r['type_true']} | {typ} | {g} | {_rel(r)} | {c} | {fmt(r.get('path_cm'), '.1f')} | "
            f"{fmt(r['support_recall'])} | "
            f"{fmt(r['support_precision'])} | {free} | {r['hand_iou']:.2f} | {'yes' if r['ok'] else '**no**'} | "
            f"{fmt(fit.get('ma'), '.3f')} | {fmt(fit.get('psnr_masked'), '.1f')} | "
            f"{fmt(r.get('pre_contact_pct'), '.1f')} / {fmt(r.get('drawn_gap_mm'), '.0f')} |")
    ok = [r for r in rows if "error" not in r]
    if ok:
        n = len(ok)
        t = sum(r["ok_timing"] for r in ok)
        c = sum(r["ok_contact"] for r in ok)
        free = [r for r in ok if r["free"]]
        inv = sum(r["invented_support"] for r in free)
        rec = [r["support_recall"] for r in ok if r["support_recall"] is not None]
        prec = [r["support_precision"] for r in ok if r["support_precision"] is not None and not r["free"]]
        fits = [r["fit"] for r in ok if r.get("fit") and r["fit"].get("ma") is not None]
        paths = [r["path_cm"] for r in ok if r.get("path_cm") is not None]
        lines.append(
            f"| **all ({n})** | | | | | type {np.mean([r['type_ok'] for r in ok]):.2f} | "
            f"grasp <= 1: {sum(r['grasp_err'] <= 1 for r in ok)}/{n} | "
            f"release <= 1: {sum(r['release_err'] is not None and r['release_err'] <= 1 for r in ok)}/{n} | "
            f"<= 3 cm: {c}/{n} (median {np.median([r['contact_cm'] for r in ok]):.1f}) | "
            f"median {fmt(float(np.median(paths)) if paths else None, '.1f')} | "
            f"{fmt(float(np.mean(rec)) if rec else None)} | {fmt(float(np.mean(prec)) if prec else None)} | "
            f"invented {inv}/{len(free)}, floor {sum(r['floor_found'] for r in free)}/{len(free)} | "
            f"{np.mean([r['hand_iou'] for r in ok]):.2f} | **{sum(r['ok'] for r in ok)}/{n}** "
            f"(timing {t}/{n}) | {fmt(float(np.mean([f['ma'] for f in fits])) if fits else None, '.3f')} | "
            f"{fmt(float(np.mean([f['psnr_masked'] for f in fits])) if fits else None, '.1f')} | "
            f"over 5%: {sum((r.get('pre_contact_pct') or 0) > 5 for r in ok)}/{n} |")
        by = ma_by_scenario(ok)
        if by:
            lines += ["", by]
    return "\n".join(lines)


def ma_by_scenario(rows: list[dict]) -> str:
    """One line: the fits' mean MA per scenario (floor objects apart: the grid nodes' ground brakes a roll, so their E
    is biased where they roll or tip; docs/sim.md, Limitations; the fits' rows say which ground they ran on); ""
    without fits."""
    groups: dict[str, list[float]] = {}
    for r in rows:
        f = r.get("fit") or {}
        if "error" not in r and f.get("ma") is not None:
            groups.setdefault(r["scenario"], []).append(float(f["ma"]))
    if not groups:
        return ""
    order = [s for s in ("hanging", "clamped", "anchored", "floor") if s in groups] + sorted(
        set(groups) - {"hanging", "clamped", "anchored", "floor"})
    parts = [f"{s} {np.mean(groups[s]):.3f} ({len(groups[s])})" for s in order]
    held = [m for s in order if s != "floor" for m in groups[s]]
    tail = f"; all but floor {np.mean(held):.3f} ({len(held)})" if held and "floor" in groups else ""
    grounds = {(r.get("fit") or {}).get("ground_contact") or "nodes" for r in rows
               if r.get("scenario") == "floor" and "error" not in r and (r.get("fit") or {}).get("ma") is not None}
    note = ""
    if "nodes" in grounds:
        note = " (floor: our ground at the grid nodes brakes a roll, docs/sim.md Limitations)"
    elif grounds:
        note = " (floor: the ground at the particles, PHYSINTERACT_GROUND=penalty)"
    return "MA by scenario (fits): " + ", ".join(parts) + tail + note


def run_extract(work: Path, split: str, names: list[str], json_path: Path | None, redo: bool, device: str,
                log=print, grid=None, max_particles=None) -> list[dict]:
    rows = json.loads(json_path.read_text()) if (json_path and json_path.exists() and not redo) else []
    done = {r["scene"] for r in rows if "error" not in r}
    rows = [r for r in rows if r["scene"] in done]
    for n in names:
        if n in done:
            continue
        row = {"scene": n}
        if not ((work / f"{n}.gt" / "gt.json").exists() or (work / n / "gt" / "gt.json").exists()):
            # the generator's own simulation failed (generate logged it): no truth, not an extraction failure
            row["error"] = "generation failed: no ground truth (the generator's simulation failed; see its log)"
            log(f"{n}: FAILED {row['error']}", flush=True)
        else:
            try:
                cap, gt, stage = prepare(work, n, grid, max_particles)
                t0 = time.perf_counter()
                res = api.extract(stage, log=lambda *m: None, device=device)
                row["extract_s"] = time.perf_counter() - t0
                row.update(compare(stage, gt, res))
                log(f"{n}: {row['type']}{'' if row['type_ok'] else ' (WRONG, ' + row['type_true'] + ')'}, grasp "
                    f"{row['grasp']}/{row['grasp_true']}, release {row['release']}/{row['release_true']}"
                    f"{'' if row.get('release_true_first') in (None, row['release_true']) else ' (leaves at %d)' % row['release_true_first']}, contact "
                    f"{row['contact_cm']:.1f} cm, supports R {fmt(row['support_recall'])} P {fmt(row['support_precision'])}"
                    f"{' INVENTED' if row['invented_support'] else ''}, hand IoU {row['hand_iou']:.2f}"
                    f" -> {'ok' if row['ok'] else 'FAIL'} ({row['extract_s']:.1f} s)", flush=True)
            except Exception as exc:
                row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
                log(f"{n}: FAILED {row['error']}", flush=True)
                traceback.print_exc()
                gt_dir = work / f"{n}.gt"
                if (gt_dir / "gt.json").exists():      # the capture's own property, shown with its failure
                    row.update(moved_before_contact(gt_dir, json.loads((gt_dir / "gt.json").read_text())))
        rows.append(row)
        if json_path:
            json_path.parent.mkdir(parents=True, exist_ok=True)
            json_path.write_text(json.dumps(rows, indent=1, default=float))
    order = {n: i for i, n in enumerate(names)}
    rows.sort(key=lambda r: order.get(r["scene"], 1 << 30))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", choices=["generate", "extract", "table"])
    ap.add_argument("--split", choices=["dev", "validation"], default="dev")
    ap.add_argument("--final", action="store_true", help="read the validation split for the final table (logged)")
    ap.add_argument("--work", required=True, help="the folder of the split's captures")
    ap.add_argument("--seeds", default="", help="e.g. 0-23 (generate; extract: default every capture there)")
    ap.add_argument("--json", help="rows as JSON (resumable: captures already there are skipped)")
    ap.add_argument("--fits", help="world_fit.py's JSON rows: their MA and masked PSNR go into the table")
    ap.add_argument("--redo", action="store_true", help="measure again the captures the JSON already holds")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grid", default=None, type=grid_arg,
                    help="init's --grid for every capture (e.g. auto) instead of the capture's suggested grid")
    ap.add_argument("--max-particles", type=int, default=None, help="init's --max-particles (a cap on grid auto)")
    ap.add_argument("--truth-for-auto", type=int, default=None, metavar="N",
                    help="generate: synth --truth-for-auto N (the truth finer than init --grid auto --max-particles "
                         "N's fit too; a GPU's work on thin objects; docs/benchmarks/world_fits.md)")
    from physinteract_usd.cli.synth import add_settle_flags

    add_settle_flags(ap, "generate (synth for every seed; a capture made otherwise is made again)")
    ap.add_argument("--timing", choices=["rules", "model", "hybrid"], default=None,
                    help="extract's timing: the passes' rules, the ninth pass's model, or the model's grasp with "
                         "the rules' release (timing.METHOD; default: the code's)")
    a = ap.parse_args(argv)
    if a.timing:
        from physinteract_usd.extract import timing as _timing

        _timing.METHOD = a.timing
    work = Path(a.work)
    tool = f"world_suite.py {a.command} --split dev"
    try:
        if a.command == "generate":
            generate(work, a.split, parse_seeds(a.seeds), a.device, truth_for_auto=a.truth_for_auto, settle=a.settle)
            return 0
        guard(work, a.split, a.final, tool)
        names = [name_of(a.split, s) for s in parse_seeds(a.seeds)] if a.seeds else captures(work, a.split)
        if a.split == "validation":
            log_validation_read(work, f"world_suite.py {a.command}", f"{len(names)} captures")
        jp = Path(a.json) if a.json else None
        if a.command == "extract":
            rows = run_extract(work, a.split, names, jp, a.redo, a.device, grid=a.grid,
                               max_particles=a.max_particles)
        else:
            rows = json.loads(jp.read_text())
        if a.fits and Path(a.fits).exists():
            fits = {r["scene"]: r for r in json.loads(Path(a.fits).read_text()) if "ma" in r}
            for r in rows:
                if r["scene"] in fits:
                    r["fit"] = fits[r["scene"]]
        print()
        print(table(rows))
        return 0
    except InputError as exc:
        print(f"world_suite.py: error: {exc.oneline()}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
