#!/usr/bin/env bash
# The small synthetic suite on a GPU, resumable across calls (each call does what fits in its time):
#     OUT=/dir [GRID=N|auto] [ITERATIONS=60] [FRAMES=N] bash benchmarks/gpu_suite.sh SECONDS [scene,scene,...]
# GRID: init's grid instead of the capture's suggested one (rows are kept per grid, so GRID=24 and
# GRID=auto share the captures); FRAMES: frames of the captures synth makes (not of existing ones);
# SYNTH_FIT_GRID=N: captures whose truth is simulated on a cell 0.7x grid N's (in /tmp/suite_small_gtN).
# Runs benchmarks/suite.py (synth -> init -> fit -> evaluate per scene, through the CLI) on CUDA in
# /tmp/suite_small (kept while the machine stays warm) and copies results.jsonl, the logs and the
# table to $OUT. Needs python3 with torch, warp, usd-core, opencv, trimesh on PYTHONPATH.
set -u
OUT="${OUT:-out/gpu_suite}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
SYNTH_FIT_GRID="${SYNTH_FIT_GRID:-}"
W="/tmp/suite_small${SYNTH_FIT_GRID:+_gt$SYNTH_FIT_GRID}"
LIMIT="${1:-540}"
SCENES="${2:-}"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | sed 's/^/device: /'
GRID="${GRID:-}"
ITERATIONS="${ITERATIONS:-60}"
FRAMES="${FRAMES:-}"
MD="suite_small_cuda${GRID:+_grid_$GRID}.md"
timeout "$LIMIT" python3 benchmarks/suite.py --size small --device cuda --out "$W" --iterations "$ITERATIONS" \
  ${SCENES:+--scenes "$SCENES"} ${GRID:+--grid "$GRID"} ${FRAMES:+--frames "$FRAMES"} \
  ${SYNTH_FIT_GRID:+--synth-fit-grid "$SYNTH_FIT_GRID"} --write "$W/$MD"
echo "suite exit $?"
cp "$W"/results.jsonl "$W"/*.log "$W"/suite_small_cuda*.md "$OUT"/ 2>/dev/null
ls "$OUT"
