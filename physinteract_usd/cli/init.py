"""`physinteract-usd init`: build a stage from a capture folder (the verb: `physinteract_usd.app.init`)."""

from __future__ import annotations

import argparse

from ..errors import InputError
from .common import e_range, positive_float
from .info import format_info


def add_parser(sub):
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
    s.add_argument("--fps", type=positive_float, help="frame rate, when neither transforms.json nor "
                   "the video gives one")
    s.add_argument("--grid", type=grid_arg, default=32, metavar="N|auto",
                   help="MPM grid cells along the longest side of the domain (default 32; the paper uses 100), "
                   "or 'auto': 4 cells across the object's thinnest part (measured from its fill), at least 24, "
                   "within --max-grid and --max-particles. A part 1-2 cells thick bends wrongly whatever E is; "
                   "auto costs more (more particles and substeps): sized for a GPU. init prints the grid it "
                   "chose and the cells across the thinnest part either way")
    s.add_argument("--max-grid", type=int, default=128, metavar="N",
                   help="with --grid auto: at most N cells along the longest side (default 128)")
    s.add_argument("--max-particles", type=int, default=60_000, metavar="N",
                   help="with --grid auto: at most about N particles (default 60000)")
    s.add_argument("--padding", type=positive_float, default=0.5, help="domain margin around the object, as a "
                   "fraction of its extent (default 0.5)")
    s.add_argument("--youngs-range", type=e_range, default=(1e3, 1e6), metavar="MIN,MAX",
                   help="Young's modulus range in Pa the fit may use (default 1e3,1e6); MAX sets the substep")
    s.add_argument("--poisson", type=float, default=0.3, help="starting Poisson ratio (default 0.3)")
    s.add_argument("--max-poisson", type=float, default=0.45,
                   help="largest Poisson ratio the fit may use (default 0.45); it sets the substep with E max")
    s.add_argument("--spacing", type=positive_float, help="particle spacing in metres (default: half a grid cell)")
    s.add_argument("--density", type=positive_float, default=1000.0, help="density in kg/m^3 (default 1000)")
    s.add_argument("--model", choices=["fixedCorotated", "neoHookean"], default="fixedCorotated",
                   help="constitutive model (default fixedCorotated)")
    s.add_argument("--transfer-tau", type=float, default=0.0, metavar="SECONDS",
                   help="the simulation's rate transfer time constant (docs/sim.md; default 0: APIC, whose "
                        "dissipation grows with the substeps)")
    pre = s.add_mutually_exclusive_group()
    pre.add_argument("--preload", dest="preload", action="store_const", const=True, default=None,
                     help="the scan shows the object carrying its weight (hung on its supports or resting on the "
                          "ground, already sagged): start every simulation prestressed, at rest on its supports, "
                          "instead of stress-free (where it would sag again and the fit stiffen E to stop it). "
                          "Neither this nor --no-preload: the first fit decides by the frames")
    pre.add_argument("--no-preload", dest="preload", action="store_const", const=False,
                     help="the scan is stress-free (the object was scanned unloaded, and sags in the video)")
    s.add_argument("--force", action="store_true",
                   help="replace the generated layers of an existing stage (your root layer is kept)")
    s.add_argument("--discard-fits", action="store_true",
                   help="with --force on a fitted stage: discard its fit versions (scene.versions/) too")
    s.add_argument("--yes", action="store_true",
                   help="go on even when a frame needs so many substeps that fits would take hours")
    return s


def grid_arg(s: str):
    if s.strip().lower() == "auto":
        return "auto"
    try:
        return int(s)
    except ValueError:
        raise argparse.ArgumentTypeError("must be a whole number of cells or 'auto'") from None


def run(a) -> int:
    from .. import api

    if a.capture is None and (a.object is None or a.video is None or a.camera is None):
        raise InputError(a.stage, "give --capture DIR, or all of --object, --video and --camera")
    lp = api.init(a.stage, a.capture, object=a.object, video=a.video, camera=a.camera, masks=a.masks,
                  fps=a.fps, masks_amodal=a.masks_amodal, grid=a.grid, max_grid=a.max_grid,
                  max_particles=a.max_particles, padding=a.padding,
                  youngs_range=a.youngs_range, poisson=a.poisson, density=a.density,
                  constitutive_model=a.model, max_poisson=a.max_poisson, spacing=a.spacing, force=a.force,
                  discard_fits=a.discard_fits, yes=a.yes, transfer_tau=a.transfer_tau,
                  preload=a.preload)
    print(f"wrote {lp.root} (root), {lp.init.name}, {lp.fit.name}")
    print(format_info(api.info(lp.root)))
    return 0
