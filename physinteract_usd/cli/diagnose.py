"""`physinteract-usd diagnose`: rank what the fitted model lacks (the verb:
`physinteract_usd.app.diagnose`)."""

from __future__ import annotations

import json


def add_parser(sub):
    s = sub.add_parser("diagnose", help="rank what the fitted model lacks: effects, material freedom, interaction",
                       description="Rank what the stage's fitted model lacks by the loss drop each candidate would "
                                   "bring (a projected score test at the fit, significance by block sign flips): "
                                   "the effects damping, plasticity, ground, viscoelasticity; heterogeneity; and "
                                   "the non-physical causes interaction:timing, interaction:contact, "
                                   "interaction:grasp_size, interaction:support, camera:time_offset, "
                                   "camera:depth_scale (with the flag that fixes each). The top candidates are "
                                   "refitted briefly and kept only if the loss on held-back frames falls.")
    s.add_argument("stage")
    s.add_argument("--refit", type=int, default=3, metavar="N",
                   help="refit the top N significant candidates briefly (default 3; 0: none)")
    s.add_argument("--refit-iterations", type=int, default=8, metavar="K", help="iterations of each refit (default 8)")
    s.add_argument("--refit-folds", type=int, default=None, metavar="K",
                   help="2 (default): each refit is trained on one half of the frames and judged on the other, "
                        "both ways, and the paired test pools both; 1: one split (half the refit time, less power)")
    s.add_argument("--candidates", metavar="A,B,...", help="test only these candidates (default: all)")
    s.add_argument("--starts", type=int, default=3, metavar="N",
                   help="base starts before scoring: 1 scores the fit as it is; 3 (default) first refits the base "
                        "briefly from its own E field, x 0.5 and x 2 and scores against the best (a local minimum "
                        "or an unconverged fit is not missing physics; says so); 2: own and x 0.5. The starts "
                        "about double the CPU time on the tests' tiny bar (9 -> 19 s a control)")
    s.add_argument("--trajectory-sigma", type=float, default=None, metavar="PX",
                   help="the measured hand path's pixel uncertainty that bounds its freedom (default 2, the fit's)")
    s.add_argument("--floor-rule", nargs="?", const="full", default=False, choices=("full", "match", "rest"),
                   help="model the fit's own error instead of gating on size (opt-in, docs/diagnose.md): the "
                        "superset simulator steps as the fitted model did, the rendering's floor (fitted on the "
                        "rest frames) and the model's discretisation error are projected out, and no 3%% size "
                        "gate; 'match': only the first of the three, no size gate; 'rest': matched, the camera "
                        "causes judged on the frames before the first grasp only, heterogeneity priced as the "
                        "fit's model selection, no size gate")
    s.add_argument("--gate", type=float, default=None, metavar="SHARE",
                   help="the size gate: the share of the loss a significant candidate must predict (default 0.03, "
                        "0 under --floor-rule where refits confirm)")
    s.add_argument("--resolution", nargs="?", const="2,3", default=None, metavar="A[,B]|off",
                   help="weigh the fit's own resolution error in the verdict: the fitted model simulated on grids A "
                        "and B times finer (2,3 when given alone), Richardson's estimate of what the grid costs the "
                        "fit added to the rest frame's floor before a residual is called unexplained; one split A: "
                        "its change at an assumed order (first: 1). Default: 2,3 with --device cuda (seconds), 2 on the "
                        "CPU (~16x a forward; 2,3 would be ~100x); 'off' turns it off")
    s.add_argument("--no-stage", action="store_true", help="do not store the diagnosis in the fit layer")
    s.add_argument("--device", default="cpu", help="cpu or cuda")
    s.add_argument("--json", action="store_true", help="print the diagnosis as JSON")
    return s


def run(a) -> int:
    import sys

    from .. import api

    d = api.diagnose(a.stage, refit=a.refit, refit_iterations=a.refit_iterations, candidates=a.candidates,
                     write_stage=not a.no_stage, device=a.device, starts=a.starts,
                     trajectory_sigma_px=a.trajectory_sigma, refit_folds=a.refit_folds, floor_rule=a.floor_rule, gate=a.gate, resolution=a.resolution,
                     progress=not a.json and sys.stderr.isatty(),
                     log=(lambda *m: print(*m, file=sys.stderr)) if a.json else print)
    if a.json:
        print(json.dumps(d, indent=1, allow_nan=False))
        return 0
    print(f"{d['verdict'].upper()}: {d['reason']}")
    if d["candidates"]:
        print(f"{'#':>2} {'candidate':24} {'score':>6} {'predicted':>10} {'realised':>10}  estimate")
        for i, c in enumerate(d["candidates"], 1):
            r = "-" if c["realized_loss_drop"] is None else f"{c['realized_loss_drop']:.3g}"
            est = ", ".join(f"{k}={_fmt(v)}" for k, v in (c["estimate"] or {}).items())
            print(f"{i:2d} {c['effect']:24} {c['score']:6.2f} {c['predicted_loss_drop']:10.3g} {r:>10}  {est}")
            if c["evidence"]:
                print(f"   {c['evidence']}")
    cf = d.get("confusable")
    if cf:
        print(f"CONFUSABLE: {cf['verdict']}")
        for e in cf["pair"]:
            ev = cf["evidence"][e]
            print(f"  {e}: held-back drop {_fmt(ev['held_back_drop'])} +- {_fmt(ev['held_back_se'])} "
                  f"(p {_fmt(ev['held_back_p'])}); " + ", ".join(f"{k}={_fmt(v)}" for k, v in ev["estimate"].items()))
        print(f"  what would tell them apart: {cf['to_separate']}")
        print(f"  to lower the error now: physinteract-usd effects add {d.get('stage', 'scene.usda')} {cf['add']} "
              f"({cf['add_why']})")
    for n in d.get("notes") or []:
        print(f"note: {n}")
    print(f"tested: " + ", ".join(f"{t['effect']} (p {t['marginal_p_value']:.2g})" for t in d["tested"]))
    if d.get("stage_layer"):
        print(f"stored in: {d['stage_layer']}")
    return 0


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list):
        return "(" + ", ".join(_fmt(x) for x in v) + ")"
    return str(v)
