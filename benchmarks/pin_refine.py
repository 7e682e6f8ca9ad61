"""The clamp's pin rules under grid refinement, against the Timoshenko beam (#24, CPU, seconds a run).

The test bar of tests/test_known_answers.py clamped at one end (L / h ~ 2.3), released straight at rest:
its mean tip sag and first frequency against the Timoshenko cantilever, per pin rule (simulation.PIN_RULE:
default (4, 0), band (5, 0.4), gain1 (1, 0): the world generator's) and per grid. From them, the uniform E
a fit of that simulation would need to match the beam (sag ~ 1/E, f ~ sqrt(E)): E_sag = sag / beam's,
E_freq = (beam's f / f)^2, and the same against the finest grid of the same rule (a truth simulated on a
finer grid than the fit's, as the world captures are).

    python benchmarks/pin_refine.py --rules default,band,gain1 --grids 10,16,24 --E 1e5
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

RULES = {"default": (4.0, 0.0), "band": (5.0, 0.4), "gain1": (1.0, 0.0)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rules", default="default,band,gain1")
    ap.add_argument("--grids", default="10,16,24")
    ap.add_argument("--E", type=float, default=1e5)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from physinteract_usd import simulation
    from test_known_answers import cantilever_vs_beam_theory

    grids = [int(g) for g in a.grids.split(",") if g]
    rows = []
    for rule in [r for r in a.rules.split(",") if r]:
        if rule not in RULES:
            print(f"pin_refine.py: error: --rules: unknown {rule!r} ({', '.join(RULES)})", file=sys.stderr)
            return 2
        simulation.PIN_RULE = RULES[rule]
        for g in grids:
            t0, c0 = time.perf_counter(), time.process_time()
            with tempfile.TemporaryDirectory() as td:
                try:
                    sag, f = cantilever_vs_beam_theory(Path(td), grid=g, E=a.E)
                    sag, f = float(sag), float(f)
                    r = {"rule": rule, "grid": g, "sag_over_beam": sag, "f_over_beam": f, "E_sag": sag, "E_freq": f ** -2}
                except Exception as exc:  # noqa: BLE001 - a row
                    r = {"rule": rule, "grid": g, "error": str(exc).splitlines()[0][:120]}
            r.update({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "E": a.E})
            rows.append(r)
            print(json.dumps(r), flush=True)
            if a.json:
                with open(a.json, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
    simulation.PIN_RULE = RULES["default"]
    print("| rule | grid | sag / beam | f / beam | E a fit needs / true (sag, freq) | vs the finest grid of the rule (sag, freq) |")
    print("|---|---:|---:|---:|---|---|")
    for r in rows:
        if "sag_over_beam" not in r:
            print(f"| {r['rule']} | {r['grid']} | {r.get('error')} | | | |")
            continue
        fine = max((q for q in rows if q["rule"] == r["rule"] and "sag_over_beam" in q), key=lambda q: q["grid"])
        print(f"| {r['rule']} | {r['grid']} | {r['sag_over_beam']:.3f} | {r['f_over_beam']:.3f} | {r['E_sag']:.2f}, {r['E_freq']:.2f} "
              f"| {r['sag_over_beam'] / fine['sag_over_beam']:.2f}, {(fine['f_over_beam'] / r['f_over_beam']) ** 2:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
