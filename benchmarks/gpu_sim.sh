#!/usr/bin/env bash
# GPU runs for the simulator (issue 3). Run from the repo root on the GPU host:
#     OUT=/some/dir bash benchmarks/gpu_sim.sh
# Needs python3 with torch, warp and usd-core importable (no network). Every part writes to $OUT
# and stdout; a part that fails does not stop the others. Budget: < 4 minutes in all (most of it
# is the first compilation of the Warp kernels for CUDA, cached in ~/.cache/warp afterwards).
set -x
OUT="${OUT:-out/gpu_sim}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
PROBE=.dev/probes/mpm_probe.py
[ -f "$PROBE" ] || PROBE=../shared/device/mpm_probe.py

{ nvidia-smi -L; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; } 2>&1 | tee "$OUT/gpu.txt"
python3 -c "import warp, torch; print('warp', warp.__version__, 'torch', torch.__version__)" 2>&1 | tee -a "$OUT/gpu.txt"

# 1. the baseline probe (naive MLS-MPM, wp.Tape backward, CUDA graphs), 100 substeps
timeout 60 python3 "$PROBE" cuda 2000 32 100 2>&1 | tee "$OUT/probe_2k_32.txt"
timeout 60 python3 "$PROBE" cuda 15000 100 100 2>&1 | tee "$OUT/probe_15k_100.txt"

# 2. the simulator's benchmark at matching sizes (the probe re-timed in the same run as baseline)
timeout 150 python3 benchmarks/bench_sim.py --device cuda --sizes 2000:32 15000:100 --frames 2 --substeps 50 \
    --reps 3 --probe "$PROBE" 2>&1 | tee "$OUT/bench_sim_cuda.txt"

# 3. CPU vs CUDA consistency: a 100-substep rollout (and its gradients) on both devices
REF=.dev/probes/sim_cpu_ref.npz; timeout 120 python3 benchmarks/check_sim_cuda.py --device cuda:0 $([ -f $REF ] && echo --cpu-ref $REF) 2>&1 | tee "$OUT/check_sim_cuda.txt"

ls -l "$OUT"
