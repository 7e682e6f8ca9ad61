"""`physinteract-usd fit`: fit the material field and the trajectory (the verb: `physinteract_usd.app.fit`)."""

from __future__ import annotations

import json

from ..errors import InputError
from .common import progress_log


def add_parser(sub):
    s = sub.add_parser("fit", help="fit the material field and the trajectory to the video")
    s.add_argument("stage")
    s.add_argument("--iterations", type=int, default=None,
                   help="optimiser iterations (default 60; 20 for a warm start after `effects add/remove`; with "
                        "--resume after a killed fit: the ones it had left)")
    s.add_argument("--no-joint", action="store_true",
                   help="keep the trajectory at its initialisation T0 (the paper's w/o JO ablation)")
    s.add_argument("--contact-from", metavar="DIR/gt", help="take contacts, supports and T0 from a synthetic "
                   "capture's ground truth instead of the stage / extraction")
    s.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    s.add_argument("--seed", type=int, default=0, help="random seed (runs are repeatable)")
    s.add_argument("--resume", action="store_true", help="go on from a stopped fit's checkpoint, else from the "
                   "newest version")
    s.add_argument("--fresh", action="store_true", help="fit from scratch even when the effects changed since the "
                   "current version (default: a refit after `effects add/remove` warm-starts from it)")
    s.add_argument("--warm-path", default="both", choices=("both", "fitted", "measured"),
                   help="a warm start after `effects add`: the hand paths from the current version (fitted), from the "
                        "measured ones (measured: the current path may have soaked up the effect just added) or "
                        "both, the lower final loss kept (default; twice the refit)")
    kb = s.add_mutually_exclusive_group()
    kb.add_argument("--keep-best", dest="keep_best", action="store_true", default=True,
                    help="the new version becomes current only if its loss is below the current one's (default)")
    kb.add_argument("--no-keep-best", dest="keep_best", action="store_false",
                    help="the new version becomes current (unless it was interrupted and the current one is complete)")
    s.add_argument("--checkpoint-every", type=int, default=5, metavar="N",
                   help="write the best iterate to <stem>.versions/checkpoint.npz every N iterations, for --resume "
                        "after a kill (default 5; 0: never)")
    s.add_argument("--yes", action="store_true", help="go on even when the fit is estimated to take hours")
    s.add_argument("--appearance", type=float, default=None, metavar="W",
                   help="weight of the appearance prior (material parts follow colour edges; default 1, "
                        "0 turns it off, with the smoothness back to its weak edge-blind 0.02: for objects whose "
                        "colour says nothing about their material)")
    s.add_argument("--schedule", choices=("bumps", "select", "ladder"), default=None,
                   help="the fit's schedule (default bumps): select = a dense uniform-E sweep, then the uniform "
                        "model vs the bumps field chosen on held-back frames; ladder = uniform then regions")
    s.add_argument("--patience", type=int, default=None, metavar="N",
                   help="convergence stop: a level of the schedule ends when its last N iterations bring no new "
                        "best loss 0.5%% below the one before (default 3; 0: every iteration runs)")
    s.add_argument("--track-weight", type=float, default=None, metavar="W",
                   help="weight of the point-track term: the video's 2D point tracks (OpenCV DIS flow, the report's, "
                        "cached) against the projected Gaussians, beside pixels and silhouette (default 0: off; "
                        "1: a 1-px error on every track costs about a 1-px shift of the outline)")
    s.add_argument("--starts", type=int, default=1, metavar="N",
                   help="fit from N starts (the searched uniform E x 1, 0.71, 0.5, 0.35, ...: none stiffer than x1, so "
                        "batched they keep its substep; each with its own seed) and "
                        "keep the lowest loss; every start's loss goes into the version's JSON. With --device cuda the "
                        "starts run batched (one tiled rollout per iteration; 4 starts of a small scene: predicted ~2x one "
                        "fit's time, docs/benchmarks/gpu.md); on the CPU one after another, N times one fit "
                        "(tiling saves ~20%% there at best, and loses when the stiffest start needs more substeps). "
                        "Bumps schedule only; default 1")
    s.add_argument("--guard", action="store_true",
                   help="bumps schedule: fit the field and the uniform model on training frames and return the field "
                        "only if its loss on the held-back frames is clearly lower (else one E, the field recorded as "
                        "rejected); about 1.1-1.4x the fit's time (#24)")
    s.add_argument("--unconstrained-floor", type=float, default=None, metavar="F",
                   help="after the fit, mark the particles strained less than F x the median over the clip (and the "
                        "held ones) as unconstrained: confidence 0, E from the material they are attached to (0.1 is "
                        "select.EXPOSURE_FLOOR; default 0: off)")
    s.add_argument("--gauss-newton", type=int, default=None, metavar="N",
                   help="bumps schedule: N Gauss-Newton steps on the finest level's bump amplitudes before its Adam "
                        "iterations (K+2..K+5 forward simulations each, charged to the iteration budget; default 0: "
                        "off; #24)")
    s.add_argument("--parts-start", type=int, default=None, metavar="N",
                   help="bumps schedule: start the finest level from the colour parts' E (or the shape's thin and "
                        "thick parts where the colours make no regions: --no-shape-parts), found by a simplex of at "
                        "most N forward probes from the uniform E (on the CPU 3 per part + 3 below N: 9-11 for two "
                        "parts, stopped early when it stalls; on a GPU all N, and on while it still descends, up to 3N; charged to the iteration budget when "
                        "taken; 0 turns it off; default: 20 on a GPU (the suite's 12 scenes: mean MA 0.40 -> 0.51, "
                        "none lower), off on the CPU (the demo's fit ~+16-20 CPU s for no MA); #24)")
    s.add_argument("--trend-start", type=int, default=None, metavar="N",
                   help="bumps schedule: start the finest level from E graded "
                        "log-linearly along one of the object's axes (gravity's, principal ones) when that beats one E "
                        "on held-back frames; a screen of 4-6 probes per axis, then a simplex of at most N; charged "
                        "to the iteration budget when taken; 0 turns it off; default: 20 on a GPU (the suite's 12 "
                        "scenes: mean MA 0.58 -> 0.63; the paper-size scene 0.82 -> 1.00), off on the CPU; #24)")
    s.add_argument("--no-shape-parts", action="store_true",
                   help="bumps schedule: the parts start uses colour parts only; by default, where the colours make "
                        "no regions (one colour, or a pattern), it takes the shape's thin and thick parts instead "
                        "(a glove's fingers and palm: the suite's glove 0.27 -> 0.87 on a GPU; #24)")
    s.add_argument("--starts-order", choices=("screened", "parts-first"), default=None,
                   help="bumps schedule, where both starts run (a GPU's default): 'screened' (the default) screens both "
                        "on the training frames and runs the lower one's simplex first, the other's only where it is "
                        "not taken, the parts start judged on held-back frames and nested; 'parts-first' runs the "
                        "parts start (projected onto the bumps) then the trend start (#24, #26)")
    s.add_argument("--nuisance-damping", action="store_true",
                   help="fit a global damping c (1/s) jointly with E though the stage has no damping effect: the "
                        "dissipation the video has and the model lacks goes into c, not E; recorded in the version's "
                        "settings, the stage's effects untouched; diagnose then does not test damping (opt-in; #24)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    return s


def run(a) -> int:
    from .. import api

    log = progress_log(a.json)
    if a.iterations is not None and a.iterations < 1:
        raise InputError("--iterations", f"must be at least 1, got {a.iterations}")
    if a.checkpoint_every < 0:
        raise InputError("--checkpoint-every", f"must be >= 0, got {a.checkpoint_every}")
    if a.appearance is not None and not a.appearance >= 0:
        raise InputError(a.stage, f"--appearance must be >= 0, got {a.appearance}")
    over = {"appearance": a.appearance} if a.appearance is not None else {}
    if a.schedule is not None:
        over["schedule"] = a.schedule
    if a.patience is not None:
        if a.patience < 0:
            raise InputError("--patience", f"must be >= 0, got {a.patience}")
        over["plateau_patience"] = a.patience
    if a.track_weight is not None:
        if not a.track_weight >= 0:
            raise InputError("--track-weight", f"must be >= 0, got {a.track_weight}")
        over["track_weight"] = a.track_weight
    if a.guard:
        if (a.schedule or "bumps") != "bumps" or a.starts > 1:
            raise InputError("--guard", "guards the bumps schedule's single fit (not --schedule select / ladder, "
                             "not --starts > 1)")
        over["uniform_guard"] = True
    if a.unconstrained_floor is not None:
        if not 0 <= a.unconstrained_floor < 1:
            raise InputError("--unconstrained-floor", f"must be in [0, 1), got {a.unconstrained_floor}")
        over["unconstrained_floor"] = a.unconstrained_floor
    for flag, given, key in (("--gauss-newton", a.gauss_newton, "gn_steps"), ("--parts-start", a.parts_start, "parts_start"),
                             ("--trend-start", a.trend_start, "trend_start")):
        if given is not None:
            if given < 0:
                raise InputError(flag, f"must be >= 0, got {given}")
            over[key] = given
    if a.nuisance_damping:
        over["nuisance_damping"] = True
    if a.starts_order is not None:
        over["starts_order"] = a.starts_order.replace("-", "_")
    if a.no_shape_parts:
        over["parts_by_shape"] = False
    over = over or None
    outcome = api.fit(a.stage, iterations=a.iterations, joint=not a.no_joint, contact_from=a.contact_from,
                      device=a.device, seed=a.seed, resume=a.resume, log=log, settings_overrides=over,
                      keep_best=a.keep_best, checkpoint_every=a.checkpoint_every, yes=a.yes, warm=not a.fresh,
                      starts=a.starts, warm_path=getattr(a, "warm_path", "both"))
    summary = outcome.summary()
    if a.json:
        print(json.dumps(summary, indent=2))
    else:
        stopped = (f" (stopped by {summary['stopped_by']}: best iterate kept)" if summary["stopped_by"]
                   else " (interrupted: best iterate kept)" if summary["interrupted"] else "")
        print(f"fit v{summary['version']} written to {summary['layer']}{stopped}")
        cur = summary["current_version"]
        if summary["is_current"]:
            print(f"  v{summary['version']} is now current: {summary['current_reason']}")
        else:
            print(f"  v{summary['version']} is kept as a version ({summary['snapshot']}); v{cur} stays current: "
                  f"{summary['current_reason']}")
        print(f"  {summary['iterations']} iterations in {summary['runtime_s']:.0f} s on {summary['device']}, "
              f"loss {summary['final_loss']:.5f}")
        print(f"  PSNR {summary['psnr']:.2f} dB (masked {summary['psnr_masked']:.2f}), SSIM {summary['ssim']:.3f}, "
              f"IoU {summary['iou']:.3f}")
        e = summary["youngs_modulus_pa"]
        conf = (f"mean confidence {summary['confidence_mean']:.2f}" if summary["confidence_estimated"]
                else "confidence not estimated (stopped)")
        print(f"  E {e['min']:.3g} .. {e['max']:.3g} Pa (median {e['median']:.3g}), {conf}")
        said = (summary.get("identifiability") or {}).get("sentence")
        if said:
            print(f"  {said}")
        pre = summary.get("preload")
        if pre:
            print(f"  {pre['reason']}")
    return 130 if summary["interrupted"] or summary["stopped_by"] else 0
