"""The colour parts' separation per suite scene (#24; fit/regions.py `separation`, fit/parts_start.py
PARTS_MIN_SEPARATION): the parts start tries a scene's appearance parts only where they lie apart as regions.

    python benchmarks/parts_separation.py [--scenes a,b,...] [--work /tmp/parts_sep]

Each scene: a 3-frame small capture (`synth --frames 3`: the object and its colours do not depend on the frames; the
truth at the size's default grid), `init --grid auto` with the capture's suggested settings (the suite's particles), the
appearance candidate of `select.part_candidates`, its separation. Prints a markdown table (CPU, ~10 s a scene)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

SCENES = ("foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope,balloon,bow_tie,glove,flower,basketball,"
          "knit_cap")


def stage_for(scene: str, work: Path) -> tuple[Path, Path]:
    cap, st = work / scene, work / f"{scene}.usda"
    if not st.exists():
        py = sys.executable
        subprocess.run([py, "-m", "physinteract_usd", "synth", scene, str(cap), "--size", "small", "--frames", "3",
                        "--force"], check=True, capture_output=True)
        sug = json.loads((cap / "gt" / "gt.json").read_text())["suggested_init"]
        subprocess.run([py, "-m", "physinteract_usd", "init", str(st), "--capture", str(cap), "--grid", "auto",
                        "--padding", str(sug["padding"]), "--youngs-range", ",".join(map(str, sug["youngs_range"])),
                        "--max-poisson", str(sug["max_poisson"]), "--density", str(sug["density"])],
                       check=True, capture_output=True)
    return st, cap


def separation_of(scene: str, work: Path) -> dict:
    from physinteract_usd import api
    from physinteract_usd.fit import FitProblem, FitSettings
    from physinteract_usd.fit.parts_start import PARTS_MIN_SEPARATION
    from physinteract_usd.fit.regions import separation
    from physinteract_usd.fit.select import part_candidates
    from physinteract_usd.usd.stage import read_stage

    st, cap = stage_for(scene, work)
    sd = read_stage(st)
    prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, cap / "gt"))
    c = [c for c in part_candidates(prob, FitSettings(), None) if c["kind"] == "appearance" and c["parts"] > 1]
    if not c:
        return {"scene": scene, "particles": len(prob.x0), "parts": 1, "separation": None, "tried": False}
    sep = separation(np.asarray(prob.x0), c[0]["labels"])
    return {"scene": scene, "particles": len(prob.x0), "parts": int(c[0]["parts"]), "separation": round(sep, 3),
            "tried": bool(sep >= PARTS_MIN_SEPARATION)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--work", default="/tmp/parts_sep")
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = [separation_of(s, work) for s in a.scenes.split(",") if s]
    print("| scene | particles | colour parts | separation | parts start tries them |\n|---|---:|---:|---:|---|")
    for r in sorted(rows, key=lambda r: -(r["separation"] or 0)):
        sep = "-" if r["separation"] is None else f"{r['separation']:.2f}"
        print(f"| {r['scene']} | {r['particles']:,} | {r['parts']} | {sep} | {'yes' if r['tried'] else 'no'} |")


if __name__ == "__main__":
    main()
