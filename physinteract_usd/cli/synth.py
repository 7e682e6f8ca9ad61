"""`physinteract-usd synth`: write a synthetic capture with ground truth (the verb: `physinteract_usd.app.synth`)."""

from __future__ import annotations

from ..errors import InputError


def add_parser(sub):
    s = sub.add_parser("synth", help="write a synthetic capture folder with ground truth (gt/)")
    s.add_argument("name", nargs="?", help="scene name (see --list)")
    s.add_argument("out_dir", nargs="?", help="capture folder to write")
    s.add_argument("--list", action="store_true", help="list the scenes")
    s.add_argument("--random", type=int, metavar="SEED", help="a randomised world capture of the dev split "
                   "(synth --random SEED OUT_DIR): object, material, support or floor, toucher, camera, light, noise "
                   "and compression drawn from the seed")
    s.add_argument("--validation", type=int, metavar="SEED", help="a world capture of the validation split "
                   "(synth --validation SEED OUT_DIR): never tune anything on it; its folder carries the split's "
                   "marker, which tuning tools refuse")
    s.add_argument("--size", choices=["small", "paper"], default="small",
                   help="small: CPU-sized (default); paper: the paper's scale")
    s.add_argument("--frames", type=int, help="number of frames (default: the size's)")
    s.add_argument("--hidden", choices=["damping", "plasticity", "ground", "viscoelasticity"],
                   help="switch on an effect the model will not be told about")
    s.add_argument("--strength", type=float, default=1.0,
                   help="hidden effect strength (default 1): with --calibrate particles, multiples of the 0.5 px "
                        "noise level; with --calibrate frames, the frames' mean squared change over the noise variance")
    s.add_argument("--calibrate", choices=["particles", "frames"], default="particles",
                   help="how --strength sets the hidden effect: particles (default; RMS projected particle "
                        "displacement = strength x 0.5 px) or frames (the noise-free frames change by strength x "
                        "sigma^2, sigma the --noise or 0.015: at 1 adding the effect halves the loss, issue #22)")
    s.add_argument("--noise", type=float, help="sensor noise sigma (default 0; 0.015 for real stand-ins)")
    s.add_argument("--blur", type=int, help="motion-blur samples per frame (default 1; 3 for real stand-ins)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--fit-grid", type=int, metavar="N",
                   help="the init grid the capture suggests (default 24 small, 100 paper); the ground truth is "
                        "simulated on a cell 0.7x (small) or 0.85x (paper) that grid's, so a larger N makes a "
                        "finer truth, e.g. to compare `init --grid auto` against a truth finer than its grid")
    s.add_argument("--transfer-tau", type=float, default=0.0, metavar="SECONDS",
                   help="simulate the ground truth with the rate transfer at this time constant (docs/sim.md; "
                        "default 0: APIC, whose dissipation grows with the substeps)")
    s.add_argument("--truth-for-auto", type=int, metavar="N",
                   help="world captures: simulate the truth finer than the fit `init --grid auto --max-particles N` "
                        "makes too (default: finer than the suggested grid only, within a CPU's budget; on thin "
                        "objects this costs 3-50x: a GPU's work)")
    add_settle_flags(s, "world captures")
    s.add_argument("--device", default="cpu", help="cpu or cuda")
    s.add_argument("--force", action="store_true", help="replace an existing synth folder")
    return s


def add_settle_flags(parser, what: str) -> None:
    """`--settle` / `--no-settle` (dest `settle`: True, False, or None: as each world seed draws it) for `what`."""
    st = parser.add_mutually_exclusive_group()
    st.add_argument("--settle", dest="settle", action="store_const", const=True, default=None,
                    help=f"{what}: settle the object on its supports (or floor) before frame 0 and write its settled "
                         "shape as the scan, as a real capture is (default: as the seed draws it, settled on 3 of 4; "
                         "docs/benchmarks/world.md)")
    st.add_argument("--no-settle", dest="settle", action="store_const", const=False,
                    help=f"{what}: the object starts at its unsettled rest and may sag before anything touches it")


def run(a) -> int:
    from .. import api

    if a.list:
        for name, paper, kind, desc in api.synth_scenes():
            print(f"{name:16s} {kind:19s} {paper}: {desc}")
        return 0
    if a.random is not None or a.validation is not None:
        if a.random is not None and a.validation is not None:
            raise InputError("--validation", "give --random or --validation, not both")
        if not a.name or a.out_dir:
            raise InputError("synth", "give --random SEED OUT_DIR or --validation SEED OUT_DIR")
        split, seed = ("dev", a.random) if a.random is not None else ("validation", a.validation)
        api.synth(None, a.name, frames=a.frames, random=seed, split=split, device=a.device, force=a.force,
                  size=a.size, hidden=a.hidden, noise=a.noise, blur=a.blur, fit_grid=a.fit_grid,
                  truth_for_auto=a.truth_for_auto, overrides=None if a.settle is None else {"settle": a.settle},
                  transfer_tau=a.transfer_tau, calibrate=a.calibrate)
        return 0
    if not a.name or not a.out_dir:
        raise InputError("synth", "give NAME OUT_DIR (or --list, or --random / --validation SEED OUT_DIR)")
    if a.settle is not None:
        raise InputError("--settle" if a.settle else "--no-settle",
                         "only for world captures (--random / --validation SEED)")
    api.synth(a.name, a.out_dir, size=a.size, frames=a.frames, hidden=a.hidden, strength=a.strength,
              noise=a.noise, blur=a.blur, seed=a.seed, device=a.device, force=a.force, fit_grid=a.fit_grid,
              transfer_tau=a.transfer_tau, calibrate=a.calibrate, truth_for_auto=a.truth_for_auto)
    return 0
