"""The diagnosis on the synthetic suite's named scenes with a hidden effect (issue #22's suite table).

Per case (scene, hidden effect or `none`, strength): `synth NAME --hidden EFFECT --strength S
--noise 0.015` (the effect is calibrated by the generator to S x its noise level in pixels), `init`
with the capture's suggested settings (or `--grid`), a base `fit` from the TRUE interaction
(`--contact-from gt`: extraction is measured elsewhere) with the model the user starts with (no
effects), `evaluate`, then `diagnose` (all candidates, the top 3 refitted briefly), then the hidden
effect added (`effects add`, the truth's effect: the table's "after adding it") and a warm refit,
evaluated again. Controls (`none`) add nothing: a `missing_effect` verdict on them is a false alarm.

Row per case (JSON lines, resumable: done cases are skipped): the rank of the hidden effect among
the significant candidates, the verdict, predicted vs realised loss drop of the top candidate, the
masked PSNR before and after adding the hidden effect, the fitted parameter against the truth's.
Everything goes through the package's Python API in one process (one Warp start).

    python benchmarks/suite_diagnose.py --scenes foam_bar --device cuda --out /tmp/sd \
        [--effects damping,none] [--strengths 1] [--iterations 30] [--frames 14] [--grid auto] \
        [--deadline 540] [--write docs/benchmarks/diagnose_suite_named.md]

Development data only (the synthetic suite's scenes).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from physinteract_usd import api

TRUTH_PARAM = {"damping": "coefficient", "plasticity": "yieldStress", "ground": "height",
               "viscoelasticity": "modulus"}
NOISE = 0.015


def cases(scenes: list[str], effects: list[str] | None, strengths: list[float]) -> list[tuple[str, str, float]]:
    """Every (scene, effect, strength) to run: a scene's own hidden effects (the generator's list
    for it) unless `effects` names them, and a control (`none`) per scene."""
    from physinteract_usd.synth.scenes import get_scene

    out = []
    for sc in scenes:
        own = list(get_scene(sc).hidden_effects)
        for eff in (effects or [*own, "none"]):
            if eff == "none":
                out.append((sc, "none", 0.0))
                continue
            out += [(sc, eff, s) for s in strengths]
    return out


def key(sc: str, eff: str, s: float) -> str:
    return f"{sc}_{eff}" + ("" if eff == "none" else f"@{s:g}")


def scored(stage: Path, gt: Path, device: str) -> dict:
    ev = api.evaluate(stage, gt, device=device)
    return {k: ev.get(k) for k in ("ma", "ma_best_uniform", "psnr_masked", "psnr", "position_error_m")}


def one(sc: str, eff: str, s: float, a, work: Path, log) -> dict:
    k = key(sc, eff, s)
    cap, stage = work / k, work / f"{k}.usda"
    row = {"case": k, "scene": sc, "hidden": eff, "strength": s, "device": a.device, "iterations": a.iterations}
    quiet = lambda *_a, **_k: None  # noqa: E731
    t0 = time.perf_counter()
    if not (cap / "gt" / "gt.json").exists():
        api.synth(sc, cap, size=a.size, frames=a.frames, hidden=None if eff == "none" else eff, strength=s or 1.0,
                  noise=NOISE, device=a.device, force=True, log=quiet)
    row["synth_s"] = round(time.perf_counter() - t0, 1)
    gtj = json.loads((cap / "gt" / "gt.json").read_text())
    sug = gtj["suggested_init"]
    if eff != "none":
        row["truth"] = gtj["hidden_effect"]["parameters"].get(TRUTH_PARAM[eff])
    for suffix in (".usda", ".init.usdc", ".fit.usdc"):
        (work / f"{k}{suffix}").unlink(missing_ok=True)
    shutil.rmtree(work / f"{k}.versions", ignore_errors=True)
    grid = sug["grid"] if a.grid is None else a.grid
    api.init(stage, cap, grid=grid, padding=sug["padding"], youngs_range=tuple(sug["youngs_range"]),
             max_poisson=sug["max_poisson"], density=sug["density"], force=True, log=quiet)
    gt = cap / "gt"
    t1 = time.perf_counter()
    f1 = api.fit(stage, iterations=a.iterations, contact_from=gt, device=a.device, progress=False, log=quiet)
    row["fit_s"] = round(time.perf_counter() - t1, 1)
    row["loss_before"] = f1.summary().get("final_loss")
    row["before"] = scored(stage, gt, a.device)
    log(f"{k}: base fit MA {row['before']['ma']:.3f}, masked PSNR {row['before']['psnr_masked']:.2f} dB "
        f"({row['fit_s']:.0f} s)")
    t2 = time.perf_counter()
    d = api.diagnose(stage, device=a.device, refit=a.refit, progress=False, log=quiet)
    row["diagnose_s"] = round(time.perf_counter() - t2, 1)
    row["verdict"] = d.get("verdict")
    row["reason"] = d.get("reason")
    sig = [c["effect"] for c in d.get("candidates", [])]
    row["significant"] = sig
    row["rank"] = (sig.index(eff) + 1) if eff in sig else None
    top = (d.get("candidates") or [None])[0]
    if top:
        row["top"] = {kk: top.get(kk) for kk in ("effect", "predicted_loss_drop", "realized_loss_drop", "estimate")}
    row["tested"] = [{kk: c.get(kk) for kk in ("effect", "p_value", "predicted_loss_drop", "relative_drop")}
                     for c in d.get("tested", [])]
    row["false_alarm"] = bool(eff == "none" and row["verdict"] == "missing_effect")
    log(f"{k}: diagnose {row['verdict']} {sig} ({row['diagnose_s']:.0f} s)")
    if eff != "none":
        api.effects_add(stage, eff)
        t3 = time.perf_counter()
        f2 = api.fit(stage, iterations=a.refit_iterations, contact_from=gt, device=a.device, progress=False,
                     log=quiet, keep_best=False)
        row["refit_s"] = round(time.perf_counter() - t3, 1)
        row["loss_after"] = f2.summary().get("final_loss")
        row["after"] = scored(stage, gt, a.device)
        params = (getattr(getattr(f2, "result", None), "effect_parameters", None) or {}).get(eff) or {}
        est = params.get(TRUTH_PARAM[eff])
        row["estimate"] = None if est is None else float(est)
        if est is not None and row.get("truth"):
            row["estimate_ratio"] = float(est) / float(row["truth"])
        log(f"{k}: + {eff}: masked PSNR {row['after']['psnr_masked']:.2f} dB, estimate {row.get('estimate')} "
            f"(truth {row.get('truth')})")
    return row


def fmt(v, f="{:.3g}"):
    return "-" if v is None else f.format(v)


def table(rows: list[dict]) -> str:
    out = ["| case | base: MA, masked PSNR | verdict: significant (best first) | hidden effect's rank | "
           "top: predicted / realised drop | + hidden effect: masked PSNR gain, loss after / before | "
           "estimate / truth | s (fit, diagnose, refit) |", "|---" * 8 + "|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['case']} | {r['error']} | | | | | | |")
            continue
        b, af, t = r.get("before") or {}, r.get("after") or {}, r.get("top") or {}
        gain = (f"{af['psnr_masked'] - b['psnr_masked']:+.2f} dB, "
                f"{fmt((r.get('loss_after') or 0) / r['loss_before'], '{:.2f}')}" if af and r.get("loss_before") else "-")
        out.append(f"| {r['case']} | {fmt(b.get('ma'), '{:.3f}')}, {fmt(b.get('psnr_masked'), '{:.2f}')} dB | "
                   f"{r.get('verdict')}: {', '.join(r.get('significant') or []) or '-'} | "
                   f"{r.get('rank') or ('-' if r['hidden'] == 'none' else 'not named')} | "
                   f"{fmt(t.get('predicted_loss_drop'))} / {fmt(t.get('realized_loss_drop'))} | {gain} | "
                   f"{fmt(r.get('estimate_ratio'), '{:.2f}x')} | {r.get('fit_s', '-')}, {r.get('diagnose_s', '-')}, "
                   f"{r.get('refit_s', '-')} |")
    named = [r for r in rows if r.get("hidden") not in (None, "none") and "error" not in r]
    ctrl = [r for r in rows if r.get("hidden") == "none" and "error" not in r]
    if named:
        first = sum(1 for r in named if r.get("rank") == 1)
        out.append(f"\nHidden effect ranked first: {first}/{len(named)}; false alarms on controls: "
                   f"{sum(r['false_alarm'] for r in ctrl)}/{len(ctrl)}.")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="foam_bar")
    ap.add_argument("--effects", default=None, help="comma-separated (default: each scene's own, and none)")
    ap.add_argument("--strengths", default="1")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--grid", default=None, help="init grid (default: the capture's suggestion), a number or auto")
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--refit-iterations", type=int, default=20)
    ap.add_argument("--refit", type=int, default=3, help="diagnose --refit")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="/tmp/suite_diagnose")
    ap.add_argument("--deadline", type=float, default=0, help="stop starting cases after this many seconds")
    ap.add_argument("--write", default=None)
    a = ap.parse_args(argv)
    if a.grid not in (None, "auto"):
        a.grid = int(a.grid)
    from physinteract_usd.synth.scenes import SCENES

    unknown = [sc for sc in a.scenes.split(",") if sc not in SCENES]
    bad_eff = [e for e in (a.effects.split(",") if a.effects else []) if e != "none" and e not in TRUTH_PARAM]
    if unknown or bad_eff:
        what = (f"unknown scene(s) {', '.join(unknown)} (`physinteract-usd synth --list`)" if unknown
                else f"unknown effect(s) {', '.join(bad_eff)} (one of {', '.join(TRUTH_PARAM)}, none)")
        print(f"suite_diagnose.py: error: {what}", file=sys.stderr)
        return 2
    work = Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    jl = work / "results.jsonl"
    done = {json.loads(l)["case"] for l in jl.read_text().splitlines() if l.strip()} if jl.exists() else set()
    t0 = time.perf_counter()
    todo = cases(a.scenes.split(","), a.effects.split(",") if a.effects else None,
                 [float(v) for v in a.strengths.split(",")])
    log = lambda m: print(m, flush=True)  # noqa: E731
    for sc, eff, s in todo:
        if key(sc, eff, s) in done:
            continue
        if a.deadline and time.perf_counter() - t0 > a.deadline:
            log("deadline: stopping")
            break
        try:
            row = one(sc, eff, s, a, work, log)
        except Exception as exc:  # noqa: BLE001 - one case's failure is a row
            row = {"case": key(sc, eff, s), "scene": sc, "hidden": eff, "strength": s,
                   "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"}
            log(f"{row['case']}: {row['error']}")
        with open(jl, "a") as f:
            f.write(json.dumps(row, default=float) + "\n")
    rows = [json.loads(l) for l in jl.read_text().splitlines() if l.strip()] if jl.exists() else []
    text = table(rows)
    print(text)
    if a.write:
        Path(a.write).write_text("# diagnose on the suite's named scenes\n\n" + __doc__.split("\n\n")[1] + "\n\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
