#!/bin/bash
# session 35, lease A run 1: the 12 named scenes (the 22nd session's standard) with the trend start's simplex extended
# past its cap while still descending (FitSettings.trend_extend, default on at this commit); baseline: the 34th
# session's lease B rows (62f8411; nothing in the fit changed since but this) (#24)
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
T0=$(date +%s.%N)
python3 -c "from physinteract_usd.simulation import warm_kernels; print('compiled:', ', '.join(warm_kernels('cuda')))"
echo "warm-up $(python3 -c "import time;print(round(time.time()-$T0,1))") s"
OUT=$OUT/suite LIMIT=480 bash benchmarks/gpu_suite12.sh
