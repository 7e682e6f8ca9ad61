"""`physinteract-usd` command line: a thin front end over `physinteract_usd.api`.

Exit codes: 0 success, 2 bad input (one line on stderr naming the file and the problem),
3 a simulation that went unstable (what to change is in the message), 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys

from . import __version__
from .errors import InputError, SimulationError


def _positive_float(s: str) -> float:
    v = float(s)
    if not v > 0:
        raise argparse.ArgumentTypeError("must be positive")
    return v


def _e_range(s: str):
    try:
        lo, hi = (float(x) for x in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected MIN,MAX in Pa, e.g. 1e3,1e6") from None
    return lo, hi


class _Parser(argparse.ArgumentParser):
    """Bad flags are one line on stderr (exit 2), like every other bad input; `-h` shows the usage."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="physinteract-usd",
                                description="Fit a simulation-ready digital twin of a soft object from a "
                                            "video of a hand handling it, stored in OpenUSD.")
    p.add_argument("--version", action="version", version=f"physinteract-usd {__version__}")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")

    s = sub.add_parser("init", help="build a stage from a capture folder (object, video, camera, masks)")
    s.add_argument("stage", help="root layer to write, e.g. scene.usda")
    s.add_argument("--capture", metavar="DIR", help="capture folder (object.*, frames/ or video.mp4, "
                   "masks/, transforms.json)")
    s.add_argument("--object", metavar="FILE", help="3DGS PLY or mesh (overrides the folder's)")
    s.add_argument("--video", metavar="FILE|DIR", help="video file or folder of frames")
    s.add_argument("--camera", metavar="FILE", help="nerfstudio transforms.json")
    s.add_argument("--masks", metavar="DIR", help="folder of object silhouettes, one per frame")
    s.add_argument("--masks-amodal", action="store_true",
                   help="the masks include the object behind the hand (default: visible only)")
    s.add_argument("--fps", type=_positive_float, help="frame rate, when neither transforms.json nor "
                   "the video gives one")
    s.add_argument("--grid", type=int, default=32, help="MPM grid cells along the longest side of the "
                   "domain (default 32; the paper uses 100)")
    s.add_argument("--padding", type=float, default=0.5, help="domain margin around the object, as a "
                   "fraction of its extent (default 0.5)")
    s.add_argument("--youngs-range", type=_e_range, default=(1e3, 1e6), metavar="MIN,MAX",
                   help="Young's modulus range in Pa the fit may use (default 1e3,1e6); MAX sets the substep")
    s.add_argument("--poisson", type=float, default=0.3, help="starting Poisson ratio (default 0.3)")
    s.add_argument("--max-poisson", type=float, default=0.45,
                   help="largest Poisson ratio the fit may use (default 0.45); it sets the substep with E max")
    s.add_argument("--spacing", type=_positive_float, help="particle spacing in metres (default: half a grid cell)")
    s.add_argument("--density", type=_positive_float, default=1000.0, help="density in kg/m^3 (default 1000)")
    s.add_argument("--model", choices=["fixedCorotated", "neoHookean"], default="fixedCorotated",
                   help="constitutive model (default fixedCorotated)")
    s.add_argument("--force", action="store_true",
                   help="replace the generated layers of an existing stage (your root layer is kept)")

    s = sub.add_parser("synth", help="write a synthetic capture folder with ground truth (gt/)")
    s.add_argument("name", nargs="?", help="scene name (see --list)")
    s.add_argument("out_dir", nargs="?", help="capture folder to write")
    s.add_argument("--list", action="store_true", help="list the scenes")
    s.add_argument("--size", choices=["small", "paper"], default="small",
                   help="small: CPU-sized (default); paper: the paper's scale")
    s.add_argument("--frames", type=int, help="number of frames (default: the size's)")
    s.add_argument("--hidden", choices=["damping", "plasticity", "ground", "viscoelasticity"],
                   help="switch on an effect the model will not be told about")
    s.add_argument("--strength", type=float, default=1.0,
                   help="hidden effect strength, in multiples of the 0.5 px noise level (default 1)")
    s.add_argument("--noise", type=float, help="sensor noise sigma (default 0; 0.015 for real stand-ins)")
    s.add_argument("--blur", type=int, help="motion-blur samples per frame (default 1; 3 for real stand-ins)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--device", default="cpu", help="cpu or cuda")
    s.add_argument("--force", action="store_true", help="replace an existing synth folder")

    s = sub.add_parser("extract", help="find the hand's contact, timing, type, supports and initial trajectory")
    s.add_argument("stage")
    s.add_argument("--type", choices=["pointAdherent", "pointNonAdherent", "surfaceNonAdherent"],
                   help="the interaction type (overrides detection)")
    s.add_argument("--hint-pixel", metavar="K,U,V", help="the contact is at pixel column U, row V of frame K")
    s.add_argument("--hint-particles", metavar="I,J,...", help="the contact holds these particles")
    s.add_argument("--support-pixel", metavar="K,U,V", action="append",
                   help="the object is held still at pixel column U, row V of frame K (repeat for several "
                        "supports): keeps the still region detected there, or holds the particles within 3 cm of "
                        "that point; detected supports elsewhere are dropped")
    s.add_argument("--support-particles", metavar="I,J,...", help="these particles are held still (the one "
                   "support; replaces the detected ones)")
    s.add_argument("--grasp-radius", type=float, metavar="R", help="the hand holds the particles within R metres "
                   "of the contact (a fingertip's radius for a poke); the video shows where the hand grasps, not "
                   "how much it holds (default: a 3 cm pinch, more when the contact region is larger)")
    s.add_argument("--no-preview", action="store_true", help="skip the preview PNG")
    s.add_argument("--device", default="cpu", help="cpu or cuda (rendering the object's depth; default cpu)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")

    s = sub.add_parser("fit", help="fit the material field and the trajectory to the video")
    s.add_argument("stage")
    s.add_argument("--iterations", type=int, default=60, help="optimiser iterations (default 60)")
    s.add_argument("--no-joint", action="store_true",
                   help="keep the trajectory at its initialisation T0 (the paper's w/o JO ablation)")
    s.add_argument("--contact-from", metavar="DIR/gt", help="take contacts, supports and T0 from a synthetic "
                   "capture's ground truth instead of the stage / extraction")
    s.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    s.add_argument("--seed", type=int, default=0, help="random seed (runs are repeatable)")
    s.add_argument("--resume", action="store_true", help="start from the stage's last fit")
    s.add_argument("--appearance", type=float, default=None, metavar="W",
                   help="weight of the appearance prior (material parts follow colour edges; default 1, "
                        "0 turns it off, with the smoothness back to its weak edge-blind 0.02: for objects whose "
                        "colour says nothing about their material)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")

    s = sub.add_parser("evaluate", help="score a fitted stage against synthetic ground truth")
    s.add_argument("stage")
    s.add_argument("--gt", required=True, metavar="DIR/gt", help="the synth capture's gt/ folder")
    s.add_argument("--device", default="cpu", help="cpu or cuda (rendering)")
    s.add_argument("--json", action="store_true", help="print JSON")

    from .api import INTERACTION_DOC

    s = sub.add_parser("simulate", help="re-simulate the fitted object under a new interaction",
                       epilog=INTERACTION_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("stage")
    s.add_argument("--interaction", required=True, metavar="SPEC.json", help="the new interaction (see below)")
    s.add_argument("--name", help="name of the simulation (default: the spec's name or file stem)")
    s.add_argument("--device", default="cpu")

    s = sub.add_parser("export", help="write a self-contained simulation-ready asset (flattened USD)")
    s.add_argument("stage")
    s.add_argument("out", help="OUT.usd, .usdc, .usda or .usdz")
    s.add_argument("--ply-sequence", metavar="DIR", help="also write one 3DGS PLY per frame into DIR")

    s = sub.add_parser("info", help="summarise a stage")
    s.add_argument("stage")
    s.add_argument("--json", action="store_true", help="print JSON")
    return p


def _cmd_init(a) -> int:
    from . import api

    if a.capture is None and (a.object is None or a.video is None or a.camera is None):
        raise InputError(a.stage, "give --capture DIR, or all of --object, --video and --camera")
    lp = api.init(a.stage, a.capture, object=a.object, video=a.video, camera=a.camera, masks=a.masks,
                  fps=a.fps, masks_amodal=a.masks_amodal, grid=a.grid, padding=a.padding,
                  youngs_range=a.youngs_range, poisson=a.poisson, density=a.density,
                  constitutive_model=a.model, max_poisson=a.max_poisson, spacing=a.spacing, force=a.force)
    print(f"wrote {lp.root} (root), {lp.init.name}, {lp.fit.name}")
    print(api.format_info(api.info(lp.root)))
    return 0


def _cmd_info(a) -> int:
    from . import api

    d = api.info(a.stage)
    print(json.dumps(d, indent=2) if a.json else api.format_info(d))
    return 0


def _cmd_synth(a) -> int:
    from .synth import generate, list_scenes

    if a.list:
        for name, paper, kind, desc in list_scenes():
            print(f"{name:16s} {kind:19s} {paper}: {desc}")
        return 0
    if not a.name or not a.out_dir:
        raise InputError("synth", "give NAME OUT_DIR (or --list)")
    generate(a.name, a.out_dir, size=a.size, frames=a.frames, hidden=a.hidden, strength=a.strength,
             noise=a.noise, blur=a.blur, seed=a.seed, device=a.device, force=a.force)
    return 0


def _cmd_extract(a) -> int:
    from .extract import extract, parse_hint

    log = (lambda m: print(m, file=sys.stderr)) if a.json else print
    r = extract(a.stage, hint=parse_hint(a.hint_pixel, a.hint_particles, a.support_pixel, a.support_particles,
                                           a.grasp_radius), interaction_type=a.type,
                preview=not a.no_preview, log=log, device=a.device)
    if a.json:
        print(json.dumps(r.summary(), indent=2, default=str))
    return 0


def _cmd_fit(a) -> int:
    from . import api

    log = (lambda m: print(m, file=sys.stderr)) if a.json else print
    if a.appearance is not None and a.appearance < 0:
        raise InputError(a.stage, f"--appearance must be >= 0, got {a.appearance}")
    over = {"appearance": a.appearance} if a.appearance is not None else None
    result, info = api.fit(a.stage, iterations=a.iterations, joint=not a.no_joint, contact_from=a.contact_from,
                           device=a.device, seed=a.seed, resume=a.resume, log=log, settings_overrides=over)
    import numpy as np

    fm = result.frame_metrics
    summary = {"version": info["version"], "layer": info["layer"], "iterations": len(result.loss_history),
               "final_loss": result.final_loss, "runtime_s": result.runtime_s, "device": result.device,
               "interrupted": result.interrupted,
               "psnr": float(np.mean([min(f["psnr"], 100) for f in fm])),
               "psnr_masked": float(np.nanmean([min(f["psnr_masked"], 100) for f in fm])),
               "ssim": float(np.mean([f["ssim"] for f in fm])), "iou": float(np.mean([f["iou"] for f in fm])),
               "youngs_modulus_pa": {"min": float(result.youngs.min()), "median": float(np.median(result.youngs)),
                                     "max": float(result.youngs.max())},
               "confidence_mean": float(result.confidence.mean())}
    if a.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"fit v{summary['version']} written to {info['layer']}"
              + (" (interrupted: best iterate kept)" if result.interrupted else ""))
        print(f"  {summary['iterations']} iterations in {summary['runtime_s']:.0f} s on {summary['device']}, "
              f"loss {summary['final_loss']:.5f}")
        print(f"  PSNR {summary['psnr']:.2f} dB (masked {summary['psnr_masked']:.2f}), SSIM {summary['ssim']:.3f}, "
              f"IoU {summary['iou']:.3f}")
        e = summary["youngs_modulus_pa"]
        print(f"  E {e['min']:.3g} .. {e['max']:.3g} Pa (median {e['median']:.3g}), mean confidence "
              f"{summary['confidence_mean']:.2f}")
    return 130 if result.interrupted else 0


def _cmd_evaluate(a) -> int:
    from . import api

    d = api.evaluate(a.stage, a.gt, device=a.device)
    keys = ("ma", "psnr", "psnr_masked", "ssim", "iou", "position_error_m")
    if a.json:
        print(json.dumps({**{k: d[k] for k in keys}, "ma_best_uniform": d["ma_best_uniform"]}, indent=2))
    else:
        print(f"{'metric':22s} value")
        print(f"{'MA':22s} {d['ma']:.3f}   (best uniform E: {d['ma_best_uniform']:.3f} at {d['best_uniform_e']:.3g} Pa)")
        print(f"{'PSNR':22s} {d['psnr']:.2f} dB")
        print(f"{'PSNR (masked)':22s} {d['psnr_masked']:.2f} dB")
        print(f"{'SSIM':22s} {d['ssim']:.3f}")
        print(f"{'IoU':22s} {d['iou']:.3f}")
        print(f"{'position error':22s} {d['position_error_m'] * 1000:.2f} mm")
    return 0


def _cmd_simulate(a) -> int:
    from . import api

    out = api.simulate(a.stage, a.interaction, name=a.name, device=a.device)
    print(f"simulated {out['frames']} frames: layer {out['layer']}; open {out['stage']} to view it over the fit")
    return 0


def _cmd_export(a) -> int:
    from . import api

    out = api.export(a.stage, a.out, ply_sequence=a.ply_sequence)
    print(f"wrote {out['usd']}" + (f" and {out['ply_frames']} PLY frames in {out['ply_sequence']}"
                                    if "ply_sequence" in out else ""))
    return 0


COMMANDS = {"extract": _cmd_extract, "simulate": _cmd_simulate, "export": _cmd_export, "init": _cmd_init, "info": _cmd_info, "synth": _cmd_synth, "fit": _cmd_fit, "evaluate": _cmd_evaluate}


def _check_device(device) -> None:
    """--device cuda on a machine without a usable GPU: one line, not a traceback."""
    if device is None or str(device) == "cpu":
        return
    if not str(device).startswith("cuda"):
        raise InputError("--device", f"must be cpu or cuda, not {device!r}")
    import torch

    if not torch.cuda.is_available():
        raise InputError("--device", "cuda was asked for, but this torch has no usable CUDA GPU: use --device cpu")


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        _check_device(getattr(args, "device", None))
        return COMMANDS[args.verb](args)
    except InputError as exc:
        print(f"physinteract-usd {args.verb}: error: {exc.oneline()}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        print(f"physinteract-usd {args.verb}: {exc}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(f"physinteract-usd {args.verb}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
