"""Per frame pair of a dev world capture: the extraction's toucher and object velocities next to the
contact, its coupling and `near`, against the truth's (the toucher's path and the held particles,
or the particles nearest the contact point, projected). What the video shows at the true grasp and
release, and why the timing rules pick the frames they pick (#23, docs/benchmarks/world.md, fifth
pass). Dev split only: a validation folder or capture is refused (a tuning tool).

    python benchmarks/world_timing.py --work data/world_dev dev_0002 [dev_0014 ...]

The capture must have been prepared by `world_suite.py extract` (its stage DIR/<name>.stage and
its ground truth DIR/<name>.gt). The truth's world is rebuilt from gt.json's drawn values.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import physinteract_usd  # noqa: F401  (schemas)
from physinteract_usd.errors import InputError
from physinteract_usd.synth.splits import refuse_validation

TOOL = "world_timing.py"


def true_motion(work: Path, name: str, camera):
    """(T-1, 2) the truth's toucher and contact-material image velocities, the true grasp/release."""
    from physinteract_usd.synth.world import World, toucher_positions

    g = json.loads((work / f"{name}.gt" / "gt.json").read_text())
    w = dict(g["world"])
    world = World(w)
    world.contacts()
    hp = toucher_positions(world)
    x = np.load(work / f"{name}.gt" / "particles.npz")["positions"]
    idx = world.contact_indices if len(world.contact_indices) else \
        np.argsort(np.linalg.norm(world.x0 - world.contact_point, axis=1))[:20]
    uh = camera.project(hp)[0]
    uo = np.stack([camera.project(x[k][idx])[0].mean(0) for k in range(len(x))])
    return np.diff(uh, axis=0), np.diff(uo, axis=0), g["interaction"]


def run(work: Path, name: str, log=print) -> dict:
    from physinteract_usd import api
    import physinteract_usd.extract.pipeline as P

    for p in (work, work / name, work / f"{name}.gt"):
        refuse_validation(p, TOOL)
    stage = work / f"{name}.stage" / "scene.usda"
    if not stage.exists():
        raise InputError(stage, "no prepared stage: run world_suite.py extract --split dev on the folder first")
    seen = {}
    orig = P.find_timing

    def spy(an, contact, evidence):
        t = orig(an, contact, evidence)
        seen["t"] = t
        return t

    P.find_timing = spy
    try:
        res = api.extract(stage, log=lambda *a: None)
    finally:
        P.find_timing = orig
    t = seen["t"]
    vh_t, vo_t, it = true_motion(work, name, api.read_scene(stage).camera)
    log(f"{name}: type {it['type']} / {res.interaction_type}; grasp {it['grasp_frame']} / {res.grasp_frame}; "
        f"release {it['release_frame']} / {res.release_frame}; confidence {res.evidence.get('timing_confidence')}")
    log(" k near  mark |  toucher (extracted)  object (extracted) cpl |  toucher (true)   object (true)")

    def f(v):
        return "    nan     nan" if not np.isfinite(v).all() else f"{v[0]:7.2f} {v[1]:7.2f}"

    for k in range(len(t.coupled)):
        mark = ("G" if k == it["grasp_frame"] else " ") + ("R" if k == it["release_frame"] else " ") + \
               ("g" if k == res.grasp_frame else " ") + ("r" if k == res.release_frame else " ")
        log(f"{k:2d} {int(t.near[k])}     {mark} | {f(t.hand_velocity[k])} {f(t.object_velocity[k])} "
            f"{int(t.coupled[k]):2d} | {f(vh_t[k])} {f(vo_t[k])}")
    for n in res.notes:
        log("  note:", n)
    return {"name": name, "grasp": res.grasp_frame, "release": res.release_frame,
            "grasp_true": it["grasp_frame"], "release_true": it["release_frame"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="the dev folder of captures (world_suite.py's)")
    ap.add_argument("names", nargs="+", help="captures, e.g. dev_0002")
    a = ap.parse_args(argv)
    try:
        for n in a.names:
            run(Path(a.work), n)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
