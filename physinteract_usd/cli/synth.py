"""`physinteract-usd synth`: write a synthetic capture with ground truth (the verb: `physinteract_usd.app.synth`)."""

from __future__ import annotations

from ..errors import InputError


def add_parser(sub):
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
    return s


def run(a) -> int:
    from .. import api

    if a.list:
        for name, paper, kind, desc in api.synth_scenes():
            print(f"{name:16s} {kind:19s} {paper}: {desc}")
        return 0
    if not a.name or not a.out_dir:
        raise InputError("synth", "give NAME OUT_DIR (or --list)")
    api.synth(a.name, a.out_dir, size=a.size, frames=a.frames, hidden=a.hidden, strength=a.strength,
              noise=a.noise, blur=a.blur, seed=a.seed, device=a.device, force=a.force)
    return 0
