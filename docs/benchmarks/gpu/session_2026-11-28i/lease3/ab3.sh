#!/bin/bash
# lease 3 (session 30): the paper row A/B in one lease: tiled probes (screen, confidence) on / off, per-start seconds
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
C=/tmp/pp/cap
python3 -m physinteract_usd synth hemp_rope $C --size paper --device cuda --force > $OUT/synth.log 2>&1
for t in on off on2; do
  mkdir -p /tmp/pp/$t
  python3 -m physinteract_usd init /tmp/pp/$t/scene.usda --capture $C --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/init_$t.log 2>&1
done
for t in on off on2; do
  if [ $t = off ]; then export PHYSINTERACT_FD_BATCH=never; B=never; else export PHYSINTERACT_FD_BATCH=cuda; B=cuda; fi
  /usr/bin/time -f "wall %e s" python3 - $t $B $C > $OUT/fit_$t.log 2>&1 <<'PY'
import sys, json, time
t0 = time.perf_counter()
from physinteract_usd import api
from physinteract_usd.usd.stage import read_stage
tag, batch, cap = sys.argv[1:4]
st = f"/tmp/pp/{tag}/scene.usda"
out = api.fit(st, iterations=20, contact_from=cap + "/gt", device="cuda", progress=False,
              settings_overrides={"select_sweep_batch": batch})
s = out.summary()
ps = (out.result.model or {}).get("parts_start") or {}
print("RESULT", json.dumps({"tag": tag, "batch": batch, "wall": time.perf_counter() - t0, "runtime": s["runtime_s"],
      "phases": s["phases_s"], "trend_s": ps.get("seconds"), "trend_forwards": ps.get("forwards"),
      "parts_s": (ps.get("parts_start") or {}).get("seconds"), "used": ps.get("used"), "log_e": ps.get("log_e"),
      "final_loss": s["final_loss"], "psnr_masked": s["psnr_masked"]}))
PY
  grep -E "RESULT|wall" $OUT/fit_$t.log
done
