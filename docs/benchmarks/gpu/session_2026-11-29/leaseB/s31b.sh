#!/bin/bash
# session 31, lease B (a fresh H200): the CUDA warm-up's time and the first fit after it; the one-run table at the
# screened starts; foam_bar and bow_tie of the suite with the parts' clear-drop rule
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
CACHE=$(python3 -c "import warp as wp; print(wp.config.kernel_cache_dir)")
echo "kernel cache $CACHE: $(ls $CACHE 2>/dev/null | wc -l) entries"
T0=$(date +%s.%N)
python3 -c "from physinteract_usd.simulation import warm_kernels; print('compiled:', ', '.join(warm_kernels('cuda')))"
T1=$(date +%s.%N)
echo "warm_kernels(cuda) wall $(python3 -c "print(round($T1-$T0,1))") s; cache $(ls $CACHE | wc -l) entries"
ls $CACHE > /tmp/cache_before.txt
S=/tmp/sm/scene.usda; mkdir -p /tmp/sm
python3 -m physinteract_usd init $S --capture samples/foam_bar --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > /dev/null 2>&1
T0=$(date +%s.%N)
python3 -m physinteract_usd fit $S --contact-from samples/foam_bar/gt --device cuda --json --yes > /tmp/sm/fit.json 2> /tmp/sm/fit.err
T1=$(date +%s.%N)
python3 - $T0 $T1 <<'PY'
import json, sys
t0, t1 = map(float, sys.argv[1:3])
txt = open("/tmp/sm/fit.json").read(); d = json.loads(txt[txt.index("{"):])
print(f"first fit after warm-up: CLI wall {t1-t0:.1f} s, fit clock {d['runtime_s']:.1f} s, phases {d.get('phases_s')}")
PY
ls $CACHE > /tmp/cache_after.txt
echo "modules compiled by that fit (new cache entries):"; comm -13 /tmp/cache_before.txt /tmp/cache_after.txt
cp /tmp/sm/fit.err $OUT/first_fit.err
python3 benchmarks/gpu_bench.py --out $OUT/bench --deadline 400 --probes .dev/probes
T0=$(date +%s)
timeout -s INT 150 python3 benchmarks/stall_suite.py --scenes foam_bar --device cuda --size small --frames 14 --synth-fit-grid 128 \
  --grid auto --iterations 20 --work /tmp/ss1 --out $OUT/suite1.jsonl --jobs 1 --variants "" > $OUT/suite1.out 2>&1 &
timeout -s INT 150 python3 benchmarks/stall_suite.py --scenes bow_tie --device cuda --size small --frames 14 --synth-fit-grid auto \
  --grid auto --iterations 20 --work /tmp/ss2 --out $OUT/suite2.jsonl --jobs 1 --variants "" > $OUT/suite2.out 2>&1 &
wait
echo "suite scenes $(( $(date +%s) - T0 )) s"
mkdir -p $OUT/logs; cp /tmp/ss1/foam_bar/foam_bar.log /tmp/ss2/bow_tie/bow_tie.log $OUT/logs/ 2>/dev/null
grep -h "starts:\|parts start\|trend start" $OUT/logs/*.log | cut -c1-300
cat $OUT/suite1.jsonl $OUT/suite2.jsonl 2>/dev/null | python3 -c "import sys,json; [print(r['scene'], r['ma'], r.get('fit_s'), r.get('error')) for r in map(json.loads, sys.stdin)]"
