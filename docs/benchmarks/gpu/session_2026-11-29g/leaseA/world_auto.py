"""World dev captures through the product path with the preload left to the fit: generate (settled or default),
init with the suggested settings but no preload flag, fit from the true contacts (world_fit.fit_one), one row each."""
import json, os, sys, time
DEV = os.environ.get("DEVICE", "cuda")
from pathlib import Path
sys.path.insert(0, "benchmarks")
import world_fit, world_suite
from physinteract_usd import api

work = Path(sys.argv[1]); out = Path(sys.argv[2]); settle = sys.argv[3] == "settled"; seeds = sys.argv[4].split(",")
its = int(sys.argv[5]) if len(sys.argv) > 5 else 60
work.mkdir(parents=True, exist_ok=True)
for s in seeds:
    n = f"dev_{int(s):04d}"
    t = time.time()
    row = {"scene": n, "settled": settle}
    try:
        api.synth(None, work / n, random=int(s), split="dev", device=DEV, force=True,
                  overrides={"settle": True} if settle else None)
        row["synth_s"] = round(time.time() - t, 1)
        world_suite.prepare(work, n)
        r = world_fit.fit_one(work, n, its, 0, DEV, true_contacts=True)
        g = json.loads((work / f"{n}.gt" / "gt.json").read_text())
        row.update({k: r.get(k) for k in ("ma", "ma_best_uniform", "psnr_masked", "fit_s", "preload", "preload_stage")})
        row["e_ratio"] = r.get("e_ratio")
        row["truth_E"] = g["youngs_modulus"]
        row["row"] = {k: v for k, v in r.items() if k not in ("interaction_check",)}
    except Exception as exc:  # noqa: BLE001
        import traceback
        row["error"] = f"{type(exc).__name__}: {exc}"
        traceback.print_exc()
    with open(out, "a") as fh:
        fh.write(json.dumps(row, default=str) + "\n")
    print(json.dumps({k: v for k, v in row.items() if k != "row"}, default=str), flush=True)
