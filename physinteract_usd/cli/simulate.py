"""`physinteract-usd simulate`: re-simulate the fitted object under a new interaction (the verb: `physinteract_usd.app.simulate`)."""

from __future__ import annotations

import argparse

from ..app.interaction_spec import INTERACTION_DOC


def add_parser(sub):
    s = sub.add_parser("simulate", help="re-simulate the fitted object under a new interaction",
                       epilog=INTERACTION_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("stage")
    s.add_argument("--interaction", required=True, metavar="SPEC.json", help="the new interaction (see below)")
    s.add_argument("--name", help="name of the simulation (default: the spec's name or file stem)")
    s.add_argument("--device", default="cpu")
    return s


def run(a) -> int:
    from .. import api

    out = api.simulate(a.stage, a.interaction, name=a.name, device=a.device)
    print(f"simulated {out['frames']} frames: layer {out['layer']}; open {out['stage']} to view it over the fit")
    return 0
