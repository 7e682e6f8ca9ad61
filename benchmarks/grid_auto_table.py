"""What `init --grid auto` chooses on each synthetic scene, beside the suggested grid 24 (init only,
no fit, no ground-truth simulation: the scene's Gaussians are the ones `synth` writes as
object.ply, made here directly; the measurement and the choice are init's own functions).

    python benchmarks/grid_auto_table.py [--size small] [--scenes a,b] [--write out.md]

Per scene: the thinnest part, the grid auto picks (and the cap that bound it, if any), cells across
the thinnest part at grid 24 and at auto, particles and substeps per frame at both, and the CPU
seconds of init's grid planning (measurement + fill) at both.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def one(name: str, size: str) -> dict:
    from physinteract_usd.app import init as app_init
    from physinteract_usd.fill import fill_from_gaussians
    from physinteract_usd.synth.generate import SIZES, surface_gaussians
    from physinteract_usd.synth.scenes import SCENES

    spec, sz = SCENES[name], SIZES[size]
    g, _ = surface_gaussians(spec, spec.shape(), sz.gaussians, 0)
    pts = g.means
    fill = lambda h, anchor=None: fill_from_gaussians(g, h, anchor=anchor)  # noqa: E731
    settings_for = lambda n: app_init.choose_sim_settings(  # noqa: E731
        pts, sz.fps, n, sz.fit_padding, sz.fit_youngs, 0.3, spec.density, max_poisson=sz.fit_poisson_max)
    floor = app_init.splat_floor(g)
    t0 = time.process_time()
    s24, p24, c24 = app_init.plan_grid(fill, settings_for, pts, sz.fit_grid, sz.fit_padding, resolution=floor)
    t_fixed = time.process_time() - t0
    t0 = time.process_time()
    sa, pa, ca = app_init.plan_grid(fill, settings_for, pts, app_init.AUTO, sz.fit_padding, resolution=floor)
    t_auto = time.process_time() - t0
    row = {"scene": name, "thinnest_mm": 1000 * ca.thinnest, "splat_floor_mm": 1000 * floor,
           "grid_auto": ca.grid, "limit": ca.limit, "init_cpu_s_24": round(t_fixed, 2),
           "init_cpu_s_auto": round(t_auto, 2), "message_auto": ca.message, "message_24": c24.message}
    for tag, s, c in (("24", s24, c24), ("auto", sa, ca)):
        row[f"cells_across_{tag}"] = c.cells_across
        row[f"particles_{tag}"] = c.particles
        row[f"substeps_{tag}"] = s.substeps
        row[f"cells_{tag}"] = int(np.prod(s.grid_resolution))
    return row


def table(rows: list[dict]) -> str:
    head = ("| scene | thinnest part mm | grid auto | cells across @24 | cells across @auto | "
            "particles @24 | particles @auto | substeps/frame @24 / @auto | init CPU s @24 / @auto |\n"
            + "|---" * 9 + "|\n")
    out = []
    for r in rows:
        lim = f" ({r['limit']} cap)" if r["limit"] else ""
        out.append(f"| {r['scene']} | {r['thinnest_mm']:.1f} | {r['grid_auto']}{lim} | "
                   f"{r['cells_across_24']:.1f} | {r['cells_across_auto']:.1f} | {r['particles_24']} | "
                   f"{r['particles_auto']} | {r['substeps_24']} / {r['substeps_auto']} | "
                   f"{r['init_cpu_s_24']:.1f} / {r['init_cpu_s_auto']:.1f} |")
    return head + "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="small")
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--write", default=None, help="markdown file to write the table to")
    ap.add_argument("--json", default=None, help="JSON-lines file to write the rows to")
    a = ap.parse_args(argv)
    from physinteract_usd.synth.scenes import SCENES

    names = a.scenes.split(",") if a.scenes else [n for n in SCENES if n != "foam_bar"] + ["foam_bar"]
    rows = []
    for n in names:
        r = one(n, a.size)
        rows.append(r)
        print(json.dumps(r), flush=True)
        if a.json:
            with open(a.json, "a") as f:
                f.write(json.dumps(r) + "\n")
    md = table(rows)
    print(md)
    if a.write:
        with open(a.write, "w") as f:
            f.write(md)


if __name__ == "__main__":
    main()
