#!/bin/bash
# session 34, lease A (a fresh H200): the set-up's CUDA warm-up (as scripts/setup.sh leaves a GPU machine), then the
# one-run table (gpu_bench.py) at head, with the issue's small capture (36 frames, 60 iterations) as its own row (#26)
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
T0=$(date +%s.%N)
python3 -c "from physinteract_usd.simulation import warm_kernels; print('compiled:', ', '.join(warm_kernels('cuda')))"
echo "warm-up $(python3 -c "import time;print(round(time.time()-$T0,1))") s"
python3 benchmarks/gpu_bench.py --out $OUT/bench --deadline 540 --probes .dev/probes
cd $OUT && tar czf raw.tgz bench && cp bench/gpu_bench.md bench/gpu_bench.json . && rm -rf bench
