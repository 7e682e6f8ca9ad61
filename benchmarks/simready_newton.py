"""Cross-check of `export --sim-ready` with Newton: our MPM and Newton (from the exported file alone)
under the same loads, on the bundled sample's fitted stage and on one synthetic scene per archetype.

    python benchmarks/simready_newton.py --sample out/demo/scene.usda --scenes hemp_rope,bow_tie,balloon,flower \\
        --work /tmp/simready --json docs/benchmarks/simready_newton.json

The sample is its fitted stage (`bash scripts/demo.sh` writes out/demo/scene.usda): the fitted field
and the fitted interaction. A synthetic scene is `synth NAME --size small` + `init` with its
suggested settings, then its ground-truth field (from gt/particles.npz, nearest particle) and
ground-truth contacts (no fit: what is compared is the two simulators on one asset). Each asset is
exported with `app.simready` and loaded into Newton by `crosscheck` (see physinteract_usd/
crosscheck.py for the loads and the measures). Prints one row per scene and load.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))

ARCHETYPES = {"hemp_rope": "rope", "bow_tie": "flat", "balloon": "inflated", "flower": "thin stem + petals",
              "glove": "flat, fingers", "balloon_dog": "inflated, limbs", "tow_rope": "rope, two anchors"}


def synthetic_scene(name: str, work: Path, grid: int | None = None):
    """(SceneData with the ground-truth field and contacts, its stage path). `grid`: init's grid
    instead of the capture's suggested one (a finer lattice: more particles, smaller cells)."""
    from physinteract_usd import api

    from eval_extract import init_stage

    cap = work / name
    if not (cap / "gt" / "gt.json").exists():
        api.synth(name, cap, size="small", force=True, log=lambda *a: None)
    stage = work / (f"{name}.grid{grid}.stage" if grid else f"{name}.stage") / "scene.usda"
    if not stage.exists():
        if grid:
            g = json.loads((cap / "gt" / "gt.json").read_text())["suggested_init"]
            stage.parent.mkdir(parents=True, exist_ok=True)
            api.init(stage, cap, grid=grid, padding=g["padding"], youngs_range=tuple(g["youngs_range"]),
                     max_poisson=g["max_poisson"], density=g["density"])
        else:
            init_stage(cap, cap / "gt", stage)
    sd = api.read_scene(stage)
    gtp = np.load(cap / "gt" / "particles.npz")            # the ground-truth simulation's particles
    _, nn = cKDTree(gtp["rest"]).query(sd.particles_positions)
    E, nu = gtp["E"][nn], gtp["nu"][nn]
    contacts = api.true_contacts(sd, cap / "gt")
    return dataclasses.replace(sd, youngs_modulus=np.asarray(E, np.float64), poisson_ratio=np.asarray(nu, np.float64),
                               contacts=contacts, trajectories=[]), stage


def run_one(label: str, archetype: str, sd, out: Path, args) -> list[dict]:
    from physinteract_usd.app.simready import build_sim_ready
    from physinteract_usd.crosscheck import crosscheck
    from physinteract_usd.usd.simready import write_sim_ready

    t0 = time.perf_counter()
    asset = build_sim_ready(sd, log=lambda *a: None)
    write_sim_ready(out, asset)
    export_s = time.perf_counter() - t0
    print(f"{label}: {len(asset.tets)} tetrahedra, {len(asset.points)} points, {len(asset.regions)} regions, "
          f"surface within {asset.info['surfaceDistanceMax'] / asset.info['particleSpacing']:.2f} h of the Gaussians, "
          f"exported in {export_s:.1f} s", flush=True)
    from physinteract_usd.crosscheck import loads_for
    from physinteract_usd.usd.simready import read_sim_ready

    wanted = set(args.loads.split(","))
    loads = [ld for ld in loads_for(read_sim_ready(out)) if ld.name in wanted]
    r = crosscheck(sd, out, duration=args.duration, damping=args.damping, newton_substeps=args.rate,
                   iterations=args.iterations, loads=loads, log=lambda m: print(f"{label}{m}", flush=True))
    if args.one_material:   # what add_usd gives alone: the body's one material (subset bindings ignored)
        from physinteract_usd.crosscheck import Load

        r1 = crosscheck(sd, out, per_tet=False, duration=args.duration, damping=args.damping,
                        newton_substeps=args.rate, iterations=args.iterations, loads=[Load("sag", np.zeros(3), 0.0)],
                        log=lambda m: print(f"{label} (one material){m}", flush=True))
        r["loads"]["sag, Newton with one material"] = r1["loads"]["sag"]
    rows = []
    for load, c in r["loads"].items():
        rows.append({"scene": label, "archetype": archetype, "load": load, "particles": len(sd.particles_positions),
                     "tetrahedra": len(asset.tets), "points": len(asset.points), "regions": len(asset.regions),
                     "spacing_m": asset.info["particleSpacing"], "surface_max_h": asset.info["surfaceDistanceMax"]
                     / asset.info["particleSpacing"], "volume_ratio": asset.info["volumeRatio"], **c})
    for w in r.get("newton_warnings", []):
        print(f"{label}: Newton: {w}")
    return rows


def table(rows: list[dict]) -> str:
    head = ("| scene | archetype | load | particles | tets | tip ours [mm] | tip Newton [mm] | tip error | "
            "surface error | free surface error | MPM s | Newton s |")
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['archetype']} | {r['load']} | {r['particles']} | {r['tetrahedra']} | "
                     f"{1e3 * r['tip_ours_norm_m']:.2f} | {1e3 * r['tip_newton_norm_m']:.2f} | "
                     f"{100 * r['tip_error']:.1f}% | {100 * r['surface_error']:.1f}% | "
                     f"{100 * r['free_surface_error']:.1f}% | {r['mpm_seconds']:.0f} | {r['newton_seconds']:.0f} |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sample", help="the bundled sample's fitted stage (out/demo/scene.usda)")
    ap.add_argument("--scenes", default="hemp_rope,bow_tie,balloon,flower", help="synthetic scenes (comma list)")
    ap.add_argument("--work", default="/tmp/simready", help="scratch folder for captures, stages and assets")
    ap.add_argument("--json", help="append the rows here")
    ap.add_argument("--duration", type=float, default=1.5, help="seconds simulated per load")
    ap.add_argument("--damping", type=float, default=25.0, help="mass-proportional damping c [1/s]")
    ap.add_argument("--rate", type=int, default=2000, help="Newton steps per second")
    ap.add_argument("--iterations", type=int, default=10, help="Newton VBD iterations per step")
    ap.add_argument("--grid", type=int, help="init the synthetic scenes on this grid instead of their suggested "
                    "one (the refined rows: e.g. 48 for 2x finer than 24)")
    ap.add_argument("--loads", default="sag,pull", help="which loads (comma list of sag, pull)")
    ap.add_argument("--one-material", action="store_true",
                    help="also the sag with the body's one material (what add_usd resolves), not per tetrahedron")
    args = ap.parse_args()
    import physinteract_usd  # noqa: F401
    from physinteract_usd import api

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    jobs = []
    if args.sample:
        jobs.append(("bar (sample)", lambda: ("foam_bar (sample, fitted)", api.read_scene(args.sample))))

    def synthetic(name):
        sd = synthetic_scene(name, work, args.grid)[0]
        if not args.grid:
            return name, sd
        g = json.loads((work / name / "gt" / "gt.json").read_text())["suggested_init"]["grid"]
        return f"{name}, grid {args.grid} ({args.grid / g:g}x finer)", sd

    for name in filter(None, args.scenes.split(",")):
        jobs.append((ARCHETYPES.get(name, "?"), lambda n=name: synthetic(n)))
    for arch, load in jobs:
        label, sd = load()
        out = work / (label.split()[0].rstrip(",") + (f".grid{args.grid}" if "grid" in label else "") + ".simready.usdc")
        new = run_one(label, arch, sd, out, args)
        rows += new
        if args.json:
            p = Path(args.json)
            old = json.loads(p.read_text()) if p.exists() else {"machine": platform.processor() or platform.machine(),
                                                                   "rows": []}
            old["rows"] += new
            p.write_text(json.dumps(old, indent=1))
        print(table(new), flush=True)
    print()
    print(table(rows))


if __name__ == "__main__":
    main()
