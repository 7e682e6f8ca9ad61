"""`physinteract-usd export`: write a self-contained asset (the verb: `physinteract_usd.app.export`)."""

from __future__ import annotations


def add_parser(sub):
    s = sub.add_parser("export", help="write a self-contained simulation-ready asset (flattened USD)")
    s.add_argument("stage")
    s.add_argument("out", help="OUT.usd, .usdc, .usda or .usdz")
    s.add_argument("--ply-sequence", metavar="DIR", help="also write one 3DGS PLY per frame into DIR")
    s.add_argument("--force", action="store_true", help="replace OUT if it exists")
    s.add_argument("--sim-ready", action="store_true",
                   help="write OUT as a tetrahedral soft body with the OpenUSD deformable-physics schemas (Newton, "
                        "Isaac Sim): the fitted field per tetrahedron, the splats bound to it (docs/simready.md)")
    s.add_argument("--capture-paths", choices=["drop", "absolute"], default="drop",
                   help="the capture's frames and masks: drop them (default: the asset depends on no other file) "
                        "or keep them as absolute paths (valid on this machine only)")
    return s


def run(a) -> int:
    from .. import api

    out = api.export(a.stage, a.out, ply_sequence=a.ply_sequence, force=a.force, capture_paths=a.capture_paths,
                     sim_ready=a.sim_ready)
    print(f"wrote {out['usd']}" + (f" and {out['ply_frames']} PLY frames in {out['ply_sequence']}"
                                    if "ply_sequence" in out else ""))
    if "sim_ready" in out:
        r = out["sim_ready"]
        print(f"  sim-ready: {r['tetrahedra']} tetrahedra, {r['points']} points, {r['regions']} material region(s); "
              f"surface within {1e3 * r['surface_distance_max_m']:.1f} mm of the Gaussians "
              f"(particle spacing {1e3 * r['particle_spacing_m']:.1f} mm)"
              + (f"; effects without a schema equivalent: {', '.join(r['unmapped_effects'])}" if r["unmapped_effects"] else ""))
    return 0
