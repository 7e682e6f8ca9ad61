"""The diagnosis on the synthetic suite's named scenes with a hidden effect (issue #22's suite table).

Per case (scene, hidden effect or `none`, strength): `synth NAME --hidden EFFECT --strength S
--noise 0.015` (the effect is calibrated by the generator to S x its noise level in pixels), `init`
with the capture's suggested settings (or `--grid`), a base `fit` from the TRUE interaction
(`--contact-from gt`: extraction is measured elsewhere) with the model the user starts with (no
effects), `evaluate`, then `diagnose` (all candidates, the top 3 refitted briefly), then the hidden
effect added (`effects add`, the truth's effect: the table's "after adding it") and a warm refit,
evaluated again. Controls (`none`) add nothing: a `missing_effect` verdict on them is a false alarm.

Row per case (JSON lines, resumable: done cases are skipped): the rank of the hidden effect among
the significant candidates, the verdict, predicted vs realised loss drop of the top candidate and of
the hidden effect's own test, the confusable pair named, the masked PSNR before and after adding the
hidden effect, the fitted parameter against the truth's, wall and CPU seconds. The table: per
effect x strength, the controls' false alarms (`--controls N`: N noise seeds of the scene, nothing
hidden) and a confusion matrix (hidden effect x what the verdict named first).
Everything goes through the package's Python API; `--jobs N` runs N cases at once in N worker
processes (one Warp start each; on a GPU the cases are launch-bound, so several share it well).

    python benchmarks/suite_diagnose.py --scenes foam_bar --device cuda --out /tmp/sd \
        [--effects damping,viscoelasticity] [--strengths 0.5,1,2,4] [--controls 20] [--iterations 30] \
        [--frames 14] [--fit-grid 24] [--jobs 8] [--deadline 540] [--write docs/benchmarks/diagnose_named_table.md]

Development data only (the synthetic suite's scenes).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from physinteract_usd import api  # noqa: E402

TRUTH_PARAM = {"damping": "coefficient", "plasticity": "yieldStress", "ground": "height",
               "viscoelasticity": "modulus"}
NOISE = 0.015


def cases(scenes: list[str], effects: list[str] | None, strengths: list[float], controls: int = 1,
          first_seed: int = 0) -> list[tuple[str, str, float, int]]:
    """Every (scene, effect, strength, seed) to run: a scene's own hidden effects (the generator's list
    for it) unless `effects` names them (seed 0), and `controls` controls (`none`, seeds 0..N-1) per
    scene (seeds `first_seed`.. `first_seed` + N - 1: `--control-seed`, so that two runs on two machines
    make different controls). The effects first, strength by strength, then the controls interleaved,
    so that a run cut by its deadline has a bit of everything."""
    from physinteract_usd.synth.scenes import get_scene

    eff_cases, ctrl = [], []
    for sc in scenes:
        own = list(get_scene(sc).hidden_effects)
        effs = [e for e in (effects or own) if e != "none"]
        for s in strengths:
            eff_cases += [(sc, e, s, 0) for e in effs]
        ctrl += [(sc, "none", 0.0, k) for k in range(int(first_seed), int(first_seed) + int(controls))]
    out, step = [], max(1, len(eff_cases) // max(len(ctrl), 1))
    while eff_cases or ctrl:
        out += eff_cases[:step]
        eff_cases = eff_cases[step:]
        if ctrl:
            out.append(ctrl.pop(0))
    return out


def key(sc: str, eff: str, s: float, seed: int = 0, calibrate: str = "particles") -> str:
    """A case's name; a frame-calibrated effect case (`synth --calibrate frames`) is another capture (`_frames`)."""
    return (f"{sc}_{eff}" + ("" if eff == "none" else f"@{s:g}") + (f"#{seed}" if seed else "")
            + ("_frames" if calibrate == "frames" and eff != "none" else ""))


def scored(stage: Path, gt: Path, device: str) -> dict:
    ev = api.evaluate(stage, gt, device=device)
    return {k: ev.get(k) for k in ("ma", "ma_best_uniform", "psnr_masked", "psnr", "position_error_m")}


def one(sc: str, eff: str, s: float, a, work: Path, log, seed: int = 0) -> dict:
    k = key(sc, eff, s, seed, a.calibrate)
    cap, stage = work / k, work / f"{k}.usda"
    row = {"case": k, "scene": sc, "hidden": eff, "strength": s, "seed": seed, "device": a.device,
           "calibrate": None if eff == "none" else a.calibrate,
           "iterations": a.iterations, "frames": a.frames, "fit_grid": a.fit_grid,
           "diagnose_refit_iterations": a.diagnose_refit_iterations, "refit_folds": a.refit_folds}
    quiet = lambda *_a, **_k: None  # noqa: E731
    t0, c0 = time.perf_counter(), time.process_time()
    if not (cap / "gt" / "gt.json").exists():
        api.synth(sc, cap, size=a.size, frames=a.frames, hidden=None if eff == "none" else eff, strength=s or 1.0,
                  noise=NOISE, seed=seed, device=a.device, force=True, log=quiet, fit_grid=a.fit_grid,
                  calibrate=a.calibrate)
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
    d = api.diagnose(stage, device=a.device, refit=a.refit, refit_iterations=a.diagnose_refit_iterations,
                     starts=a.starts, progress=False, log=quiet, write_stage=False, refit_folds=a.refit_folds)
    row["diagnose_s"] = round(time.perf_counter() - t2, 1)
    row["verdict"] = d.get("verdict")
    row["reason"] = d.get("reason")
    sig = [c["effect"] for c in d.get("candidates", [])]
    row["significant"] = sig
    row["rank"] = (sig.index(eff) + 1) if eff in sig else None
    top = (d.get("candidates") or [None])[0]
    if top:
        row["top"] = {kk: top.get(kk) for kk in ("effect", "predicted_loss_drop", "realized_loss_drop", "estimate")}
    row["tested"] = [{kk: c.get(kk) for kk in ("effect", "p_value", "predicted_loss_drop", "relative_drop",
                                               "marginal_p_value", "marginal_predicted_loss_drop", "significant",
                                               "accepted", "held_back_drop", "held_back_se", "held_back_p",
                                               "rival_test", "confusable_with", "collinearity", "note")}
                     for c in d.get("tested", [])]
    row["loss"], row["noise_floor"] = d.get("loss"), d.get("noise_floor")
    own = next((c for c in d.get("candidates", []) if c["effect"] == eff), None)
    if own:       # the hidden effect's own candidate: its predicted and realised drop, its estimate
        row["hidden_candidate"] = {kk: own.get(kk) for kk in ("predicted_loss_drop", "realized_loss_drop",
                                                               "estimate")}
        e = (own.get("estimate") or {}).get(TRUTH_PARAM.get(eff, ""))
        if e is not None and row.get("truth"):
            row["diagnose_estimate_ratio"] = float(e) / float(row["truth"])
    top_t = next((c for c in d.get("tested", []) if top and c["effect"] == top["effect"]), None)
    row["pair"] = None if top_t is None else top_t.get("confusable_with")
    row["false_alarm"] = bool(eff == "none" and row["verdict"] == "missing_effect")
    log(f"{k}: diagnose {row['verdict']} {sig} ({row['diagnose_s']:.0f} s)")
    if a.control_refit:
        # the same warm refit without the effect (`fit --resume`: from v1, the same iterations): what the
        # 20 more iterations alone gain, so the gain of adding the effect is not credited with them
        ctl = work / "control_refit" / k
        shutil.rmtree(ctl, ignore_errors=True)
        ctl.mkdir(parents=True)
        for suffix in (".usda", ".init.usdc", ".fit.usdc"):
            if (work / f"{k}{suffix}").exists():
                shutil.copy2(work / f"{k}{suffix}", ctl / f"{k}{suffix}")
        if (work / f"{k}.versions").exists():
            shutil.copytree(work / f"{k}.versions", ctl / f"{k}.versions")
        (ctl / k).symlink_to(cap.resolve())          # the stage's capture paths are relative
        t4 = time.perf_counter()
        try:        # the attribution's failure is its own, not the case's
            f3 = api.fit(ctl / f"{k}.usda", iterations=a.refit_iterations, contact_from=gt, device=a.device,
                         progress=False, log=quiet, keep_best=False, resume=True)
            row["control_refit_s"] = round(time.perf_counter() - t4, 1)
            row["loss_after_control"] = f3.summary().get("final_loss")
            row["after_control"] = scored(ctl / f"{k}.usda", gt, a.device)
            log(f"{k}: the same refit without the effect: masked PSNR {row['after_control']['psnr_masked']:.2f} dB")
        except Exception as exc:  # noqa: BLE001
            row["control_refit_error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
            log(f"{k}: the control refit failed: {row['control_refit_error']}")
    if eff != "none":
        api.effects_add(stage, eff)
        t3 = time.perf_counter()
        f2 = api.fit(stage, iterations=a.refit_iterations, contact_from=gt, device=a.device, progress=False,
                     log=quiet, keep_best=False, warm_path=a.warm_path)
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
    row["wall_s"] = round(time.perf_counter() - t0, 1)
    row["cpu_s"] = round(time.process_time() - c0, 1)
    return row


def fmt(v, f="{:.3g}"):
    return "-" if v is None else f.format(v)


def named_first(r: dict) -> str:
    """What the verdict names first: the top candidate of a `missing_effect`, else the verdict."""
    if r.get("verdict") == "missing_effect" and r.get("significant"):
        return r["significant"][0]
    return r.get("verdict") or "?"


def _gain(r: dict) -> str:
    b, af = r.get("before") or {}, r.get("after") or {}
    if not af or b.get("psnr_masked") is None or af.get("psnr_masked") is None:
        return "-"
    ratio = (r.get("loss_after") or 0) / r["loss_before"] if r.get("loss_before") else None
    return f"{af['psnr_masked'] - b['psnr_masked']:+.2f} dB, {fmt(ratio, '{:.2f}')}"


def _gain_control(r: dict) -> str:
    """The masked PSNR gain of the same warm refit without the effect (`--control-refit`), and what
    adding the effect gains beyond it."""
    b, c, af = r.get("before") or {}, r.get("after_control") or {}, r.get("after") or {}
    if b.get("psnr_masked") is None or c.get("psnr_masked") is None:
        return "-"
    out = f"{c['psnr_masked'] - b['psnr_masked']:+.2f} dB"
    if af.get("psnr_masked") is not None:
        out += f"; the effect beyond it {af['psnr_masked'] - c['psnr_masked']:+.2f} dB"
    return out


def table(rows: list[dict]) -> str:
    """The issue's table (effect x strength), the controls, the confusion matrix, then every row."""
    ok = [r for r in rows if "error" not in r]
    named = sorted([r for r in ok if r.get("hidden") not in (None, "none")],
                   key=lambda r: (r["scene"], r["hidden"], r["strength"]))
    ctrl = [r for r in ok if r.get("hidden") == "none"]
    out = ["| scene | hidden effect | strength | verdict: significant (best first) | rank of the hidden effect | "
           "named first: predicted / realised drop; held-back drop +- se (paired p) | hidden effect's test: p, predicted drop / loss (marginal) | "
           "confusable pair | + hidden effect: masked PSNR gain, loss after / before | the same refit without it: "
           "masked PSNR gain | fitted / truth (refit; diagnose) | s wall (CPU) |", "|---" * 12 + "|"]
    def held(e):
        """A refitted candidate's held-back drop +- its standard error (p of the paired test)."""
        c = next((c for c in r.get("tested") or [] if c["effect"] == e), {})
        if c.get("held_back_drop") is None:
            return ""
        se, p = c.get("held_back_se"), c.get("held_back_p")
        return (f"; held-back {fmt(c['held_back_drop'])}" + (f" +- {fmt(se, '{:.2g}')}" if se is not None else "")
                + (f" (p {fmt(p, '{:.2g}')}{'' if c.get('accepted') else ', not accepted'})" if p is not None else ""))

    for r in named:
        t = r.get("top") or {}
        h = next((c for c in r.get("tested") or [] if c["effect"] == r["hidden"]), {})
        hh = held(r["hidden"]) if h and t.get("effect") != r["hidden"] else ""
        mp, md = h.get("marginal_p_value"), h.get("marginal_predicted_loss_drop")
        hp = (f"{fmt(mp, '{:.2g}')}, {fmt(md / r['loss'] if md is not None and r.get('loss') else None, '{:.1%}')}"
              if h else "-")
        out.append(f"| {r['scene']} | {r['hidden']} | {r['strength']:g} | {r.get('verdict')}: "
                   f"{', '.join(r.get('significant') or []) or '-'} | {r.get('rank') or 'not named'} | "
                   f"{t.get('effect', '-')}: {fmt(t.get('predicted_loss_drop'))} / {fmt(t.get('realized_loss_drop'))}"
                   f"{held(t['effect']) if t.get('effect') else ''} | "
                   f"{hp}{hh} | {', '.join(r['pair']) if isinstance(r.get('pair'), list) else (r.get('pair') or '-')} | {_gain(r)} | "
                   f"{_gain_control(r)} | {fmt(r.get('estimate_ratio'), '{:.2f}x')}; "
                   f"{fmt(r.get('diagnose_estimate_ratio'), '{:.2f}x')} | {fmt(r.get('wall_s'), '{:.0f}')} "
                   f"({fmt(r.get('cpu_s'), '{:.0f}')}) |")
    if named:
        first = sum(1 for r in named if r.get("rank") == 1)
        out.append(f"\nHidden effect ranked first: {first}/{len(named)}.")
        for s_ in sorted({r["strength"] for r in named}):
            rs = [r for r in named if r["strength"] == s_]
            out.append(f"- strength {s_:g}: first {sum(1 for r in rs if r.get('rank') == 1)}/{len(rs)}")
    if ctrl:
        fa = sum(bool(r.get("false_alarm")) for r in ctrl)
        verdicts = {}
        for r in ctrl:
            verdicts[named_first(r)] = verdicts.get(named_first(r), 0) + 1
        out.append(f"\nControls (nothing hidden, noise seeds {', '.join(str(r.get('seed', 0)) for r in ctrl)}): "
                   f"false alarms {fa}/{len(ctrl)} ({100.0 * fa / len(ctrl):.0f}%); verdicts "
                   + ", ".join(f"{k} {v}" for k, v in sorted(verdicts.items())))
        cg = [r["after_control"]["psnr_masked"] - r["before"]["psnr_masked"] for r in ctrl
              if (r.get("after_control") or {}).get("psnr_masked") is not None]
        if cg:
            out.append(f"The controls' warm refit ({len(cg)} of them, no effect): masked PSNR gain "
                       f"{sum(cg) / len(cg):+.2f} dB on average ({min(cg):+.2f} to {max(cg):+.2f})")
    # the confusion matrix: hidden effect (rows) x what the verdict named first (columns)
    truth = sorted({r["hidden"] for r in ok})
    said = sorted({named_first(r) for r in ok})
    if ok:
        out.append("\nConfusion matrix (rows: hidden effect; columns: named first, or the verdict when nothing is):\n")
        out.append("| hidden \\ named | " + " | ".join(said) + " |")
        out.append("|---" * (len(said) + 1) + "|")
        for h in truth:
            rs = [r for r in ok if r["hidden"] == h]
            out.append(f"| {h} | " + " | ".join(str(sum(1 for r in rs if named_first(r) == c) or "") for c in said)
                       + " |")
    err = [r for r in rows if "error" in r]
    if err:
        out.append("\nFailed cases: " + "; ".join(f"{r['case']}: {r['error']}" for r in err))
    return "\n".join(out) + "\n"


def _worker(job):
    """One case in a worker process (`--jobs`): its row, or the error as a row."""
    sc, eff, s, seed, a, t_start = job
    if a.deadline and time.time() - t_start > a.deadline:
        return None
    log = lambda m: print(m, flush=True)  # noqa: E731
    try:
        return one(sc, eff, s, a, Path(a.out), log, seed)
    except Exception as exc:  # noqa: BLE001 - one case's failure is a row
        row = {"case": key(sc, eff, s, seed, a.calibrate), "scene": sc, "hidden": eff, "strength": s, "seed": seed,
               "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"}
        log(f"{row['case']}: {row['error']}")
        return row


def _append(jl: Path, row: dict) -> None:
    import fcntl

    with open(jl, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.write(json.dumps(row, default=float) + "\n")
        fcntl.flock(f, fcntl.LOCK_UN)


def _rows(jl: Path) -> list[dict]:
    """The rows of the results file, the last one per case (a failed case run again replaces its row)."""
    if not jl.exists():
        return []
    last = {}
    for line in jl.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            last[r["case"]] = r
    return list(last.values())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="foam_bar")
    ap.add_argument("--effects", default=None, help="comma-separated (default: each scene's own hidden effects)")
    ap.add_argument("--strengths", default="1")
    ap.add_argument("--controls", type=int, default=1, help="control runs per scene (noise seeds S..S+N-1)")
    ap.add_argument("--control-seed", type=int, default=0, help="S: the controls' first noise seed (default 0)")
    ap.add_argument("--rows", default=None, help="more results.jsonl files (another run's) merged into the table")
    ap.add_argument("--size", default="small")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--fit-grid", type=int, default=None,
                    help="synth --fit-grid: the init grid the capture suggests (the truth's grid follows it)")
    ap.add_argument("--calibrate", choices=["particles", "frames"], default="particles",
                    help="synth --calibrate: the hidden effect's strength in projected particle px (default) or as "
                         "the frames' change over the noise variance (issue #22's 1x); effect cases get _frames")
    ap.add_argument("--grid", default=None, help="init grid (default: the capture's suggestion), a number or auto")
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--refit-iterations", type=int, default=20, help="the fit after `effects add`")
    ap.add_argument("--refit", type=int, default=3, help="diagnose --refit")
    ap.add_argument("--diagnose-refit-iterations", type=int, default=8, help="diagnose --refit-iterations")
    ap.add_argument("--starts", type=int, default=3, help="diagnose --starts")
    ap.add_argument("--control-refit", action=argparse.BooleanOptionalAction, default=True,
                    help="also the same warm refit without the effect (fit --resume, --refit-iterations): what the "
                         "iterations alone gain (default on)")
    ap.add_argument("--refit-folds", type=int, default=2, choices=(1, 2),
                    help="diagnose's confirmation refits: 2 cross-fitted folds (default) or 1")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once, each in its own process")
    ap.add_argument("--warm-path", default="both", choices=("both", "fitted", "measured"),
                    help="the refit after `effects add` starts its hand paths from the base fit's, the measured ones, "
                         "or both with the lower final loss kept (fit's warm_path; default both)")
    ap.add_argument("--warm-up", action="store_true",
                    help="compile the kernels on the tests' tiny bar (seconds) instead of running the first case alone, "
                         "and spread the workers over the host's GPUs (NGPUS / GPU_LIST)")
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
    a.out = str(work)
    jl = work / "results.jsonl"
    done = {r["case"] for r in _rows(jl) if "error" not in r}      # failed cases are tried again
    t0 = time.time()
    todo = [c for c in cases(a.scenes.split(","), a.effects.split(",") if a.effects else None,
                             [float(v) for v in a.strengths.split(",")], a.controls, a.control_seed)
            if key(*c, calibrate=a.calibrate) not in done]
    print(f"{len(todo)} cases to run ({len(done)} done before)", flush=True)
    jobs = [(sc, eff, s, seed, a, t0) for sc, eff, s, seed in todo]
    if a.jobs > 1 and len(jobs) > 1:
        import multiprocessing as mp

        if a.warm_up:
            # the tests' tiny bar diagnosed in seconds compiles the kernels (diagnose_floor_rule.warm_up); every
            # case then runs in the pool, each worker on its GPU of a host of several (`NGPUS`, `GPU_LIST`)
            from diagnose_floor_rule import spread_gpus, warm_up

            warm_up(a.device, work / "warm_up")
            first, init = [], spread_gpus
        else:
            # the first case here, alone: it compiles Warp's kernels into the on-disk cache that the
            # workers then load (a fresh machine's cold cache, compiled once rather than by every worker)
            first, init = [jobs[0]], None
            row = _worker(jobs[0])
            if row is not None:
                _append(jl, row)
        rest = jobs[len(first):]
        with mp.get_context("spawn").Pool(min(a.jobs, len(rest)), initializer=init) as pool:
            for row in pool.imap_unordered(_worker, rest):
                if row is not None:
                    _append(jl, row)
    else:
        for job in jobs:
            row = _worker(job)
            if row is None:
                print("deadline: stopping", flush=True)
                break
            _append(jl, row)
    rows = {r["case"]: r for f in ([jl] + [Path(x) for x in (a.rows.split(",") if a.rows else [])]) for r in _rows(f)}
    text = table(list(rows.values()))
    print(text)
    if a.write:
        Path(a.write).write_text("# diagnose on the suite's named scenes\n\n" + __doc__.split("\n\n")[1] + "\n\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
