"""Where the suite's MA is lost (#24): per scene, per material of the truth (its distinct E values,
or three quantile bins of a graded truth), the share of Gaussians, the MA there, the fitted E over the
truth's (median and quartiles), the fit's mean confidence there and the truth's own peak strain (a
material that never strains is not in the video); then whether the fit's confidence holds (the MA it
claims against the MA found, and the share confident and wrong). Reads the JSON-lines rows that
`suite.py` / `stall_suite.py` write (`evaluate`'s `by_truth_level` and `calibration`).

    python benchmarks/ma_breakdown.py ROWS.jsonl [ROWS2.jsonl ...] [--variant old]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def rows_of(paths, variant: str | None) -> list[dict]:
    out, best = {}, {}
    for p in paths:
        for line in Path(p).read_text().splitlines():
            if not line.startswith("{"):      # a log's other lines
                continue
            r = json.loads(line)
            if r.get("ma_best_uniform") is not None:
                best[r["scene"]] = r["ma_best_uniform"]
    for p in paths:
        for line in Path(p).read_text().splitlines():
            if not line.startswith("{"):
                continue
            r = json.loads(line)
            if r.get("by_truth_level") is None or (variant and r.get("variant", variant) != variant):
                continue
            r.setdefault("ma_best_uniform", best.get(r["scene"]))
            out[r["scene"]] = r          # the last row of a scene wins
    return [out[k] for k in sorted(out)]


def table(rows: list[dict]) -> str:
    lines = ["| scene | MA (best single E) | E truth (Pa) | share | MA there | E fit / truth: median (q25-q75) "
             "| confidence | truth's peak strain |", "|---|---|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        first = True
        for lv in r["by_truth_level"]:
            bu = r.get("ma_best_uniform")
            head = (f"{r['scene']} | {r['ma']:.3f} ({bu:.3f})" if bu is not None else f"{r['scene']} | {r['ma']:.3f}") \
                if first else " | "
            conf = f"{lv['confidence']:.2f}" if lv.get("confidence") is not None else "-"
            lines.append(f"| {head} | {lv['e_truth']:.3g} | {lv['share']:.2f} | {lv['ma']:.2f} | "
                         f"{lv['ratio_median']:.2f} ({lv['ratio_q25']:.2f}-{lv['ratio_q75']:.2f}) | {conf} | "
                         f"{lv.get('exposure', float('nan')):.3f} |")
            first = False
    lines += ["", "| scene | MA | MA the fit claims (mean confidence) | confident (>= 0.8) and wrong | "
              "per confidence bin: share / claimed / MA |", "|---|---:|---:|---:|---|"]
    for r in rows:
        c = r.get("calibration")
        if not c:
            continue
        bins = "; ".join(f"[{b['lo']:.1f}, {b['hi']:.1f}]: {b['share']:.2f} / {b['claimed']:.2f} / {b['ma']:.2f}"
                         for b in c["bins"])
        lines.append(f"| {r['scene']} | {c['ma']:.3f} | {c['claimed']:.3f} | {c['confident_wrong']:.3f} | {bins} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rows", nargs="+")
    ap.add_argument("--variant", default="old", help="stall_suite's variant to show ('' = any)")
    a = ap.parse_args(argv)
    print(table(rows_of(a.rows, a.variant or None)))


if __name__ == "__main__":
    main()
