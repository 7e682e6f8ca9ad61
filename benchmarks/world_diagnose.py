"""Compare -> diagnose -> add the effect -> refit, on world captures with an effect nobody told us about.

The world generator's pins blend the grid per substep (`pin_gain` 1, no rate-consistent blend): with
hundreds of substeps a frame, the nodes a support or a grasp partly covers act as a strong damper,
and a hanging bar released by the hand creeps back overdamped where our model swings
(docs/benchmarks/world_fits.md). That is an effect the fit's model lacks. Per development capture:
a fit from the TRUE interaction (and the truth's floor), its evaluation, `diagnose`, then (when it
names an effect, or `--add` one) `effects add` and the warm refit, evaluated again.

    python benchmarks/world_diagnose.py --work data/world_dev --seeds 19 --device cuda --iterations 20 --json out/wd.json
    python benchmarks/world_diagnose.py --work data/world_dev --seeds 19 --cap 400 --iterations 4 --starts 1 --reuse-base

`--reuse-base` takes the base fit kept from an earlier run (<scratch>/<name>.base, written after
every base fit) instead of fitting again: diagnose and the refit on the same base, e.g. before
and after a change to diagnose.

A tuning tool: it refuses the validation split. Results in docs/benchmarks/world_fits.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

import physinteract_usd  # noqa: F401
from physinteract_usd import api
from physinteract_usd.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from world_bias import gt_dir, per_capture, prepare_stage  # noqa: E402
from world_fit import add_ground  # noqa: E402

EFFECTS = ("damping", "plasticity", "viscoelasticity", "ground")


def scored(stage: Path, gt: Path, device: str, e_true: float) -> dict:
    ev = api.evaluate(stage, gt, device=device)
    sd = api.read_scene(stage)
    e = float(np.median(sd.youngs_modulus))
    return {"ma": ev["ma"], "ma_best_uniform": ev.get("ma_best_uniform"), "psnr_masked": ev["psnr_masked"],
            "position_error_m": ev.get("position_error_m"), "e_fit": e, "e_ratio": e / e_true}


def one(work: Path, n: str, cap: int, iterations: int, refit_iterations: int, device: str, add: str | None,
        scratch: Path, log=print, starts: int = 3, reuse_base: bool = False, diagnose_refit: int = 3,
        skip_diagnose: bool = False) -> dict:
    gt = gt_dir(work, n)
    g = json.loads((gt / "gt.json").read_text())
    out, kept = scratch / n, scratch / f"{n}.base"
    stage = out / "scene.usda"
    e_true = float(np.median(np.load(gt / "youngs_modulus.npy")))
    row = {"scene": n, "e_true": e_true, "shape": g["world"].get("shape"), "scenario": g["world"].get("scenario"),
           "type": g["interaction"]["type"], "device": device, "iterations": iterations, "cap": cap,
           "starts": starts}
    quiet = lambda *a, **k: None  # noqa: E731
    t0, c0 = time.perf_counter(), time.process_time()
    if reuse_base and (kept / "base.json").exists():
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(kept, out)
        row.update(json.loads((kept / "base.json").read_text()), reused_base=True)
    else:
        prepare_stage(work / n, gt, out, cap)
        if g.get("floor"):
            add_ground(stage, g["floor"]["height"], g["floor"].get("friction", 0.5))
        f1 = api.fit(stage, iterations=iterations, contact_from=gt, device=device, progress=False, log=quiet)
        row["fit_s"], row["fit_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        row["loss_before"] = f1.summary().get("final_loss")
        row["before"] = scored(stage, gt, device, e_true)
        shutil.rmtree(kept, ignore_errors=True)
        shutil.copytree(out, kept)
        (kept / "base.json").write_text(json.dumps({k: row[k] for k in ("fit_s", "fit_cpu_s", "loss_before", "before")}))
    log(f"{n}: base fit E x{row['before']['e_ratio']:.2f}, MA {row['before']['ma']:.3f} ({row['fit_s']:.0f} s)", flush=True)
    t1, c1 = time.perf_counter(), time.process_time()
    try:
        if skip_diagnose and add:
            raise RuntimeError("skipped (--skip-diagnose)")
        d = api.diagnose(stage, device=device, progress=False, log=quiet, starts=starts, refit=diagnose_refit,
                         refit_iterations=refit_iterations)
    except Exception as exc:  # noqa: BLE001 - the base fit's row stands
        row["error"] = f"diagnose: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
        log(f"{n}: {row['error']}", flush=True)
        if not add:
            return row
        d = {}
    row["diagnose_s"], row["diagnose_cpu_s"] = time.perf_counter() - t1, time.process_time() - c1
    row["verdict"] = d.get("verdict")
    row["reason"] = d.get("reason")
    row["candidates"] = [{k: c.get(k) for k in ("effect", "score", "predicted_loss_drop", "realized_loss_drop",
                                                "estimate", "evidence")} for c in d.get("candidates", [])]
    # every candidate tested: why it was (not) significant
    row["tested"] = d.get("tested", [])
    row["loss"], row["noise_floor"] = d.get("loss"), d.get("noise_floor")
    row["noise"] = d.get("noise")
    top = [c["effect"] for c in row["candidates"]]
    log(f"{n}: diagnose {row['verdict']}: {top} ({row['diagnose_s']:.0f} s)", flush=True)
    name = add or next((e for e in top if e in EFFECTS), None)
    if name:
        api.effects_add(stage, name)
        t2, c2 = time.perf_counter(), time.process_time()
        # the refit becomes current whatever its loss (keep_best off) so that it is what is scored;
        # `kept` says whether `fit`'s default would have kept it
        f2 = api.fit(stage, iterations=refit_iterations, contact_from=gt, device=device, progress=False, log=quiet,
                     keep_best=False)
        row["refit_s"], row["refit_cpu_s"] = time.perf_counter() - t2, time.process_time() - c2
        row["added"] = name
        row["loss_after"] = f2.summary().get("final_loss")
        row["kept"] = bool(row["loss_after"] is not None and row["loss_before"] is not None
                           and row["loss_after"] < row["loss_before"])
        row["effect_parameters"] = getattr(getattr(f2, "result", None), "effect_parameters", None)
        row["after"] = scored(stage, gt, device, e_true)
        log(f"{n}: + {name}: E x{row['after']['e_ratio']:.2f}, MA {row['after']['ma']:.3f}", flush=True)
    return row


def top_tested(r: dict) -> dict:
    """The first significant candidate, else the tested one with the smallest p-value."""
    t = r.get("tested") or []
    sig = [c for c in t if c.get("significant")]
    return sig[0] if sig else (min(t, key=lambda c: c.get("marginal_p_value", 1.0)) if t else {})


def table(rows: list[dict]) -> str:
    out = ["| capture | what | base fit: E / true, MA, masked PSNR | diagnose: verdict, candidates (best first) | top: p, predicted / realised drop (of loss) | added | after: E / true, MA, masked PSNR |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        b, a = r.get("before") or {}, r.get("after") or {}
        cands = ", ".join(c["effect"] for c in r.get("candidates", [])) or "-"
        fa = (f"{a['e_ratio']:.2f}, {a['ma']:.3f}, {a['psnr_masked']:.1f} dB" if a else "-")
        t = top_tested(r)
        real = next((c.get("realized_loss_drop") for c in r.get("candidates", []) if c["effect"] == t.get("effect")), None)
        ts = (f"{t['effect']}: p {t.get('marginal_p_value', 1):.2g}, {t.get('marginal_predicted_loss_drop', 0):.2e} / "
              f"{'-' if real is None else f'{real:.2e}'} (loss {r.get('loss') or float('nan'):.2e})" if t else "-")
        out.append(f"| {r['scene']} | {r.get('shape')} {r.get('scenario')}, {r.get('type')} | "
                   f"{b.get('e_ratio', float('nan')):.2f}, {b.get('ma', float('nan')):.3f}, {b.get('psnr_masked', float('nan')):.1f} dB "
                   f"| {r.get('verdict', r.get('error', '-'))}: {cands} | {ts} | {r.get('added', '-')} | {fa} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--seeds", required=True)
    ap.add_argument("--cap", type=int, default=15000)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--refit-iterations", type=int, default=20)
    ap.add_argument("--add", default=None, choices=EFFECTS, help="add this effect whatever diagnose says")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    ap.add_argument("--scratch", default="/tmp/world_diagnose")
    ap.add_argument("--starts", type=int, default=3, help="diagnose --starts (1: score the base fit as it is)")
    ap.add_argument("--diagnose-refit", type=int, default=3, help="diagnose --refit: how many top candidates it "
                    "refits (--refit-iterations each) to judge them on held-back frames")
    ap.add_argument("--skip-diagnose", action="store_true", help="with --add: add the effect and refit without "
                    "diagnosing first")
    ap.add_argument("--reuse-base", action="store_true", help="diagnose the base fit an earlier run kept "
                    "(<scratch>/<name>.base) instead of fitting again")
    a = ap.parse_args(argv)

    def rows_of(n):
        try:
            return [one(Path(a.work), n, a.cap, a.iterations, a.refit_iterations, a.device, a.add, Path(a.scratch),
                        starts=a.starts, reuse_base=a.reuse_base, diagnose_refit=a.diagnose_refit, skip_diagnose=a.skip_diagnose)]
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - one capture's failure is a row
            return [{"scene": n, "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"}]

    return per_capture("world_diagnose.py", Path(a.work), a.seeds, rows_of, a.json, table,
                       show=lambda r: r.get("error") or f"{r['scene']}: done")

if __name__ == "__main__":
    sys.exit(main())
