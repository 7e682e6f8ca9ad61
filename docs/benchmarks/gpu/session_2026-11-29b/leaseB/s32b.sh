#!/bin/bash
# session 32, lease B (a fresh H200): the warm-up (block-size fix 603e219) and a fresh machine's first fit, then the
# one-run table (gpu_bench.py) with each fit's gradient iterations' seconds
export PYTHONUNBUFFERED=1
OUT0=$OUT
PHYSINTERACT_WARP_LOG=info OUT=$OUT0/first bash benchmarks/gpu_first_fit.sh
for k in 1 2; do echo "fit $k: $(cat $OUT0/first/fit_$k.json $OUT0/first/fit_$k.err | grep -c '(compiled)') compiled, $(cat $OUT0/first/fit_$k.json $OUT0/first/fit_$k.err | grep -c '(cached)') cached"; done
cat $OUT0/first/fit_1.json $OUT0/first/fit_1.err | grep "(compiled)" | head
python3 benchmarks/gpu_bench.py --out $OUT0/bench --deadline 490 --probes .dev/probes
cd $OUT0 && tar czf raw.tgz first bench && rm -rf first bench
