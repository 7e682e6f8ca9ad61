"""session 36, lease C: the settled captures again after the scan fix (its splats deformed as frame 0 shows them),
preloaded, suggested grid, true contacts, 60 iterations (s36a.py's rows, the first part)."""
import json, sys, time
from pathlib import Path
sys.path.insert(0, "benchmarks")
from physinteract_usd import api
from world_suite import prepare
from world_fit import fit_one

out = Path(sys.argv[1])
t0 = time.time()
work = Path("/tmp/wset")
for s in (546, 549):
    n = f"dev_{s:04d}"
    api.synth(None, work / n, random=s, split="dev", device="cuda", force=True, log=lambda *a: None,
              overrides={"settle": True})
    prepare(work, n)
    t = time.time()
    r = fit_one(work, n, 60, 0, "cuda", log=lambda *a, **k: None, true_contacts=True)
    (out / f"pre_{n}.json").write_text(json.dumps(r, indent=1, default=str))
    print(f"pre {n}: MA {r['ma']:.3f} (uniform {r['ma_best_uniform']:.3f}), e_ratio {r['e_ratio']:.3f}, "
          f"PSNRm {r['psnr_masked']:.2f}, fit {r['fit_s']:.0f} s (wall {time.time() - t:.0f} s), "
          f"probe {r.get('model', {}).get('uniform_probe_interval')}, total {time.time() - t0:.0f} s", flush=True)
