"""The fit columns of the world suite's tables: MA and masked PSNR from the extracted interactions.

For every capture that `world_suite.py extract` prepared (DIR/<name>, DIR/<name>.gt, DIR/<name>.stage
with its extraction), a fresh copy of the stage (DIR/<name>.fit-s<seed>/) is fitted with `api.fit`
and scored with `api.evaluate` against the ground truth. Where the extraction found that the
object rests on a floor (its notes suggest the `ground` effect), the copy gets the effect at the
floor's height, as a user following the note would (`effects add`). One JSON row per capture,
appended as soon as its fit ends; a run cut short resumes where it stopped (rows already in --json
are skipped unless --redo).

    python benchmarks/world_fit.py --work data/world_dev --json out/world_dev_fit.json --iterations 60 --device cuda
    python benchmarks/world_fit.py --work data/world_val --split validation --final --json out/world_val_fit.json

The validation split is read only with `--split validation --final` (logged in the folder's
VALIDATION_SPLIT marker): never tune on it. `world_suite.py extract ... --fits out.json` puts the
rows' MA and masked PSNR into its table.
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
from physinteract_usd.synth.splits import log_validation_read

sys.path.insert(0, str(Path(__file__).resolve().parent))

from world_suite import captures, guard, name_of, parse_seeds  # noqa: E402


def add_ground(stage: Path, height: float, friction: float = 0.5) -> None:
    """Switch the `ground` effect on in the stage's root layer (what `effects add ground` does)."""
    from pxr import Usd

    st = Usd.Stage.Open(str(stage))
    st.SetEditTarget(st.GetRootLayer())
    prim = st.GetPrimAtPath("/World/PhysInteract")
    prim.ApplyAPI("PhysInteractGroundAPI")
    prim.GetAttribute("physinteract:ground:height").Set(float(height))
    prim.GetAttribute("physinteract:ground:friction").Set(float(friction))
    st.GetRootLayer().Save()


def truth_sweep(stage: Path, gt: Path, device: str, e_true: float, nu: float | None = None) -> dict:
    """Does this capture determine E at all, for our model? The select schedule's uniform-E sweep
    (fit/select.uniform_stage, one minimum refined) with the TRUE contacts, supports and hand path,
    every frame but the first: its near-best hull (every uniform E within 1% of the best loss) and
    the level `identifiability` gives it. A capture whose hull is wide is one where no fit can be
    expected to find E within 20% from this video; MA there says nothing about the fit. The floor is
    the truth's too (on a copy of the stage: `<stage folder>.truth-sweep`). `nu`: the
    sweep's Poisson ratio (default: the stage's default, as the fit's uniform stage takes it)."""
    import dataclasses

    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit.select import identifiability, sweep_interval, uniform_stage

    g = json.loads((gt / "gt.json").read_text())
    if g.get("floor"):
        # the TRUE interaction includes the floor: a copy of the stage with the truth's (the
        # extraction's floor, or none where it missed it, made dev_0003 fall out of its grid)
        tmp = stage.parent.parent / f"{stage.parent.name}.truth-sweep"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(stage.parent, tmp)
        stage = tmp / stage.name
        add_ground(stage, g["floor"]["height"], g["floor"].get("friction", 0.5))
    job = prepare_fit(stage, iterations=1, contact_from=gt, device=device, log=lambda *a: None, warm=False)
    prob = make_problem(job)
    s = dataclasses.replace(job.settings, select_minima=1, search_evals=4)
    st = job.scene.settings
    nu = min(st.poisson_default, 0.98 * st.poisson_max) if nu is None else float(nu)
    uni = uniform_stage(prob, list(range(1, prob.T)), s, nu)
    iv = sweep_interval(uni["sweep"], uni.get("rise", 0.01))
    idf = identifiability({"uniform_sweep_interval": iv}, None, uni["e"])
    return {"truth_sweep_e": uni["e"], "truth_sweep_interval": iv, "truth_level": idf["level"],
            "truth_sweep_covers": bool(iv and iv[0] <= e_true <= iv[1]), "truth_sweep": uni["sweep"],
            "truth_sweep_nu": nu}


def fit_one(work: Path, n: str, iterations: int, seed: int, device: str, log=print, overrides=None,
            with_truth_sweep: bool = False, true_contacts: bool = False) -> dict:
    """One capture's fit and score. `true_contacts`: the fit from the TRUE interaction (the truth's contacts, hand
    path and supports, `fit --contact-from <gt>`, and the truth's floor as the `ground` effect) instead of the
    extraction's: the material's accuracy with extraction taken out (issue #24's targets are with true contacts)."""
    src = work / f"{n}.stage"
    gt = work / f"{n}.gt"
    if not (src / "scene.usda").exists() or not (gt / "gt.json").exists():
        raise InputError(src, "not prepared: run world_suite.py extract on this folder first")
    d = work / f"{n}.fit-s{seed}"
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(src, d)
    stage = d / "scene.usda"
    effects = {}
    if true_contacts:
        floor = json.loads((gt / "gt.json").read_text()).get("floor")
    else:
        # the extraction's word on a floor (re-extracted on the copy: the stage keeps contacts, not notes)
        res = api.extract(stage, log=lambda *a: None, device=device, preview=False)
        floor = res.evidence.get("floor")
    if floor:
        add_ground(stage, floor["height"], floor.get("friction", 0.5))
        effects["ground"] = {"height": floor["height"]}
    t0 = time.perf_counter()
    said = []
    out = api.fit(stage, iterations=iterations, device=device, seed=seed, progress=False,
            contact_from=gt if true_contacts else None,
            log=lambda *m: said.append(" ".join(map(str, m))), settings_overrides=overrides or None)
    fit_s = time.perf_counter() - t0
    ev = api.evaluate(stage, gt, device=device)
    row = {"scene": n, "ma": ev["ma"], "ma_best_uniform": ev.get("ma_best_uniform"), "psnr": ev["psnr"],
           "psnr_masked": ev["psnr_masked"], "ssim": ev.get("ssim"), "iou": ev.get("iou"),
           "position_error_m": ev.get("position_error_m"), "truth_resolution": ev.get("truth_resolution"), "fit_s": fit_s, "iterations": iterations, "seed": seed,
           "device": device, "true_contacts": bool(true_contacts), "effects": effects, "settings": dict(overrides or {}), "stopped_by": out.stopped_by,
           "interaction_check": [m for m in said if m.startswith(("interaction check", "the interaction may",
                                                                  "the contact may", "the fitted"))],
           # the fit's decision on the scan's preload where the stage left it open (fit/preload_choice.py)
           "preload": (out.result.settings or {}).get("preload"),
           "preload_stage": api.read_scene(stage).settings.preload}
    # the fitted E against the truth, the fit's own confidence and (schedule select) its uniform sweep's
    # minima and intervals: is a wrong E at least said to be uncertain?
    summ = out.summary()
    from physinteract_usd import simulation   # the pin rule this process fitted with (PHYSINTERACT_PIN_RULE; #24 A/B rows)

    row["pin_rule"] = list(simulation.PIN_RULE)
    row["support_rule"] = None if simulation.SUPPORT_RULE is None else list(simulation.SUPPORT_RULE)
    row["cfl"] = simulation.CFL
    row["ground_contact"] = simulation.GROUND_CONTACT
    e_true = float(np.median(np.load(gt / "youngs_modulus.npy")))
    row.update({"e_true": e_true, "e_fit": summ["youngs_modulus_pa"]["median"],
                "e_ratio": summ["youngs_modulus_pa"]["median"] / e_true, "best_uniform_e": ev.get("best_uniform_e"),
                "confidence_mean": summ["confidence_mean"] if summ["confidence_estimated"] else None,
                "model": summ.get("model")})
    idf = summ.get("identifiability") or {}
    row["identifiability"] = idf.get("level")
    if idf.get("interval"):
        row["sweep_interval"] = idf["interval"]
        row["sweep_covers_truth"] = bool(idf["interval"][0] <= e_true <= idf["interval"][1])
    if with_truth_sweep:
        t1 = time.perf_counter()
        try:
            row.update(truth_sweep(stage, gt, device, e_true))
        except Exception as exc:  # noqa: BLE001 - the sweep is a diagnostic beside the fit's row
            row["truth_sweep_error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
        row["truth_sweep_s"] = time.perf_counter() - t1
    mins = (summ.get("model") or {}).get("uniform_minima") or []
    if mins:
        best = min(mins, key=lambda m: m["loss"])
        row["uniform_interval"] = best["interval"]
        row["interval_covers_truth"] = bool(best["interval"][0] <= e_true <= best["interval"][1])
    log(f"{n}: MA {row['ma']:.3f}, masked PSNR {row['psnr_masked']:.2f} dB ({fit_s:.0f} s)", flush=True)
    return row


def e_table(rows: list[dict]) -> str:
    """Per fit: E fitted / true, the fit's mean confidence, the select schedule's uniform interval and
    whether it holds the truth, MA against the best single E."""
    def f(v, spec):
        return "-" if v is None else format(v, spec)
    out = ["| capture | E true [Pa] | E fit [Pa] | fit / true | confidence | E determined | near-best sweep [Pa] | "
           "holds truth | curvature interval [Pa] | holds truth | true interaction: E determined, sweep [Pa] | MA | "
           "best single E MA |", "|" + "---|" * 13]
    for r in rows:
        iv, sw, tw = r.get("uniform_interval"), r.get("sweep_interval"), r.get("truth_sweep_interval")
        truth = "-" if not tw else (f"{r.get('truth_level')}, {tw[0]:.3g} .. {tw[1]:.3g} "
                                    f"({'holds' if r.get('truth_sweep_covers') else 'misses'} the truth)")
        out.append(f"| {r['scene']} | {f(r.get('e_true'), '.3g')} | {f(r.get('e_fit'), '.3g')} | "
                   f"{f(r.get('e_ratio'), '.2f')} | {f(r.get('confidence_mean'), '.2f')} | "
                   f"{r.get('identifiability') or '-'} | {'-' if not sw else f'{sw[0]:.3g} .. {sw[1]:.3g}'} | "
                   f"{'-' if 'sweep_covers_truth' not in r else ('yes' if r['sweep_covers_truth'] else 'no')} | "
                   f"{'-' if not iv else f'{iv[0]:.3g} .. {iv[1]:.3g}'} | "
                   f"{'-' if 'interval_covers_truth' not in r else ('yes' if r['interval_covers_truth'] else 'no')} | "
                   f"{truth} | {f(r.get('ma'), '.3f')} | {f(r.get('ma_best_uniform'), '.3f')} |")
    swept = [r for r in rows if r.get("truth_level")]
    if swept:
        det = [r for r in swept if r["truth_level"] == "determined"]
        rough = [r for r in swept if r["truth_level"] == "rough"]
        mean = lambda rs: "-" if not rs else f"{np.mean([r['ma'] for r in rs]):.3f}"  # noqa: E731
        held = [r for r in rows if "sweep_covers_truth" in r]
        out.append("")
        out.append(f"With the true interaction, the video determines E (near-best sweep <= 1.5x wide) on {len(det)} of "
                   f"{len(swept)} captures (mean MA there {mean(det)}), roughly (<= 4x) on {len(rough)} (mean MA "
                   f"{mean(rough)}), not at all on {len(swept) - len(det) - len(rough)} (mean MA "
                   f"{mean([r for r in swept if r not in det and r not in rough])}).")
        if held:
            out.append(f"The fit's own near-best sweep holds the true E on {sum(r['sweep_covers_truth'] for r in held)} "
                       f"of {len(held)} captures.")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True)
    ap.add_argument("--split", choices=["dev", "validation"], default="dev")
    ap.add_argument("--final", action="store_true", help="read the validation split for the final table (logged)")
    ap.add_argument("--seeds", default="", help="capture seeds (default: every prepared capture of the split)")
    ap.add_argument("--json", required=True, help="rows (resumable)")
    ap.add_argument("--redo", action="store_true")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0, help="the fit's seed")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--truth-sweep", action="store_true",
                    help="also sweep a uniform E with the true interaction: does the capture determine E at all?")
    ap.add_argument("--true-contacts", action="store_true",
                    help="fit from the truth's interaction and floor (the material alone), not the extraction's")
    ap.add_argument("--min-e-true", type=float, default=0.0,
                    help="fit only captures whose true median E is at least this (Pa): e.g. 1e5, the stiff objects")
    ap.add_argument("--fit-settings", default="", help="FitSettings overrides key=value,... (e.g. a quick smoke "
                    "test: search_evals=2,confidence_probes=0)")
    a = ap.parse_args(argv)
    from eval_extract import parse_overrides

    overrides = parse_overrides(a.fit_settings)
    work = Path(a.work)
    try:
        guard(work, a.split, a.final, "world_fit.py --split dev")
        names = [name_of(a.split, s) for s in parse_seeds(a.seeds)] if a.seeds else captures(work, a.split)
        if a.split == "validation":
            log_validation_read(work, "world_fit.py", f"{len(names)} captures, {a.iterations} iterations")
    except InputError as exc:
        print(f"world_fit.py: error: {exc.oneline()}", file=sys.stderr)
        return 2
    jp = Path(a.json)
    rows = json.loads(jp.read_text()) if jp.exists() and not a.redo else []
    done = {r["scene"] for r in rows if "ma" in r}
    rows = [r for r in rows if r["scene"] in done]
    for n in names:
        if n in done:
            continue
        if a.min_e_true and (work / f"{n}.gt" / "youngs_modulus.npy").exists() and \
                float(np.median(np.load(work / f"{n}.gt" / "youngs_modulus.npy"))) < a.min_e_true:
            print(f"{n}: true median E below {a.min_e_true:g} Pa: not fitted (--min-e-true)", flush=True)
            continue
        try:
            row = fit_one(work, n, a.iterations, a.seed, a.device, overrides=overrides,
                          with_truth_sweep=a.truth_sweep, true_contacts=a.true_contacts)
        except Exception as exc:
            row = {"scene": n, "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"}
            print(f"{n}: FAILED {row['error']}", flush=True)
            traceback.print_exc()
        rows.append(row)
        jp.parent.mkdir(parents=True, exist_ok=True)
        jp.write_text(json.dumps(rows, indent=1, default=float))
    ok = [r for r in rows if "ma" in r]
    if ok:
        print(e_table(ok))
        print(f"{len(ok)} fits: mean MA {np.mean([r['ma'] for r in ok]):.3f}, mean masked PSNR "
              f"{np.mean([r['psnr_masked'] for r in ok]):.2f} dB; {len(rows) - len(ok)} failed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
