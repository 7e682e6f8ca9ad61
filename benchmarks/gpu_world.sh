#!/usr/bin/env bash
# The world suite on a GPU machine, end to end under one deadline (#23):
#     OUT=/dir bash benchmarks/gpu_world.sh SPLIT SEEDS DEADLINE_S
#     OUT=/dir bash benchmarks/gpu_world.sh dev 0-23 540
#     OUT=/dir bash benchmarks/gpu_world.sh validation 0-23 540      # the final table: reads it with --final
# Per seed, one worker: `world_suite.py generate` (synth --random/--validation SEED, --device cuda),
# `world_suite.py extract` (init with the capture's suggested settings, extract, compared with the
# truth) and `world_fit.py` (fit from the extracted interaction, ITER iterations, evaluate: MA and
# masked PSNR). JOBS workers share the GPU (the simulator is launch-bound: several processes keep
# it busy; extraction is CPU work). Rows are written per seed as each step ends, so whatever ends
# before the deadline is in the table; at DEADLINE_S - 45 s the workers are stopped (a fit by SIGTERM: it writes its
# best iterate, its row says stopped_by) and
# `world_suite.py table --fits` prints the table (also into $OUT/world_<split>.md, with the rows as
# JSON and the logs). Captures already generated in WORK are reused (a warm machine's second call).
# Env: OUT (default out/gpu_world), WORK (default /tmp/world_<split>), ITER (fit iterations, 25),
# JOBS (4), DEVICE (cuda; cpu for a local smoke test), FIT_SETTINGS (FitSettings overrides for
# world_fit.py, e.g. search_evals=2,confidence_probes=0 for a smoke test, schedule=select), GRID (init's
# --grid for every capture, e.g. auto; default the capture's suggested grid), MAX_PARTICLES (its cap), TRUTH_FOR_AUTO (synth
# --truth-for-auto N: the truth finer than that auto fit too; with GRID=auto the default is MAX_PARTICLES (60000 unset); 0: today's truths), TRUTH_SWEEP (1: world_fit.py --truth-sweep), TIMING (rules, model or hybrid: extract's
# timing method, world_suite.py --timing; default the code's), NOFIT (1: generate and
# extract only; a second call on the same WORK then fits, the extraction rows kept).
# TRUE_CONTACTS (1: world_fit.py --true-contacts: the fit from the truth's interaction and floor, the material
# alone), MIN_E_TRUE (world_fit.py --min-e-true: fit only captures whose true median E is at least this, e.g. 1e5),
# NGPUS (a host of several GPUs: seed s on GPU s mod NGPUS), GPUS (a list, e.g. 1,2,3: seed s on the list's (s mod
# its length)-th GPU, the others left to another job). SETTLE (1: every truth settled before frame 0; 0: none,
# as the tables before the 37th session; unset: as each seed draws it, 3 of 4). ROWS (default $WORK/rows: the rows and logs; a second
# variant on the same captures, e.g. PHYSINTERACT_PIN_RULE=1,0, takes its own ROWS so that its fits are not skipped
# as already done).
# Needs python3 with torch, warp, usd-core, opencv, trimesh, scipy, scikit-image on PYTHONPATH.
set -u
SPLIT="${1:?split: dev or validation}"
SEEDS="${2:?seeds, e.g. 0-23}"
DEADLINE="${3:-540}"
OUT="${OUT:-out/gpu_world}"
WORK="${WORK:-/tmp/world_$SPLIT}"
ITER="${ITER:-25}"
JOBS="${JOBS:-4}"
DEVICE="${DEVICE:-cuda}"
FIT_SETTINGS="${FIT_SETTINGS:-}"
GRID="${GRID:-}"
MAX_PARTICLES="${MAX_PARTICLES:-}"
TRUTH_FOR_AUTO="${TRUTH_FOR_AUTO-}"   # synth --truth-for-auto N: the truth finer than init --grid auto's fit at that cap
# With GRID=auto the truth is made finer than that fit by default (the 23rd session's dev read: with today's truths,
# 1.1-2.8x coarser than the fit, the ropes' E came out 0.38-0.53x and MA 0; with truths finer, 0.81-0.92x and MA 0.8-1;
# generation 16 -> 24 s a capture on an H200). TRUTH_FOR_AUTO=0 keeps the old truths (to compare with earlier tables).
if [ "$GRID" = auto ] && [ -z "$TRUTH_FOR_AUTO" ]; then TRUTH_FOR_AUTO="${MAX_PARTICLES:-60000}"; fi
[ "$TRUTH_FOR_AUTO" = 0 ] && TRUTH_FOR_AUTO=""
TRUTH_SWEEP="${TRUTH_SWEEP:-}"
# SETTLE: 1 every truth settled before frame 0, 0 none (the tables before the 37th session), unset: as each seed draws
SETTLE_FLAG=""
[ "${SETTLE:-}" = 1 ] && SETTLE_FLAG="--settle"
[ "${SETTLE:-}" = 0 ] && SETTLE_FLAG="--no-settle"
NOFIT="${NOFIT:-}"
TIMING="${TIMING:-}"
PY="${PYTHON:-python3}"
T_START=$(date +%s)
ROWS="${ROWS:-$WORK/rows${TRUTH_FOR_AUTO:+_fine$TRUTH_FOR_AUTO}}"   # rows per truth: a capture made again for another truth is fitted again
mkdir -p "$OUT" "$ROWS"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
FINAL=""
[ "$SPLIT" = validation ] && FINAL="--final"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | sed 's/^/device: /'
echo "split $SPLIT seeds $SEEDS deadline ${DEADLINE}s iterations $ITER jobs $JOBS device $DEVICE work $WORK"

SEED_LIST=$($PY -c "import sys; sys.path.insert(0, 'benchmarks'); from world_suite import parse_seeds; print(' '.join(map(str, parse_seeds('$SEEDS'))))") || exit 2

END=$(( T_START + DEADLINE - 45 ))   # the workers' steps end here (a fit stopped by SIGTERM writes its best iterate)

step() {  # step SECONDS_GRACE cmd...: run cmd until END (SIGTERM, then SIGKILL after the grace)
  local grace=$1 left
  shift
  left=$(( END - $(date +%s) ))
  [ "$left" -gt 3 ] || return 124
  timeout -s TERM -k "$grace" "$left" "$@"
}

worker() {
  local s=$1 n t0 t1 t2
  n=$(printf '%s_%04d' "$SPLIT" "$s")
  # on a host of several GPUs (NGPUS > 1) seed s runs on GPU s mod NGPUS
  if [ -n "${GPUS:-}" ]; then  # GPUS=1,2,3: seed s on the (s mod 3)-th of those (another job has the rest)
    local g=(${GPUS//,/ })
    export CUDA_VISIBLE_DEVICES=${g[$(( s % ${#g[@]} ))]}
  elif [ "${NGPUS:-1}" -gt 1 ]; then
    export CUDA_VISIBLE_DEVICES=$(( s % NGPUS ))
  fi
  {
    t0=$(date +%s)
    step 5 $PY benchmarks/world_suite.py generate --split "$SPLIT" --seeds "$s" --work "$WORK" --device "$DEVICE" \
      ${TRUTH_FOR_AUTO:+--truth-for-auto "$TRUTH_FOR_AUTO"} $SETTLE_FLAG || return
    t1=$(date +%s)
    step 5 $PY benchmarks/world_suite.py extract --split "$SPLIT" $FINAL --seeds "$s" --work "$WORK" \
      --json "$ROWS/extract_$n.json" --device "$DEVICE" ${GRID:+--grid "$GRID"} \
      ${MAX_PARTICLES:+--max-particles "$MAX_PARTICLES"} ${TIMING:+--timing "$TIMING"} || return
    t2=$(date +%s)
    [ -n "$NOFIT" ] && { echo "$n: generate $((t1 - t0)) s, extract $((t2 - t1)) s (no fit)"; return; }
    step 15 $PY benchmarks/world_fit.py --work "$WORK" --split "$SPLIT" $FINAL --seeds "$s" --iterations "$ITER" \
      --json "$ROWS/fit_$n.json" --device "$DEVICE" --fit-settings "$FIT_SETTINGS" ${TRUTH_SWEEP:+--truth-sweep} ${TRUE_CONTACTS:+--true-contacts} \
      ${MIN_E_TRUE:+--min-e-true "$MIN_E_TRUE"}
    echo "$n: generate $((t1 - t0)) s, extract $((t2 - t1)) s, fit $(( $(date +%s) - t2 )) s"
  } > "$ROWS/$n.log" 2>&1
  grep -E "^$n|Error|error" "$ROWS/$n.log" | head -5
}
export -f worker step
export TRUE_CONTACTS MIN_E_TRUE NGPUS GPUS SPLIT WORK ROWS ITER DEVICE PY FINAL FIT_SETTINGS END GRID MAX_PARTICLES TRUTH_SWEEP NOFIT TIMING TRUTH_FOR_AUTO SETTLE_FLAG

# the first seed alone until its capture is written (Warp's kernel cache is built once, not by
# every worker at the same time), then the others, JOBS at a time
FIRST=${SEED_LIST%% *}
REST=${SEED_LIST#"$FIRST"}
bash -c "worker $FIRST" &
PID_FIRST=$!
while kill -0 $PID_FIRST 2>/dev/null && [ ! -e "$WORK/$(printf '%s_%04d' "$SPLIT" "$FIRST")/transforms.json" ] \
      && [ "$(date +%s)" -lt "$END" ]; do sleep 2; done
if [ -n "${REST// /}" ]; then
  echo $REST | tr ' ' '\n' | xargs -P "$JOBS" -I{} bash -c 'worker {}'
fi
wait $PID_FIRST 2>/dev/null

# merge the per-seed rows and print the table
$PY - "$ROWS" "$OUT" "$SPLIT" <<'EOF'
import json, sys
from pathlib import Path
rows, out, split = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
for kind in ("extract", "fit"):
    merged = []
    for p in sorted(rows.glob(f"{kind}_*.json")):
        try:
            merged += json.loads(p.read_text())
        except ValueError:
            pass
    (out / f"world_{split}_{kind}.json").write_text(json.dumps(merged, indent=1))
    print(f"{kind}: {len(merged)} rows")
EOF
$PY benchmarks/world_suite.py table --split "$SPLIT" $FINAL --work "$WORK" --json "$OUT/world_${SPLIT}_extract.json" \
  --fits "$OUT/world_${SPLIT}_fit.json" | tee "$OUT/world_${SPLIT}.md"
$PY -c "import json, sys; sys.path.insert(0, 'benchmarks'); import world_fit; \
print(world_fit.e_table([r for r in json.load(open('$OUT/world_${SPLIT}_fit.json')) if 'ma' in r]))" | tee -a "$OUT/world_${SPLIT}.md"
cat "$ROWS"/*.log > "$OUT/world_${SPLIT}_logs.txt" 2>/dev/null
echo "total $(( $(date +%s) - T_START )) s"
