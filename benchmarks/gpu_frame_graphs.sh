#!/usr/bin/env bash
# Issue #26: the CLI's small fit with one captured graph per frame (the old path, PHYSINTERACT_FRAME_GRAPHS=0)
# and per frame shape (=1, sim/rollout.py FRAME_GRAPHS), in one run on one GPU, then the Python-issued Warp
# launches per phase of the same fit in-process (benchmarks/count_launches.py --fit). Development data (the
# bundled sample). Usage, from the repository root on the GPU machine:
#     OUT=/tmp/out bash benchmarks/gpu_frame_graphs.sh [REPEATS]      # ~4-5 min on an H200
# Prints a table; writes $OUT/frame_graphs_cli.tsv, $OUT/frame_graphs_launches.json and each fit's log.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-out/frame_graphs}
REPEATS=${1:-2}
DEVICE=${DEVICE:-cuda}; GRID=${GRID:-24}; ITERS=${ITERS:-60}     # (DEVICE=cpu GRID=12 ITERS=2: a CPU smoke test)
mkdir -p "$OUT"
PY=${PYTHON:-python}
CLI="$PY -m physinteract_usd"
W=$(mktemp -d); mkdir -p "$W/base"
$CLI init "$W/base/scene.usda" --capture samples/foam_bar --grid "$GRID" --padding 0.3 --youngs-range 1e3,6e4 \
  --max-poisson 0.4 --density 150 --no-preload > "$OUT/init.log" 2>&1 || { echo "init failed"; cat "$OUT/init.log"; exit 1; }
(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader || echo "$DEVICE") | tee "$OUT/device.txt"
printf "path\trepeat\twall_s\texit\tfit_line\n" > "$OUT/frame_graphs_cli.tsv"
# a first fit warms the kernel caches (not counted)
cp -r "$W/base" "$W/warm"
$CLI fit "$W/warm/scene.usda" --contact-from samples/foam_bar/gt --iterations 5 --device "$DEVICE" > "$OUT/warm.log" 2>&1
for r in $(seq 1 "$REPEATS"); do
  for fg in 0 1; do
    d="$W/r${r}_fg${fg}"; cp -r "$W/base" "$d"
    t0=$EPOCHREALTIME
    PHYSINTERACT_FRAME_GRAPHS=$fg $CLI fit "$d/scene.usda" --contact-from samples/foam_bar/gt --iterations "$ITERS" \
      --device "$DEVICE" > "$OUT/fit_fg${fg}_r${r}.log" 2>&1
    rc=$?
    t1=$EPOCHREALTIME
    line=$(grep -m1 "iterations in" "$OUT/fit_fg${fg}_r${r}.log" | sed 's/^ *//')
    printf "%s\t%s\t%.2f\t%s\t%s\n" "$([ $fg = 1 ] && echo per-shape || echo per-frame)" "$r" \
      "$(awk "BEGIN{print $t1 - $t0}")" "$rc" "$line" >> "$OUT/frame_graphs_cli.tsv"
  done
done
column -t -s $'\t' "$OUT/frame_graphs_cli.tsv"
# launches per phase, both paths in one process (the fit in-process: no CLI start-up)
$PY benchmarks/count_launches.py --fit --device "$DEVICE" --grid "$GRID" --iterations "$ITERS" --repeats 1 \
  --json "$OUT/frame_graphs_launches.json" 2>&1 | tee "$OUT/frame_graphs_launches.log" | grep -v "^Warp"
rm -rf "$W"
