"""session 36, lease B: is dev_0546's flat preloaded landscape its grid's (16: 1.8 cells across; auto chooses 36)?
The settled captures at init --grid auto, preloaded then stress-free, fitted from their true contacts (60 iterations)."""
import json, sys, time
from pathlib import Path
sys.path.insert(0, "benchmarks")
from physinteract_usd import api
from world_suite import prepare
from world_fit import fit_one

out = Path(sys.argv[1])
t0 = time.time()
work = Path("/tmp/wset")
jobs = [(546, True), (546, False), (549, True), (534, True)]
made = set()
for s, pre in jobs:
    n = f"dev_{s:04d}"
    if time.time() - t0 > 430:
        print("deadline", flush=True)
        break
    if s not in made:
        api.synth(None, work / n, random=s, split="dev", device="cuda", force=True, log=lambda *a: None,
                  overrides={"settle": True})
        made.add(s)
    g = json.loads((work / n / "gt" / "gt.json").read_text()) if (work / n / "gt").exists() else \
        json.loads((work / f"{n}.gt" / "gt.json").read_text())
    if (work / n / "gt").exists():
        prepare(work, n)
    gp = work / f"{n}.gt" / "gt.json"
    g = json.loads(gp.read_text())
    g["suggested_init"]["preload"] = pre
    gp.write_text(json.dumps(g))
    prepare(work, n, grid="auto")
    t = time.time()
    try:
        r = fit_one(work, n, 60, 0, "cuda", log=lambda *a, **k: None, true_contacts=True)
    except Exception as exc:  # noqa: BLE001
        print(f"{n} preload={pre}: ERROR {type(exc).__name__}: {exc}", flush=True)
        continue
    tag = "pre" if pre else "free"
    (out / f"{tag}_auto_{n}.json").write_text(json.dumps(r, indent=1, default=str))
    print(f"{tag} auto {n}: MA {r['ma']:.3f} (uniform {r['ma_best_uniform']:.3f}), e_ratio {r['e_ratio']:.3f}, "
          f"PSNRm {r['psnr_masked']:.2f}, fit {r['fit_s']:.0f} s (wall {time.time() - t:.0f} s), "
          f"probe {r.get('model', {}).get('uniform_probe_interval')}", flush=True)
print(f"total {time.time() - t0:.0f} s")
