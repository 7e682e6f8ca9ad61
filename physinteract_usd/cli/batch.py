"""`physinteract-usd batch`: init -> extract -> fit -> report -> diagnose -> export over a manifest,
in a local process pool or on Ray (the verb: `physinteract_usd.app.batch`, docs/batch.md).

Exit codes: 0 every item done, 1 some item failed (named on stderr; the others are kept), 2 bad
input (the manifest, a flag, --ray without Ray), 130 interrupted (finished items kept)."""

from __future__ import annotations

import json
import sys

from .common import positive_float, progress_log


def _grid(s: str):
    return "auto" if s.strip().lower() == "auto" else _workers(s)


def _workers(s: str) -> int:
    import argparse

    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {s!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
    return v


def add_parser(sub):
    s = sub.add_parser("batch", help="run init, extract, fit, report, diagnose and export over a manifest of captures",
                       description="Process a manifest (CSV or JSON: capture folders or stages, per-item overrides; "
                                   "docs/batch.md) item by item: init -> extract -> fit -> report -> diagnose -> "
                                   "export. Items done earlier with the same inputs and settings are reused; a "
                                   "failing item is recorded and the rest go on.")
    s.add_argument("manifest", help="CSV or JSON manifest")
    s.add_argument("--out", metavar="DIR", help="output folder (default: <manifest stem>.batch beside the manifest)")
    s.add_argument("--workers", type=_workers, metavar="N",
                   help="local worker processes (default: one per CPU core; 1 when an item uses CUDA)")
    s.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run one Ray task per item: on the cluster at ADDRESS, or (no ADDRESS) the one RAY_ADDRESS "
                        "names, else a new local one (pip install physinteract-usd[ray])")
    s.add_argument("--gpus-per-item", type=positive_float, default=1.0, metavar="F",
                   help="with --ray and CUDA: GPUs each item asks for, fractional to share a GPU (default 1)")
    s.add_argument("--retries", type=int, default=2, metavar="N",
                   help="times an item is tried again when its worker process dies (default 2)")
    s.add_argument("--device", default=None, help="cpu or cuda for items that do not say (default cpu)")
    s.add_argument("--iterations", type=_workers, default=None, metavar="N",
                   help="fit iterations for items that do not say (default 60)")
    s.add_argument("--schedule", choices=["bumps", "select", "ladder"], default=None,
                   help="the fit's schedule for items that do not say")
    s.add_argument("--seed", type=int, default=None, help="the fit's seed for items that do not say (default 0)")
    s.add_argument("--grid", type=_grid, default=None, metavar="N|auto",
                   help="init's grid cells along the longest side (or auto: 4 across the object's thinnest "
                        "part) for items that do not say")
    s.add_argument("--skip", metavar="STEP,...", default=None,
                   help="steps left out for items that do not say: report, diagnose, export (the diagnosis refits "
                        "the model several times: the costliest step after the fit)")
    s.add_argument("--force", action="store_true", help="run every item from its first step, even when done")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    return s


def run(a) -> int:
    from .. import api

    log = progress_log(a.json)
    res = api.batch(a.manifest, out=a.out, workers=a.workers, ray=a.ray, device=a.device, iterations=a.iterations,
                    schedule=a.schedule, seed=a.seed, grid=a.grid, skip=a.skip, gpus_per_item=a.gpus_per_item, retries=a.retries,
                    force=a.force, progress=not a.no_progress and not a.json, log=log)
    summ = res.summary()
    if a.json:
        print(json.dumps(summ, indent=2, default=str))
    else:
        print(f"{len(res.records)} items: {len(res.ran)} done now, {len(res.reused)} reused, {len(res.failed)} failed"
              + (f", {len(res.interrupted)} interrupted" if res.interrupted else "")
              + (f", {len(res.not_started)} not started" if res.not_started else "") + f" ({res.seconds:.0f} s)")
        print(f"  summary: {summ['outputs']['summary_csv']}, {summ['outputs']['summary_html']}")
        print(f"  catalogue: {summ['outputs']['catalogue']}")
    for name in res.failed:
        print(f"physinteract-usd batch: {name} failed: {res.records[name].get('error')}", file=sys.stderr)
    if res.interrupted or res.not_started:
        print(f"physinteract-usd batch: interrupted ({len(res.interrupted)} items cut short, "
              f"{len(res.not_started)} not started: run the same command to go on)", file=sys.stderr)
        return 130
    return 1 if res.failed else 0
