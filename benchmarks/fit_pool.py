"""Fits from extracted and from ground-truth contacts on prepared captures, several at a time.

The small suite's fits underfill a GPU (a 2k-particle scene keeps an H100 mostly idle), so this
runs them as parallel worker processes on one device. The captures must be prepared by
`eval_extract.py --work DIR --keep` (DIR/<scene>, DIR/<scene>.gt, DIR/<scene>.stage with its
extraction): the extracted fits then use exactly the contacts that run measured.

    python benchmarks/fit_pool.py --work data/ex --scenes all --sources extracted,gt \\
        --jobs 8 --device cuda --json out/pool.json

Each job fits a fresh copy (DIR/<scene>.pool-<source>-s<seed>/), evaluates it against gt/ and
appends its row to --json as soon as it ends (a run cut short keeps what it measured). Prints a
table of MA (extracted, true contacts, difference) per scene at the end.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import shutil
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _job(args):
    name, source, work, iterations, seed, device, overrides = args
    import physinteract_usd  # noqa: F401
    from physinteract_usd import api

    from eval_extract import init_stage

    work = Path(work)
    cap, gt = work / name, work / f"{name}.gt"
    d = work / f"{name}.pool-{source}-s{seed}"
    shutil.rmtree(d, ignore_errors=True)
    t0 = time.perf_counter()
    lines = []
    try:
        if source.startswith("extracted"):
            # extracted: DIR/<scene>.stage; extracted-X: an alternative extraction in DIR/<scene>.stage-X
            shutil.copytree(work / f"{name}.stage{source[len('extracted'):]}", d)
            stage = d / "scene.usda"
            api.fit(stage, iterations=iterations, progress=False, log=lambda m, *a: lines.append(str(m)), device=device, seed=seed,
                    settings_overrides=overrides)
        else:
            stage = d / "scene.usda"
            init_stage(cap, gt, stage)
            api.fit(stage, iterations=iterations, contact_from=gt, progress=False, log=lambda *a: None,
                    device=device, seed=seed, settings_overrides=overrides)
        ev = api.evaluate(stage, gt, device=device)
        sd = api.read_scene(stage)
        return {"scene": name, "source": source, "seed": seed, "ma": ev["ma"], "ma_best_uniform": ev["ma_best_uniform"],
                "psnr_masked": ev["psnr_masked"], "psnr": ev["psnr"], "position_error_m": ev["position_error_m"],
                "final_loss": float(sd.reports[-1]["final_loss"]) if sd.reports else None,
                "grasp_particles": [len(c.particle_indices) for c in sd.contacts if c.contact_type == "pointAdherent"],
                "support_particles": int(sum(len(c.particle_indices) for c in sd.contacts if c.contact_type == "fixed")),
                "support_log": [m for m in lines if m.startswith("supports")],
                "seconds": time.perf_counter() - t0}
    except Exception as exc:  # a failed fit is a row, not the end of the run
        return {"scene": name, "source": source, "seed": seed, "error": f"{type(exc).__name__}: {exc}",
                "trace": traceback.format_exc(limit=3), "seconds": time.perf_counter() - t0}


def table(rows, key: str = "extracted") -> str:
    by = {}
    for r in rows:
        by.setdefault(r["scene"], {})[r["source"]] = r
    out = ["| scene | MA extracted | MA true contacts | difference | within 0.05 | masked PSNR extracted | fit [s] |",
           "|---|---|---|---|---|---|---|"]
    ok = n = 0
    for name, d in by.items():
        e, g = d.get(key, {}), d.get("gt", {})
        me, mg = e.get("ma"), g.get("ma")
        diff = None if me is None or mg is None else me - mg
        if diff is not None:
            n += 1
            ok += diff >= -0.05
        f = lambda v, s=".3f": "-" if v is None else format(v, s)  # noqa: E731
        out.append(f"| {name} | {f(me)} | {f(mg)} | {f(diff, '+.3f')} | "
                   f"{'-' if diff is None else ('yes' if diff >= -0.05 else '**no**')} | {f(e.get('psnr_masked'), '.2f')} | "
                   f"{f(e.get('seconds'), '.0f')} |")
    out.append(f"\nwithin 0.05 of the true-contact fit (or better): {ok} of {n}")
    return "\n".join(out)


def main(argv=None):
    from eval_extract import EXTRA, parse_overrides

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--scenes", default="all")
    ap.add_argument("--sources", default="extracted,gt", help="extracted (DIR/<scene>.stage), gt (true contacts), "
                    "extracted-X (an alternative extraction in DIR/<scene>.stage-X)")
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fit-settings", default="")
    ap.add_argument("--json", required=True)
    a = ap.parse_args(argv)
    from physinteract_usd.synth.scenes import SCENES

    names = list(SCENES) + list(EXTRA) if a.scenes == "all" else a.scenes.split(",")
    names = [n for n in names if (Path(a.work) / f"{n}.stage").is_dir()]
    overrides = parse_overrides(a.fit_settings)
    jobs = [(n, s, a.work, a.iterations, a.seed, a.device, overrides) for n in names for s in a.sources.split(",")]
    out = Path(a.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = json.loads(out.read_text()) if out.exists() else []
    done = {(r["scene"], r["source"], r["seed"]) for r in rows if "error" not in r}
    jobs = [j for j in jobs if (j[0], j[1], j[4]) not in done]
    print(f"{len(jobs)} fits, {a.jobs} at a time on {a.device}", flush=True)
    with mp.get_context("spawn").Pool(a.jobs) as pool:
        for r in pool.imap_unordered(_job, jobs):
            rows.append(r)
            out.write_text(json.dumps(rows, indent=1))
            msg = r.get("error") or f"MA {r['ma']:.3f}, masked PSNR {r['psnr_masked']:.2f}, loss {r['final_loss']}"
            print(f"{r['scene']} {r['source']}: {msg} ({r['seconds']:.0f} s)", flush=True)
    for src in a.sources.split(","):
        if src != "gt":
            print(f"\n{src}:\n" + table(rows, src))


if __name__ == "__main__":
    main()
