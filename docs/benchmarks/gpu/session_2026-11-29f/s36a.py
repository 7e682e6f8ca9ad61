"""session 36, lease A: the fit's preload (#23, init --preload). The 3 held dev worlds the 35th session fitted 6-21x
too stiff (dev 0546 / 0549 / 0534), generated settled on CUDA (their suggested init now says --preload), fitted from
their true contacts as world_fit.py does (60 iterations); then, time allowing, the same settled captures without
preload (the 35th session's rows, again in this lease). Rows printed as they finish."""
import json, sys, time
from pathlib import Path
sys.path.insert(0, "benchmarks")
from physinteract_usd import api
from world_suite import prepare
from world_fit import fit_one

out = Path(sys.argv[1])
seeds = [546, 549, 534]
t0 = time.time()
work = Path("/tmp/wset")
for s in seeds:
    n = f"dev_{s:04d}"
    t = time.time()
    api.synth(None, work / n, random=s, split="dev", device="cuda", force=True, log=lambda *a: None,
              overrides={"settle": True})
    g = json.loads((work / n / "gt" / "gt.json").read_text())
    prepare(work, n)
    print(f"set {n}: generated+init {time.time() - t:.0f} s, preload {g['suggested_init'].get('preload')}, "
          f"settle {g.get('settle')}", flush=True)
for pre in (True, False):
    for s in seeds:
        n = f"dev_{s:04d}"
        if time.time() - t0 > 470:
            print("deadline", flush=True)
            break
        if not pre:
            g = json.loads((work / f"{n}.gt" / "gt.json").read_text())
            g["suggested_init"]["preload"] = False
            (work / f"{n}.gt" / "gt.json").write_text(json.dumps(g))
            prepare(work, n)
        t = time.time()
        try:
            r = fit_one(work, n, 60, 0, "cuda", log=lambda *a, **k: None, true_contacts=True)
        except Exception as exc:  # noqa: BLE001
            print(f"{'pre' if pre else 'free'} {n}: ERROR {type(exc).__name__}: {exc}", flush=True)
            continue
        tag = "pre" if pre else "free"
        (out / f"{tag}_{n}.json").write_text(json.dumps(r, indent=1, default=str))
        print(f"{tag} {n}: MA {r['ma']:.3f} (uniform {r['ma_best_uniform']:.3f}), e_ratio {r['e_ratio']:.3f}, "
              f"PSNRm {r['psnr_masked']:.2f}, fit {r['fit_s']:.0f} s (wall {time.time() - t:.0f} s)", flush=True)
print(f"total {time.time() - t0:.0f} s")
