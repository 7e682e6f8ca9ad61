#!/bin/bash
# session 31, lease C (a fresh H200): which Warp modules the first CUDA fit still compiles after warm_kernels('cuda');
# the small and paper rows again; the paper fit with the 29th session's starts order on the same stage (A/B, same host)
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
python3 - <<'PY' 2>&1 | grep -v "^   \|^Warp \|Devices\|Kernel cache\|CUDA Toolkit"
import time, warp as wp
wp.config.log_level = wp.LOG_INFO
t = time.time()
from physinteract_usd.simulation import warm_kernels
print("compiled:", warm_kernels("cuda"), f"warm_kernels wall {time.time() - t:.1f} s")
PY
S=/tmp/sm/scene.usda; mkdir -p /tmp/sm
python3 -m physinteract_usd init $S --capture samples/foam_bar --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > /dev/null 2>&1
python3 - $S > /tmp/sm/first.log 2>&1 <<'PY'
import sys, time, warp as wp
wp.config.log_level = wp.LOG_INFO
t = time.time()
from physinteract_usd.cli import main
main(["fit", sys.argv[1], "--contact-from", "samples/foam_bar/gt", "--device", "cuda", "--json", "--yes"])
print(f"FIRST_FIT_WALL {time.time() - t:.1f}", file=sys.stderr)
PY
echo "first fit after the warm-up: module loads (compiled / cached), ms:"
grep -o "Module [^ ]* [0-9a-f]* load on device '[^']*' took [0-9.]* ms *([a-z]*)" /tmp/sm/first.log | sort | uniq -c | sort -k9 -n -r | head -30
grep -o '"runtime_s": [0-9.]*' /tmp/sm/first.log; grep FIRST_FIT_WALL /tmp/sm/first.log
python3 -c "import json,re; t=open('/tmp/sm/first.log').read(); i=t.index('\"phases_s\"'); print(t[i:i+260])"
python3 benchmarks/gpu_bench.py --out $OUT/bench --deadline 330 --skip probes,sim,render,batch
echo "=== paper, the 29th session's starts order (parts first), same stage, --fresh"
T0=$(date +%s.%N)
python3 -m physinteract_usd fit /tmp/gpu_bench/paper/scene.usda --contact-from /tmp/gpu_bench/paper_hemp_rope/gt --device cuda \
  --json --yes --fresh --iterations 20 --starts-order parts-first > $OUT/paper_pf.log 2>&1
T1=$(date +%s.%N)
echo "parts-first paper fit CLI wall $(python3 -c "print(round($T1-$T0,1))") s"
grep -h "starts:\|parts start\|trend start" $OUT/paper_pf.log $OUT/bench/paper_fit.log | cut -c1-220
grep -o '"runtime_s": [0-9.]*\|"final_loss": [0-9.e-]*' $OUT/paper_pf.log $OUT/bench/paper_fit.log
python3 -c "import json; t=open('$OUT/paper_pf.log').read(); i=t.index('\"phases_s\"'); print('parts-first', t[i:i+260])"
cp /tmp/sm/first.log $OUT/first_fit.log
cd $OUT && tar czf bench.tgz bench && rm -rf bench
