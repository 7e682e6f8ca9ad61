"""`physinteract-usd export`: write a self-contained asset (the verb: `physinteract_usd.app.export`)."""

from __future__ import annotations


def add_parser(sub):
    s = sub.add_parser("export", help="write a self-contained simulation-ready asset (flattened USD)")
    s.add_argument("stage")
    s.add_argument("out", help="OUT.usd, .usdc, .usda or .usdz")
    s.add_argument("--ply-sequence", metavar="DIR", help="also write one 3DGS PLY per frame into DIR")
    return s


def run(a) -> int:
    from .. import api

    out = api.export(a.stage, a.out, ply_sequence=a.ply_sequence)
    print(f"wrote {out['usd']}" + (f" and {out['ply_frames']} PLY frames in {out['ply_sequence']}"
                                    if "ply_sequence" in out else ""))
    return 0
