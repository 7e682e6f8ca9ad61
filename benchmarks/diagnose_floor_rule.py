"""`diagnose` with and without the floor rule on the suite's foam_bar (issue #22): false alarms on
controls and power on weak hidden effects, each case's base fit diagnosed twice on the same stage.

Per case (`synth foam_bar --hidden EFFECT --strength S --noise 0.015`, or a control: nothing hidden,
noise seed K), `init` with the capture's suggested settings, a base `fit` from the true interaction
(`--contact-from gt`, the user's model: no effects), then `diagnose` once per rule on that one fit:
- `default`: today's decision (the 3% size gate, `DiagnoseSettings.min_relative_drop`);
- `floor`: `diagnose --floor-rule` (the superset simulator steps as the fitted model did, the rendering
  floor fitted on the rest frames and the model's discretisation error projected out, no size gate);
- `match`: `diagnose --floor-rule match` (only the superset's substeps matched to the fit's, no size gate).
A `missing_effect` verdict on a control is a false alarm; on an effect case the question is whether the
hidden effect is named first. One JSON line per case (resumable: done cases are skipped), a table at
the end (stdout and `--write`), and `$OUT/diagnose_floor_rule.json` when `$OUT` is set.
**Development data** (the synthetic suite).

GPU (one H200, <= 8 min: 20 controls + the three weak effect cases at 0.5 in one wave of 23 workers after a
small warm-up that compiles Warp's kernels; the table and JSON are rewritten in $OUT after every case, so a
run cut by `timeout` keeps what finished, and the same command with the same `--out` resumes the rest):

    timeout 480 python benchmarks/diagnose_floor_rule.py --device cuda --jobs 23 --controls 20 \\
        --effects damping,viscoelasticity,plasticity --strengths 0.5 --deadline 120 --out /tmp/dfr

The `rest` rule (2026-11-26, 13th: `--floor-rule rest`, camera causes judged on the frames before the first
grasp, heterogeneity priced as the fit's model selection, no size gate), 20 controls and two effects at 1x and
2x, with today's rule at a 1% gate (`gate1`) beside it. foam_bar's grasp is at 10% of the clip: at 14 frames
(frame 1) no frame before it is in the residual (which starts at frame 1), so `--frames 16` (grasp at frame 2:
frame 1 is a rest frame). Rules in the order they matter (a cut run has the first for the most cases): `rest`
(no gate; with a 1% gate after the fact), `gate1`; `default` on the 4 effect cases only (`--effect-only-rules`:
its foam_bar controls were measured in the 12th run, 0/10, and the decision needs its power on the same effect
cases). The run is bound by the host's 16 CPU cores, not the GPU (12th run: each worker 1.2-1.4 CPU s per wall s),
so each worker keeps torch to one thread. Estimate (12th run's rows x 16/14 frames: a base fit ~230 CPU s, a
rule's diagnosis ~150 CPU s): 24 x (230 + 2 x 150) + 4 x 150 = ~13,300 CPU s / 16 cores = 670-830 s, in two
calls of the same command on the same warm machine (the second resumes from every kept base fit and diagnosis,
work/<case>.fitted.json and work/<case>.<rule>.json under out/, and stops at "total"):

    timeout -k 15 540 python benchmarks/diagnose_floor_rule.py --device cuda --jobs 24 --controls 20 \
        --effects damping,viscoelasticity --strengths 1,2 --frames 16 --rules rest,gate1 \
        --effect-only-rules default --out out/dfr3
    (the same command again, at once, while the machine is warm; the table and JSON land in $OUT after every case)

A later call may add `--rules rest,gate1,default` to run `default` on the controls too (a case is done when its
row has every rule asked for; only the missing rules run).

The table adds each rule's count with a 1% size gate applied after the fact (`+gate1%`: a name whose
predicted share of the loss is under 1% dropped; forward selection not redone).

CPU smoke test (one control, 6 frames, grid 12, one fit iteration, no refits: ~10 min wall on a loaded
2-core box; with `--refit 0` every rule keeps the 3% gate):

    python benchmarks/diagnose_floor_rule.py --controls 1 --effects none --iterations 1 --frames 6 \\
        --fit-grid 12 --refit 0 --out /tmp/dfr_cpu
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

NOISE = 0.015
# rule name -> (api.diagnose's floor_rule, its gate: None = the rule's own, 3% or 0 under a floor rule with refits)
RULES = {"default": (False, None), "floor": ("full", None), "match": ("match", None),
         "rest": ("rest", None), "rest1": ("rest", 0.01), "gate1": (False, 0.01), "pair": (False, None),
         "res": (False, None), "rescol": (False, None)}
EXTRA = {"pair": {"pair_signature": True}, "res": {"resolution": True},
         "rescol": {"resolution": True, "resolution_column": True}}     # a rule's other api.diagnose settings (pair: damping vs ground decided
                                               # by the ground's signature at the lowest points, issue #22)


def case_list(effects: list[str], strengths: list[float], controls: int, seed0: int) -> list[tuple[str, float, int]]:
    """(hidden effect or 'none', strength, noise seed): effects and controls interleaved, so that a run
    cut by its deadline has some of each."""
    eff = [(e, s, 0) for s in strengths for e in effects if e != "none"]
    ctl = [("none", 0.0, k) for k in range(seed0, seed0 + controls)]
    out = []
    while eff or ctl:
        if ctl:
            out.append(ctl.pop(0))
        if eff:
            out.append(eff.pop(0))
        if ctl:
            out.append(ctl.pop(0))
    return out


def key(scene: str, eff: str, s: float, seed: int, calibrate: str = "particles") -> str:
    """A case's name (its capture and fits under work/): a frame-calibrated effect case is another capture
    (`_frames`); a control hides nothing, so it is the same under either calibration."""
    if eff == "none":
        return f"{scene}_none_s{seed}"
    return f"{scene}_{eff}@{s:g}" + ("_frames" if calibrate == "frames" else "")


def summary(d: dict) -> dict:
    tested = d.get("tested") or []
    named = [c["effect"] for c in d.get("candidates", [])
             if any(t["effect"] == c["effect"] and t.get("accepted") for t in tested)]
    cf = d.get("confusable") or {}
    return {"verdict": d.get("verdict"), "reason": d.get("reason"), "named": named,
            "confusable": cf.get("pair"), "confusable_add": cf.get("add"),
            "confusable_tests": cf.get("tests"),
            "significant": [c["effect"] for c in d.get("candidates", [])],
            "loss": d.get("loss"), "floor": d.get("noise_floor"),
            "substeps": (d.get("noise") or {}).get("substeps"),
            "resolution": _resolution((d.get("noise") or {}).get("resolution")),
            "floor_rest_share": ((d.get("noise") or {}).get("floor_model") or {}).get("rest_share"),
            "camera_rest_frames": (d.get("noise") or {}).get("camera_rest_frames"),
            "tested": [dict({k: t.get(k) for k in ("effect", "marginal_p_value", "p_value", "relative_drop", "significant",
                                                   "accepted", "held_back_drop", "held_back_p", "held_back_level",
                                                   "rest_only", "rival_of", "pair_test")},
                            priced=(t.get("priced") or {}).get("why"))
                       for t in tested]}


def _resolution(rz: dict | None) -> dict | None:
    """The fit's resolution error (`diagnose --resolution`) without its arrays: the estimate, the order and
    each finer grid's change and loss."""
    if not rz:
        return None
    return {"error": rz.get("error"), "order": rz.get("order"), "order_raw": rz.get("order_raw"), "cos": rz.get("cos"),
            "failed": rz.get("failed"), "seconds": rz.get("seconds"),
            "levels": [{k: lv.get(k) for k in ("split", "particles", "substeps", "change", "loss_fine", "cos", "failed")}
                       for lv in rz.get("levels") or []]}


def rules_for(a, eff: str) -> list[str]:
    """The rules a case is diagnosed with: `--effect-only-rules` on the effect cases only (after the others)."""
    return list(a.rules) + ([r for r in a.effect_only_rules if r not in a.rules] if eff != "none" else [])


def one(job) -> dict | None:
    scene, eff, s, seed, a, t_start = job
    if a.deadline and time.time() - t_start > a.deadline:
        return None
    if a.jobs > 1:        # one intra-op thread per worker: the 12th run's workers (12 on 16 cores) used 1.2-1.4 CPU s
        import torch      # per wall second; 24 workers with torch's default threads each would oversubscribe the host,
        torch.set_num_threads(int(os.environ.get("WORKER_THREADS", "1")))   # whose cores, not the GPU, bound the
        # run (WORKER_THREADS: more where the host has cores to spare, e.g. 2 for 24 workers on 64 cores)
    from physinteract_usd import api

    quiet = lambda *_a, **_k: None  # noqa: E731
    k = key(scene, eff, s, seed, a.calibrate)
    work = Path(a.out) / "work"
    cap, stage = work / k, work / f"{k}.usda"
    row = {"case": k, "scene": scene, "hidden": None if eff == "none" else eff, "strength": s, "seed": seed,
           "device": a.device, "calibrate": None if eff == "none" else a.calibrate}
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        if not (cap / "gt" / "gt.json").exists():
            api.synth(scene, cap, size=a.size, frames=a.frames, hidden=None if eff == "none" else eff,
                      strength=s or 1.0, noise=NOISE, seed=seed, device=a.device, force=True, log=quiet,
                      fit_grid=a.fit_grid, calibrate=a.calibrate)
        gtj = json.loads((cap / "gt" / "gt.json").read_text())
        sug = gtj["suggested_init"]
        he = gtj.get("hidden_effect") or {}
        if he:       # what the hidden effect is and what it does: its parameters, particle px, frames' D^2 / sigma^2
            row["hidden_effect"] = {k: he.get(k) for k in ("parameters", "effect_px", "frames_d2_over_sigma2",
                                                          "calibration_reached")}
        fitted = work / f"{k}.fitted.json"          # a call cut by its timeout keeps the base fit and each rule's
        if fitted.exists() and stage.exists():       # diagnosis: the next call resumes from them
            row["fit_s"] = json.loads(fitted.read_text())["fit_s"]
        else:
            for suffix in (".usda", ".init.usdc", ".fit.usdc"):
                (work / f"{k}{suffix}").unlink(missing_ok=True)
            shutil.rmtree(work / f"{k}.versions", ignore_errors=True)
            api.init(stage, cap, grid=sug["grid"], padding=sug["padding"], youngs_range=tuple(sug["youngs_range"]),
                     max_poisson=sug["max_poisson"], density=sug["density"], force=True, log=quiet)
            api.fit(stage, iterations=a.iterations, contact_from=cap / "gt", device=a.device, progress=False, log=quiet)
            row["fit_s"] = round(time.perf_counter() - t0, 1)
            fitted.write_text(json.dumps({"fit_s": row["fit_s"]}))
        for rule in rules_for(a, eff):
            part = work / f"{k}.{rule}.json"
            if part.exists():
                row[rule] = json.loads(part.read_text())
                continue
            t1 = time.perf_counter()
            fr, gate = RULES[rule]
            d = api.diagnose(stage, device=a.device, refit=a.refit, refit_iterations=a.diagnose_refit_iterations,
                             starts=a.starts, progress=False, log=quiet, write_stage=False, floor_rule=fr, gate=gate,
                             **EXTRA.get(rule, {}))
            row[rule] = dict(summary(d), seconds=round(time.perf_counter() - t1, 1))
            part.write_text(json.dumps(row[rule], default=float))
        row["wall_s"] = round(time.perf_counter() - t0, 1)
        row["cpu_s"] = round(time.process_time() - c0, 1)
    except Exception as exc:  # noqa: BLE001 - one case's failure is a row
        row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
    print(f"{k}: " + ("ERROR " + row["error"] if "error" in row else
                      "; ".join(f"{r} {row[r]['verdict']} {row[r]['named'] or '-'} ({row[r]['seconds']:.0f} s)"
                                for r in rules_for(a, eff) if r in row)), flush=True)
    return row


def table(rows: list[dict], rules) -> tuple[str, dict]:
    out, js = [], {}
    ctl = [r for r in rows if r.get("hidden") is None and "error" not in r]
    eff = [r for r in rows if r.get("hidden") is not None and "error" not in r]
    out.append("| rule | controls: false alarms (missing_effect) | what they named | effect cases: hidden named first "
               "| named (the truth within a confusable verdict) | hidden named at all |")
    out.append("|---|---|---|---|---|---|")
    for rule in rules:
        c = [r[rule] for r in ctl if rule in r]
        fa = [x for x in c if x["verdict"] == "missing_effect"]
        what = {}
        for x in fa:
            for n in x["named"][:1]:
                what[n] = what.get(n, 0) + 1
        e = [(r, r[rule]) for r in eff if rule in r]
        # a confusable verdict ("damping or ground friction: the frames cannot tell them apart") is not a name first,
        # even when the truth is the one it would add: it is counted in its own column when the truth is in the pair
        first = sum(1 for r, x in e if x["named"][:1] == [r["hidden"]] and not x.get("confusable"))
        within = sum(1 for r, x in e if x.get("confusable") and r["hidden"] in x["confusable"])
        anyn = sum(1 for r, x in e if r["hidden"] in x["named"])
        out.append(f"| {rule} | {len(fa)}/{len(c)} | {', '.join(f'{k} {v}' for k, v in what.items()) or '-'} | "
                   f"{first}/{len(e)} | {within}/{len(e)} | {anyn}/{len(e)} |")
        js[rule] = {"controls": len(c), "false_alarms": len(fa), "named_on_controls": what, "effect_cases": len(e),
                    "hidden_first": first, "hidden_within_confusable": within, "hidden_named": anyn}

        def gated(x, g=0.01):            # the names whose predicted share of the loss is >= g (after the fact)
            rel = {t["effect"]: t.get("relative_drop") or 0.0 for t in x["tested"]}
            return [n for n in x["named"] if rel.get(n, 0.0) >= g]

        fa1 = [x for x in c if gated(x)]
        first1 = sum(1 for r, x in e if gated(x)[:1] == [r["hidden"]] and not x.get("confusable"))
        any1 = sum(1 for r, x in e if r["hidden"] in gated(x))
        out.append(f"| {rule} +gate1% | {len(fa1)}/{len(c)} | "
                   f"{', '.join(sorted({n for x in fa1 for n in gated(x)[:1]})) or '-'} | {first1}/{len(e)} | - | "
                   f"{any1}/{len(e)} |")
        js[rule + "+gate1%"] = {"controls": len(c), "false_alarms": len(fa1), "effect_cases": len(e),
                                "hidden_first": first1, "hidden_named": any1}
    out.append("")
    out.append("| case | " + " | ".join(rules) + " |")
    out.append("|---|" + "---|" * len(rules))
    for r in sorted(eff, key=lambda r: (r["hidden"], r["strength"])) + ctl:
        cells = []
        for rule in rules:
            x = r.get(rule)
            if x is None:
                cells.append("-")
                continue
            h = next((t for t in x["tested"] if t["effect"] == (r["hidden"] or (x["named"] or ["camera:depth_scale"])[0])),
                     None)
            hx = "" if h is None else (f"; {h['effect']}: p {h['marginal_p_value']:.2g}, "
                                       f"{100 * (h['relative_drop'] or 0):.1f}%"
                                       + ("" if h.get("held_back_p") is None else f", held-back p {h['held_back_p']:.2g}"))
            names = (" or ".join(x["confusable"]) + " (confusable)") if x.get("confusable") else \
                (", ".join(x["named"]) or "-")
            cells.append(f"{x['verdict']}: {names}{hx}")
        out.append(f"| {r['case']} | " + " | ".join(cells) + " |")
    return "\n".join(out), js


def spread_gpus() -> None:
    """A pool worker's GPU on a host of several (benchmarks/gpu_spread.py: `NGPUS`, `GPU_LIST`), set before Warp
    or torch start CUDA in it."""
    import multiprocessing as mp

    from gpu_spread import gpu_for

    g = gpu_for((mp.current_process()._identity or (1,))[0] - 1)
    if g is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = g


def warm_up(device: str, where: Path) -> None:
    """Warp's kernels compiled once into the on-disk cache before the workers start: the tests' tiny bar
    diagnosed with and without the rule, one refit of one iteration (seconds on a GPU, not a case)."""
    try:
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
        import diagnose_scene as ds

        from physinteract_usd import api

        info = ds.build(where, noise=NOISE, seed=0)
        for fr in (False, "full", "rest"):
            api.diagnose(info["stage"], device=device, refit=1, refit_iterations=1, starts=1, progress=False,
                         log=lambda *_a: None, write_stage=False, floor_rule=fr,
                         candidates="damping,viscoelasticity,camera:depth_scale")
    except Exception as exc:  # noqa: BLE001 - the warm-up is an optimisation
        print(f"warm-up failed ({type(exc).__name__}: {exc}); the first worker compiles", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="foam_bar")
    ap.add_argument("--effects", default="damping,viscoelasticity,plasticity")
    ap.add_argument("--strengths", default="0.5")
    ap.add_argument("--controls", type=int, default=20)
    ap.add_argument("--control-seed", type=int, default=0)
    ap.add_argument("--rules", default="default,floor,match",
                    help="diagnose each case with these: " + ", ".join(RULES) + " (rest: --floor-rule rest, no gate; "
                         "rest1: the same with a 1%% gate; gate1: today's rule with a 1%% gate)")
    ap.add_argument("--effect-only-rules", default="",
                    help="rules run on the effect cases only (e.g. default: its controls measured before), after --rules")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--fit-grid", type=int, default=None)
    ap.add_argument("--calibrate", choices=["particles", "frames"], default="particles",
                    help="synth --calibrate: the hidden effect's strength in projected particle px (default) or as "
                         "the frames' change over the noise variance (issue #22's 1x: the loss halved); the effect "
                         "cases' names get _frames, the controls are shared")
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--refit", type=int, default=3)
    ap.add_argument("--diagnose-refit-iterations", type=int, default=8)
    ap.add_argument("--starts", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--deadline", type=float, default=0, help="start no case after this many seconds")
    ap.add_argument("--out", default="/tmp/diagnose_floor_rule")
    ap.add_argument("--write", default=None, help="write the table to this markdown file")
    a = ap.parse_args(argv)
    import signal

    # `timeout`'s SIGTERM: leave through the pool's context manager, so its workers are terminated with us
    signal.signal(signal.SIGTERM, lambda *_a: sys.exit(143))
    a.rules = [r for r in a.rules.split(",") if r]
    a.effect_only_rules = [r for r in a.effect_only_rules.split(",") if r]
    bad = [r for r in a.rules + a.effect_only_rules if r not in RULES]
    if bad:
        print(f"diagnose_floor_rule.py: error: --rules: unknown {bad[0]!r} ({', '.join(RULES)})", file=sys.stderr)
        return 2
    out = Path(a.out)
    (out / "work").mkdir(parents=True, exist_ok=True)
    a.out = str(out)
    jl = out / "rows.jsonl"
    # a case is done when its row has every rule asked for now: a later call with more rules (the split run)
    # diagnoses only the missing ones, on the base fit and the rules' diagnoses kept under work/
    done = {r["case"] for r in map(json.loads, filter(str.strip, jl.read_text().splitlines()))
            if "error" not in r and all(rule in r for rule in rules_for(a, "none" if r.get("hidden") is None else "x"))} \
        if jl.exists() else set()
    t0 = time.time()
    todo = [c for c in case_list(a.effects.split(","), [float(v) for v in a.strengths.split(",")], a.controls,
                                 a.control_seed) if key(a.scene, *c, a.calibrate) not in done]
    print(f"{len(todo)} cases to run ({len(done)} done before)", flush=True)
    jobs = [(a.scene, e, s, seed, a, t0) for e, s, seed in todo]

    def report(final: bool = False) -> None:
        rows = {}
        for x in jl.read_text().splitlines() if jl.exists() else []:
            if x.strip():
                r = json.loads(x)
                rows[r["case"]] = r
        text, js = table(list(rows.values()), a.rules + [r for r in a.effect_only_rules if r not in a.rules])
        if final:
            print(text)
        if a.write:
            Path(a.write).write_text("# diagnose with and without the floor rule\n\n" + text + "\n")
        if os.environ.get("OUT"):        # after every case: a run cut short still leaves its table
            Path(os.environ["OUT"], "diagnose_floor_rule.json").write_text(
                json.dumps({"summary": js, "elapsed_s": round(time.time() - t0, 1), "rows": list(rows.values())},
                           indent=1, default=float))
            Path(os.environ["OUT"], "diagnose_floor_rule.md").write_text(text + "\n")

    def append(row):
        if row is not None:
            with jl.open("a") as f:
                f.write(json.dumps(row, default=float) + "\n")
            report()

    if a.jobs > 1 and len(jobs) > 1:
        import multiprocessing as mp

        warm_up(a.device, out / "warm")
        print(f"warm-up {time.time() - t0:.0f} s", flush=True)
        with mp.get_context("spawn").Pool(min(a.jobs, len(jobs)), initializer=spread_gpus) as pool:
            for row in pool.imap_unordered(one, jobs):
                append(row)
    else:
        for job in jobs:
            row = one(job)
            if row is None:
                print("deadline: stopping", flush=True)
                break
            append(row)
    report(final=True)
    print(f"total {time.time() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
