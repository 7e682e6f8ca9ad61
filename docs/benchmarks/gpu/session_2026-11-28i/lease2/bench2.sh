#!/bin/bash
# lease 2 (session 30): the one-run table (gpu_bench.py) with the phases, at HEAD
export PYTHONUNBUFFERED=1

ls .dev/probes
python3 benchmarks/gpu_bench.py --out $OUT/bench --deadline 555 --probes .dev/probes
