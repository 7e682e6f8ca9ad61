"""The parts start's simplex, probe by probe (#24): from one and the same state (the bumps fit's field and path just
before its finest level, true contacts), each simplex variant's probes in order with their loss and the parts' E,
and the MA of the parts field it ends at (per Gaussian, as `evaluate`); then the fit goes on with the variant
`--apply` names (its simplex run again, the same probes, through `fit/parts_start.parts_start`: the code's own rule
for taking the start and charging its probes) and its final MA is printed; none: the default fit (no start);
--trace-only stops after the traces.

Variants (name -> `select.part_refine` arguments): p20 = the 20-probe start of code f6a2cc6 (one-sided first
simplex x2, no stall stop, 20 probes); cheap = code acf1acc's (3 (m + 1) probes capped by the cap, two-sided,
stall window m + 1); now / cuda = what `parts_start` does at this commit on the CPU / on CUDA (whatever the device
the script runs on: the variants are compared from one state).

    python benchmarks/parts_simplex_trace.py STAGE GT_DIR [--iterations 20] [--cap 20] [--variants p20,cheap,now]
        [--apply now|none] [--trace-only] [--contacts gt|stage] [--device cpu] [--out rows.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


class _Done(Exception):
    pass


def variant_kwargs(name: str, m: int, cap: int) -> dict:
    """A variant's `part_refine` arguments; "now:key=json,key=json" (or "cheap:...") overrides some of them
    (bracket, stall_after_simplex, evals, stall=[k, tol], two_sided, step)."""
    from physinteract_usd.fit import parts_start as ps

    if ":" in name:
        base, rest = name.split(":", 1)
        kw = variant_kwargs(base, m, cap)
        for item in rest.split(";"):
            k, v = item.split("=", 1)
            val = json.loads(v)
            kw[k] = tuple(val) if k == "stall" and val is not None else val
        return kw

    if name == "p20":
        return dict(evals=max(cap, m + 2), step=ps.SIMPLEX_STEP)
    if name == "cheap":
        return dict(evals=max(min(cap, 3 * (m + 1)), m + 2), step=ps.SIMPLEX_STEP, stall=(m + 1, ps.STALL_TOL),
                    two_sided=True)
    if name == "now":                       # this code's rule on the CPU
        return ps.refine_kwargs(m, cap)
    if name == "cuda":                      # ... and on CUDA (the cap's probes, no stall stop)
        return ps.refine_kwargs(m, cap, cheap=False)
    raise SystemExit(f"--variants: unknown variant {name!r} (p20, cheap, now, cuda)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--cap", type=int, default=20, help="--parts-start N")
    ap.add_argument("--variants", default="p20,cheap,now", help="comma-separated; a variant may override arguments: "
                    "'now:bracket=false;stall_after_simplex=true'")
    ap.add_argument("--apply", default="now", help="p20 | cheap | now: the fit goes on from that variant's start "
                    "(the code's take rule); none: no start")
    ap.add_argument("--trace-only", action="store_true")
    ap.add_argument("--contacts", default="gt", choices=("gt", "stage"),
                    help="gt: the truth's contacts (GT_DIR); stage: those on the stage (e.g. the demo's extraction)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from physinteract_usd import metrics as M
    from physinteract_usd.app.fit import make_problem, prepare_fit
    from physinteract_usd.fit.optimize import fit_bumps, gaussian_weights
    from physinteract_usd.fit.parts_start import parts_start
    from physinteract_usd.fit.select import PartProbe, part_candidates, part_refine
    from physinteract_usd.fit.substep import kept_rung
    from physinteract_usd.synth.gt import read_gt_array

    over = {"schedule": "bumps", "parts_start": a.cap}
    job = prepare_fit(a.stage, iterations=a.iterations, contact_from=a.gt if a.contacts == "gt" else None,
                      device=a.device, warm=False,
                      progress=False, log=lambda m: None, settings_overrides=over)
    prob = make_problem(job)
    s = job.settings
    e_gt = np.asarray(read_gt_array(a.gt, "youngs_modulus.npy"), np.float64)
    feats = prob.particle_appearance() if s.appearance > 0 else None
    w, idx = gaussian_weights(prob, feats)

    def ma(E):
        return M.material_accuracy(np.exp((w * np.log(np.asarray(E, np.float64))[idx]).sum(1)), e_gt)

    report = {"stage": a.stage, "cap": a.cap, "iterations": a.iterations, "variants": {}}

    def hook(prob_, mat, s_, trajs, eff, total_fn, log=None):
        cands = [c for c in part_candidates(prob_, s_, None) if c["kind"] == "appearance" and c["parts"] > 1]
        if not cands:
            print("one colour part: nothing to trace", flush=True)
            raise _Done
        labels = cands[0]["labels"]
        m = int(labels.max()) + 1
        with torch.no_grad():
            le_now = mat.log_e().detach().cpu().numpy()
            nu = mat.poisson().detach()
        start = np.array([float(np.mean(le_now[labels == j])) for j in range(m)])
        sizes = np.bincount(labels, minlength=m).tolist()
        report.update(parts=m, part_particles=sizes, start_e=np.exp(start).tolist(), start_ma=ma(np.exp(start)[labels]))
        print(f"{m} parts ({sizes} particles), start E {np.round(np.exp(start), 1).tolist()}, "
              f"the uniform start's MA {report['start_ma']:.3f}", flush=True)
        tr = [t.detach() for t in trajs] if trajs else None
        for v in [x for x in a.variants.split(",") if x]:
            f = PartProbe(prob_, list(range(1, prob_.T)), labels, nu, tr, eff, batch=s_.select_sweep_batch)
            t0 = time.process_time()
            with kept_rung(prob_):
                r = part_refine(f, start, mat.lo + 1e-3, mat.hi - 1e-3, **variant_kwargs(v, m, a.cap))
            cpu = time.process_time() - t0
            trace = [(float(val), np.exp(np.asarray(k)).round(1).tolist()) for k, val in f.cache.items()]
            l0 = trace[0][0]
            best = math.inf
            print(f"\n[{v}] {len(trace)} forwards, {cpu:.1f} CPU s{', stalled' if r.get('stalled') else ''}", flush=True)
            for i, (val, e) in enumerate(trace):
                mark = " *" if val < best - 1e-12 else ""
                best = min(best, val)
                print(f"  {i + 1:2d} loss {val:.6f} ({100 * (val / l0 - 1):+6.2f}%) E {e}{mark}", flush=True)
            gain = l0 - float(r["loss"])
            first = next((i + 1 for i, (val, _) in enumerate(trace) if l0 - val >= 0.9 * gain), None) if gain > 0 else None
            e_end = np.exp(np.asarray(r["log_e"], np.float64))
            out = {"forwards": len(trace), "stalled": bool(r.get("stalled", False)), "loss0": l0,
                   "loss": float(r["loss"]), "gain": gain, "gain_share": gain / l0, "e": e_end.tolist(),
                   "ma_parts": ma(e_end[labels]), "probe_reaching_90pct_gain": first, "cpu_s": round(cpu, 1),
                   "trace": trace}
            report["variants"][v] = out
            print(f"  -> E {np.round(e_end, 1).tolist()}, gain {100 * gain / l0:.2f}% of the loss, 90% of it by "
                  f"probe {first}; the parts field's MA {out['ma_parts']:.3f}", flush=True)
        if a.trace_only:
            raise _Done
        if a.apply == "none":            # the default fit (the traces left the field and the rung as they were)
            return {"forwards": 0, "used": False, "parts": m}
        return parts_start(prob_, mat, s_, trajs, eff, total_fn, a.cap, log,
                           refine=lambda m: variant_kwargs(a.apply, m, a.cap))

    t0 = time.process_time()
    try:
        r = fit_bumps(prob, s, progress=False, log=lambda m: print("  log:", m, flush=True), before_finest=hook)
        report["fit"] = {"ma": ma(r.youngs), "final_loss": r.final_loss, "parts_start": r.model.get("parts_start"),
                         "cpu_s": round(time.process_time() - t0, 1)}
        print(f"\nfit with the start ({a.apply}): MA {report['fit']['ma']:.3f}, final loss {r.final_loss:.6f}, "
              f"{report['fit']['cpu_s']} CPU s", flush=True)
    except _Done:
        pass
    if a.out:
        Path(a.out).write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
