#!/bin/bash
# session 32, lease C: (1) where a CUDA CLI fit's ~7 s outside its phases go (imports, CUDA's and Warp's initialisation);
# (2) the paper row twice as is (no profiler), then with the searched uniform level skipped (the API's settings override)
export PYTHONUNBUFFERED=1
python3 - <<'PY'
import time
t0 = time.perf_counter(); T = {}
import torch; T["import torch"] = time.perf_counter() - t0; t = time.perf_counter()
torch.cuda.init(); x = torch.zeros(1, device="cuda"); torch.cuda.synchronize(); T["torch cuda init + first tensor"] = time.perf_counter() - t; t = time.perf_counter()
import pxr.Usd; T["import pxr.Usd"] = time.perf_counter() - t; t = time.perf_counter()
import warp as wp; T["import warp"] = time.perf_counter() - t; t = time.perf_counter()
import physinteract_usd.cli, physinteract_usd.app.fit, physinteract_usd.fit.optimize, physinteract_usd.simulation; T["import our package (fit path)"] = time.perf_counter() - t; t = time.perf_counter()
from physinteract_usd.devices import quiet_warp_init
quiet_warp_init("cuda"); T["warp init (cuda)"] = time.perf_counter() - t; t = time.perf_counter()
from physinteract_usd.simulation import warm_kernels
warm_kernels("cuda"); T["load the 5 cached modules"] = time.perf_counter() - t; t = time.perf_counter()
import cv2, trimesh; T["import cv2, trimesh"] = time.perf_counter() - t
for k, v in T.items(): print(f"{k:40s} {v:6.2f} s")
print(f"{'total':40s} {time.perf_counter() - t0:6.2f} s")
PY
C=/tmp/pp/cap; S=/tmp/pp/scene.usda; mkdir -p /tmp/pp
python3 -m physinteract_usd synth hemp_rope $C --size paper --device cuda --force > $OUT/psynth.log 2>&1
python3 -m physinteract_usd init $S --capture $C --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/pinit.log 2>&1
for k in 1 2; do
  T=$(date +%s.%N)
  python3 -m physinteract_usd fit $S --contact-from $C/gt --device cuda --json --yes --fresh --iterations 20 > $OUT/paper_$k.log 2>&1
  echo "=== paper fit $k (default): CLI wall $(python3 -c "import time;print(round(time.time()-$T,1))") s"
  python3 -c "import json; t=open('$OUT/paper_$k.log').read(); d=json.loads(t[t.index('\n{'):]); print('runtime', round(d['runtime_s'],1), 'final', d['final_loss'], 'phases', {k: round(v,1) for k,v in d['phases_s'].items()}, 'iter', d['iteration_s'])"
  if [ $k = 1 ]; then python3 -m physinteract_usd evaluate $S --gt $C/gt --device cuda --json 2>/dev/null | python3 -c "import json,sys; t=sys.stdin.read(); d=json.loads(t[t.index('{'):]); print('MA', d.get('ma'), 'masked PSNR', d.get('psnr_masked'))"; fi
done
T=$(date +%s.%N)
python3 - $S $C > $OUT/paper_skip.log 2>&1 <<'PY'
import json, sys
from physinteract_usd import api
o = api.fit(sys.argv[1], contact_from=sys.argv[2] + "/gt", device="cuda", iterations=20, warm=False, yes=True,
            progress=False, keep_best=False, settings_overrides={"skip_searched_uniform": True})
print(json.dumps(o.summary(), indent=2, default=str))
PY
echo "=== paper fit, level 1 skipped (API): wall $(python3 -c "import time;print(round(time.time()-$T,1))") s"
grep "level 1\|trend start\|starts:" $OUT/paper_skip.log | cut -c1-300
python3 -c "import json; t=open('$OUT/paper_skip.log').read(); d=json.loads(t[t.index('\n{'):]); print('runtime', round(d['runtime_s'],1), 'final', d['final_loss'], 'phases', {k: round(v,1) for k,v in d['phases_s'].items()}, 'iter', d['iteration_s'])"
python3 -m physinteract_usd evaluate $S --gt $C/gt --device cuda --json 2>/dev/null | python3 -c "import json,sys; t=sys.stdin.read(); d=json.loads(t[t.index('{'):]); print('MA', d.get('ma'), 'masked PSNR', d.get('psnr_masked'))"
cd $OUT && tar czf raw.tgz paper_*.log psynth.log pinit.log && rm -f paper_*.log
