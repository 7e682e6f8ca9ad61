"""The colour parts' separation per suite scene (#24; fit/regions.py `separation`, fit/parts_start.py
PARTS_MIN_SEPARATION): the parts start tries a scene's appearance parts only where they lie apart as regions.

    python benchmarks/parts_separation.py [--scenes a,b,...] [--work /tmp/parts_sep]

Each scene: a 3-frame small capture (`synth --frames 3`: the object and its colours do not depend on the frames; the
truth at the size's default grid), `init --grid auto` with the capture's suggested settings (the suite's particles), the
appearance candidate of `select.part_candidates`, its separation; and the parts by shape that the parts start takes where
the colours make no regions (`select.shape_candidate`: thin against thick, 33rd session), their median thicknesses and
separation, with the oracle MA (each part at its best single E, on the particles, from the truth: development data)
against the whole object's. Prints a markdown table (CPU, ~10 s a scene)."""

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
    row = {"scene": scene, "particles": len(prob.x0), "parts": 1, "separation": None, "tried": False}
    if c:
        sep = separation(np.asarray(prob.x0), c[0]["labels"])
        row.update(parts=int(c[0]["parts"]), separation=round(sep, 3), tried=bool(sep >= PARTS_MIN_SEPARATION))
    row.update(shape_of(prob, cap))
    return row


def oracle_ma(e_true: np.ndarray, labels: np.ndarray) -> float:
    """The MA of each part at its own best single E (`metrics.best_uniform_ma` per part), over the whole object."""
    from physinteract_usd.metrics import best_uniform_ma

    return float(sum(best_uniform_ma(e_true[labels == j])[0] * np.sum(labels == j) for j in np.unique(labels))
                 / len(labels))


def shape_of(prob, cap: Path) -> dict:
    """The shape's parts (`select.shape_candidate`), their separation and the oracle MA against one E's."""
    from scipy.spatial import cKDTree

    from physinteract_usd.fit import FitSettings
    from physinteract_usd.fit.parts_start import PARTS_MIN_SEPARATION
    from physinteract_usd.fit.regions import separation
    from physinteract_usd.fit.select import shape_candidate

    x = np.asarray(prob.x0)
    gt = np.load(cap / "gt" / "particles.npz")
    e_true = gt["E"][cKDTree(gt["rest"]).query(x)[1]].astype(float)
    out = {"oracle_uniform": round(oracle_ma(e_true, np.zeros(len(x), int)), 3), "shape": None}
    c = shape_candidate(prob, FitSettings())
    if c is not None:
        sep = separation(x, c["labels"])
        out["shape"] = {"thin_mm": round(1e3 * c["thickness_m"][0], 1), "thick_mm": round(1e3 * c["thickness_m"][1], 1),
                        "separation": round(sep, 2), "tried": bool(sep >= PARTS_MIN_SEPARATION),
                        "oracle": round(oracle_ma(e_true, c["labels"]), 3)}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=SCENES)
    ap.add_argument("--work", default="/tmp/parts_sep")
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = [separation_of(s, work) for s in a.scenes.split(",") if s]
    print("| scene | particles | colour parts | separation | parts start tries them | shape parts: thin / thick mm "
          "(separation) | oracle MA: one E -> shape parts |\n|---|---:|---:|---:|---|---|---|")
    for r in sorted(rows, key=lambda r: -(r["separation"] or 0)):
        sep = "-" if r["separation"] is None else f"{r['separation']:.2f}"
        sh = r["shape"]
        shape = "none" if sh is None else (f"{sh['thin_mm']} / {sh['thick_mm']} ({sh['separation']:.2f}"
                                           f"{'' if sh['tried'] else ': interleaved'})")
        orc = f"{r['oracle_uniform']:.3f}" + ("" if sh is None else f" -> {sh['oracle']:.3f}")
        print(f"| {r['scene']} | {r['particles']:,} | {r['parts']} | {sep} | {'yes' if r['tried'] else 'no'} | {shape} | "
              f"{orc} |")


if __name__ == "__main__":
    main()
