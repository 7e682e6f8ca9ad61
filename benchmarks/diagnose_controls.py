"""diagnose's decision rule on the tests' tiny bar (issue #22), small enough for a CPU.

Cases: `control@SEED` (nothing hidden, pixel noise sigma 0.015 with that seed: a `missing_effect`
verdict is a false alarm) and `EFFECT@STRENGTH` (benchmarks/diagnose_suite.py's hidden effects on
the same bar). Each runs `api.diagnose` with the given refit settings (default: the top 3 refitted
6 iterations, 2 folds, `--starts 1`) and records what decided: every candidate's score test (p, share
of the loss), whether it was significant, refitted, its held-back drop, p and the Holm level, and
what was named. One JSON line per case (resumable). CPU seconds (process time) beside wall seconds.
**Development data.**

    python benchmarks/diagnose_controls.py --out /tmp/diag_controls --cases control@0..19
    python benchmarks/diagnose_controls.py --out /tmp/diag_pair --cases damping@2,viscoelasticity@2
    python benchmarks/diagnose_controls.py --out /tmp/diag_floor --cases control@0..5 --floor-rule
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))


def cases_of(spec: str) -> list[str]:
    out = []
    for c in spec.split(","):
        kind, arg = c.strip().split("@")
        if ".." in arg:
            a, b = arg.split("..")
            out += [f"{kind}@{i}" for i in range(int(a), int(b) + 1)]
        else:
            out.append(f"{kind}@{arg}")
    return out


def run_case(case: str, work: Path, refit: int, iterations: int, starts: int, folds: int,
             floor_rule: bool | str = False, gate: float | None = None) -> dict:
    import shutil

    import diagnose_scene as ds
    from diagnose_suite import NOISE, hidden_for

    from physinteract_usd import api

    kind, arg = case.split("@")
    root = work / case.replace("@", "_").replace(".", "p")
    shutil.rmtree(root, ignore_errors=True)
    if kind == "control":
        info = ds.build(root, noise=NOISE, seed=int(arg))
        hidden = None
    else:
        info = ds.build(root, hidden=hidden_for(kind, float(arg)), noise=NOISE, seed=0)
        hidden = kind
    t0, c0 = time.perf_counter(), time.process_time()
    d = api.diagnose(info["stage"], refit=refit, refit_iterations=iterations, progress=False, log=lambda *a: None,
                     write_stage=False, starts=starts, refit_folds=folds, floor_rule=floor_rule, gate=gate)
    row = {"case": case, "hidden": hidden, "floor_rule": floor_rule, "gate": gate, "verdict": d["verdict"], "reason": d["reason"],
           "named": [c["effect"] for c in d["candidates"]
                     if any(t["effect"] == c["effect"] and t.get("accepted") for t in d["tested"])],
           "significant": [c["effect"] for c in d["candidates"]],
           "loss": d["loss"], "floor": d["noise_floor"],
           "seconds": round(time.perf_counter() - t0, 1), "cpu_seconds": round(time.process_time() - c0, 1),
           "tested": [{k: c.get(k) for k in ("effect", "p_value", "relative_drop", "marginal_p_value", "significant",
                                             "accepted", "held_back_drop", "held_back_se", "held_back_p",
                                             "held_back_level", "rival_test", "confusable_with", "note")}
                      for c in d["tested"]],
           "evidence": {c["effect"]: c.get("evidence") for c in d["candidates"]}}
    row["false_alarm"] = bool(hidden is None and d["verdict"] == "missing_effect")
    shutil.rmtree(root, ignore_errors=True)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="/tmp/diag_controls")
    ap.add_argument("--cases", default="control@0..19")
    ap.add_argument("--refit", type=int, default=3)
    ap.add_argument("--refit-iterations", type=int, default=6)
    ap.add_argument("--starts", type=int, default=1)
    ap.add_argument("--refit-folds", type=int, default=2)
    ap.add_argument("--floor-rule", nargs="?", const="full", default=False, choices=("full", "match", "rest"),
                    help="diagnose --floor-rule [full|match|rest] (issue #22)")
    ap.add_argument("--gate", type=float, default=None, help="diagnose --gate SHARE (the size gate)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "rows.jsonl"
    done = {json.loads(ln)["case"] for ln in path.read_text().splitlines() if ln.strip()} if path.exists() else set()
    for case in cases_of(a.cases):
        if case in done:
            continue
        r = run_case(case, out / "work", a.refit, a.refit_iterations, a.starts, a.refit_folds, a.floor_rule, a.gate)
        with path.open("a") as f:
            f.write(json.dumps(r) + "\n")
        sig = ", ".join(f"{t['effect']} (p {t['p_value']:.2g}, {100 * (t['relative_drop'] or 0):.1f}%"
                        + (f", held-back p {t['held_back_p']:.2g} < {t['held_back_level']:.2g}?"
                           if t.get("held_back_p") is not None and t.get("held_back_level") is not None else "")
                        + (", accepted" if t.get("accepted") else "") + ")"
                        for t in r["tested"] if t["significant"])
        print(f"{case}: {r['verdict']} named {r['named'] or '-'}; significant: {sig or '-'} "
              f"({r['seconds']:.0f} s, {r['cpu_seconds']:.0f} CPU s)", flush=True)
    rows = [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]
    ctl = [r for r in rows if r["hidden"] is None]
    if ctl:
        fa = sum(r["false_alarm"] for r in ctl)
        print(f"controls: {fa}/{len(ctl)} false alarms; verdicts "
              + ", ".join(f"{v} {sum(r['verdict'] == v for r in ctl)}" for v in sorted({r['verdict'] for r in ctl}))
              + f"; with a significant candidate: {sum(bool(r['significant']) for r in ctl)}/{len(ctl)}; "
              f"CPU s per case {sum(r['cpu_seconds'] for r in ctl) / len(ctl):.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
