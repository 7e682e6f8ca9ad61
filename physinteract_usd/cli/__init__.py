"""`physinteract-usd` command line: a thin front end over `physinteract_usd.api`. One module per
verb here (its flags and how it prints); what the verb does is `physinteract_usd.app.<verb>`.

Exit codes: 0 success, 2 bad input (one line on stderr naming the file and the problem),
3 a simulation that went unstable (what to change is in the message), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys

from .. import __version__
from ..devices import check_device
from ..errors import InputError, SimulationError
from . import evaluate, export, extract, fit, info, init, simulate, synth

VERBS = [init, info, synth, extract, fit, evaluate, simulate, export]   # in the order `-h` lists them


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
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        check_device(getattr(args, "device", None))
        return args.run(args)
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
