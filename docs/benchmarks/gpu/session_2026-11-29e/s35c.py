"""session 35, lease B: the settled truth's prestressed scan (#23): 3 held dev worlds made both ways on CUDA, each
initialised with its suggested settings (world_suite.prepare: no extraction) and fitted from its true contacts as
world_fit.py does (60 iterations); rows printed as they finish."""
import json, sys, time
from pathlib import Path
sys.path.insert(0, "benchmarks")
from physinteract_usd import api
from world_suite import prepare
from world_fit import fit_one

out = Path(sys.argv[1])
seeds = [546, 549, 534]
t0 = time.time()
for settle in (True, False):
    work = Path("/tmp/wset" if settle else "/tmp/wdef")
    for s in seeds:
        n = f"dev_{s:04d}"
        t = time.time()
        api.synth(None, work / n, random=s, split="dev", device="cuda", force=True, log=lambda *a: None,
                  overrides={"settle": True} if settle else None)
        g = json.loads((work / n / "gt" / "gt.json").read_text())
        prepare(work, n)
        print(f"{'set' if settle else 'def'} {n}: generated+init {time.time() - t:.0f} s, settle {g.get('settle')}", flush=True)
for s in seeds:
    for settle in (True, False):
        work = Path("/tmp/wset" if settle else "/tmp/wdef")
        n = f"dev_{s:04d}"
        if time.time() - t0 > 500:
            print("deadline", flush=True)
            break
        try:
            r = fit_one(work, n, 60, 0, "cuda", log=lambda *a, **k: None, true_contacts=True)
        except Exception as exc:  # noqa: BLE001
            print(f"{'set' if settle else 'def'} {n}: ERROR {exc}", flush=True)
            continue
        (out / f"{'set' if settle else 'def'}_{n}.json").write_text(json.dumps(r, indent=1, default=str))
        print(f"{'set' if settle else 'def'} {n}: MA {r['ma']:.3f} (uniform {r['ma_best_uniform']:.3f}), e_ratio "
              f"{r['e_ratio']:.3f}, PSNRm {r['psnr_masked']:.2f}, fit {r['fit_s']:.0f} s", flush=True)
print(f"total {time.time() - t0:.0f} s")
