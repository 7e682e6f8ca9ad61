#!/usr/bin/env bash
# The small synthetic suite on a GPU, resumable across calls (each call does what fits in its time):
#     OUT=/dir bash benchmarks/gpu_suite.sh SECONDS [scene,scene,...]
# Runs benchmarks/suite.py (synth -> init -> fit -> evaluate per scene, through the CLI) on CUDA in
# /tmp/suite_small (kept while the machine stays warm) and copies results.jsonl, the logs and the
# table to $OUT. Needs python3 with torch, warp, usd-core, opencv, trimesh on PYTHONPATH.
set -u
OUT="${OUT:-out/gpu_suite}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
W=/tmp/suite_small
LIMIT="${1:-540}"
SCENES="${2:-}"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | sed 's/^/device: /'
timeout "$LIMIT" python3 benchmarks/suite.py --size small --device cuda --out "$W" --iterations 60 \
  ${SCENES:+--scenes "$SCENES"} --write "$W/suite_small_cuda.md"
echo "suite exit $?"
cp "$W"/results.jsonl "$W"/*.log "$W"/suite_small_cuda.md "$OUT"/ 2>/dev/null
ls "$OUT"
