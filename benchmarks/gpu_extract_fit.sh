#!/usr/bin/env bash
# Extraction measured against the truth and fits from extracted vs ground-truth contacts, on a GPU:
#     OUT=/dir bash benchmarks/gpu_extract_fit.sh SECONDS scene,scene,...
# Runs benchmarks/eval_extract.py --device cuda --fit all (60 iterations) in /tmp/eval_extract_gpu
# (captures kept while the machine stays warm, so a later call reuses them) and writes the rows
# to $OUT/rows_<first scene>.json after every scene (a call cut short keeps what it measured).
# SOURCES picks the fits (default extracted,gt; "" for none), MIX adds --mix parts (e.g. support,hand),
# SEED the fits' seed, FIT_SETTINGS FitSettings overrides (key=value,...).
# Needs python3 with torch, warp, usd-core, opencv, trimesh, scipy on PYTHONPATH.
set -u
OUT="${OUT:-out/gpu_extract}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
LIMIT="${1:-560}"
SCENES="${2:?scenes}"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | sed 's/^/device: /'
timeout "$LIMIT" python3 benchmarks/eval_extract.py --device cuda --work /tmp/eval_extract_gpu --keep \
  --scenes "$SCENES" --fit all --iterations 60 --fit-sources "${SOURCES-extracted,gt}" --mix "${MIX:-}" --seed "${SEED:-0}" --fit-settings "${FIT_SETTINGS:-}" --json "$OUT/rows_${SCENES%%,*}${MIX:+_mix}${SEED:+_seed$SEED}${FIT_SETTINGS:+_fs}.json" 2>&1 | grep -v "^|"
echo "exit ${PIPESTATUS[0]}"
