"""`physinteract-usd` command line: a thin front end over `physinteract_usd.api`. One module per
verb here (its flags and how it prints); what the verb does is `physinteract_usd.app.<verb>`.

Exit codes: 0 success, 2 bad input (one line on stderr naming the file and the problem),
3 a simulation that went unstable (what to change is in the message), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys

from .. import __version__
from ..devices import check_device, quiet_warp_init_on_load
from ..errors import InputError, SimulationError
from ..stopping import sigterm_as_interrupt
from . import batch, diagnose, effects, evaluate, export, extract, fit, info, init, report, simulate, synth, versions

VERBS = [init, info, synth, extract, fit, versions, report, diagnose, effects, evaluate, simulate, export, batch]   # in the order `-h` lists them


# what to change, in flags, for the simulator's failures (its own advice names its classes)
CLI_ADVICE = {
    "domain": "the object's particles walked past the edge of the simulation's grid (a free end swinging about a hook "
              "or clamp, a fall after a release, a long pull; the grid already grows to the reach it expects: "
              "docs/sim.md): give the object more room (`init --padding`, larger), raise the smallest E it may have "
              "(`init --youngs-range MIN,MAX`), or check the trajectory",
    "unstable": "the substep is too long for the stiffness reached: lower the largest E (`init --youngs-range "
                "MIN,MAX`) or --max-poisson, or slow the trajectory",
}


class _Parser(argparse.ArgumentParser):
    """Bad flags are one line on stderr (exit 2), like every other bad input; `-h` shows the usage."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="physinteract-usd",
                description="Fit a simulation-ready digital twin of a soft object from a video of a hand "
                            "handling it, stored in OpenUSD.")
    p.add_argument("--version", action="version", version=f"physinteract-usd {__version__}")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    for mod in VERBS:
        s = mod.add_parser(sub)
        s.set_defaults(run=mod.run)
    return p


def main(argv=None) -> int:
    """Run a command line (`argv`: its words; None: the process's own, then the process ends here
    with the exit code, without Python's slow teardown of Warp's and torch's native state: ~4 s on
    a 2-core box, after the outputs are written)."""
    code = _main(argv)
    if argv is None:
        import os

        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (BrokenPipeError, ValueError):
                pass
        os._exit(code)
    return code


def _main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        device = getattr(args, "device", None)
        check_device(device)
        quiet_warp_init_on_load(device)
        with sigterm_as_interrupt():   # SIGTERM (timeout, schedulers) ends a verb as Ctrl-C does: exit 130
            return args.run(args)
    except InputError as exc:
        print(f"physinteract-usd {args.verb}: error: {exc.oneline()}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        print(f"physinteract-usd {args.verb}: {exc.message(CLI_ADVICE.get(exc.kind))}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(f"physinteract-usd {args.verb}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # a file that cannot be written or read where the checks did not foresee it
        where = exc.filename or ""
        print(f"physinteract-usd {args.verb}: error: {where}{': ' if where else ''}{exc.strerror or exc}",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
