#!/usr/bin/env bash
# #24, stiff objects (true median E >= 1e5 Pa) fit too soft from the TRUE interaction: which part of our model puts the
# E low, on DEVELOPMENT captures only (dev seeds 220-259 whose drawn E is stiff and that something holds: 222 clamped
# block, 224 hanging ring, 231 anchored sheet, 237 clamped block, 246 hanging sheet, 247 hanging bar, 255 clamped
# sheet, 258 anchored sheet; all pointAdherent). On one host of 4 GPUs, each call under 9 min, rows appended as they end:
#
#     OUT=/dir CALL=gen   bash benchmarks/gpu_stiff24.sh   # generate the 8 captures on 4 GPUs (~3-5 min)
#     OUT=/dir CALL=sim   bash benchmarks/gpu_stiff24.sh   # world_simcheck.py: 3-D error vs E x 1/4..2, pin rules
#                                                           # default / band / gain1, grid auto within 15k particles (~6 min)
#     OUT=/dir CALL=fine  bash benchmarks/gpu_stiff24.sh   # default and band at grid x1.5, and at the truth's substeps
#     OUT=/dir CALL=sweep bash benchmarks/gpu_stiff24.sh   # world_bias.py: the truth sweep (the loss, renderer included)
#                                                           # per pin rule default / band / gain1, grid auto within 15k
#
# then the fits themselves, before / after, with gpu_world.sh on the same captures (their own ROWS each):
#     WORK=/tmp/stiff24 ROWS=/tmp/stiff24/rows_default OUT=$OUT/fit_default NGPUS=4 JOBS=8 TRUE_CONTACTS=1 MIN_E_TRUE=1e5 \
#       TRUTH_SWEEP=1 GRID=auto MAX_PARTICLES=15000 bash benchmarks/gpu_world.sh dev 222,224,231,237,246,247,255,258 540
#     PHYSINTERACT_PIN_RULE=band WORK=/tmp/stiff24 ROWS=/tmp/stiff24/rows_band OUT=$OUT/fit_band ... (the same)
# (the clamp band: the rule that matches the Timoshenko beam; world_fit.py rows record the rule as pin_rule).
# Measured on the CPU first (dev_0143 / 0164 / 0269 / 0255 / 0141 / 0153): docs/benchmarks/world_fits.md, top.
#
# WORK (default /tmp/stiff24) holds the captures between calls (a warm machine); SEEDS overrides the list; DEVICE cpu
# and CAP for a CPU smoke: PATH=.venv/bin:$PATH OUT=/tmp/gs DEVICE=cpu CAP=600 SEEDS=269 CALL=sim bash benchmarks/gpu_stiff24.sh
set -u
OUT="${OUT:-out/gpu_stiff24}"
WORK="${WORK:-/tmp/stiff24}"
CALL="${CALL:-sim}"
DEVICE="${DEVICE:-cuda}"
CAP="${CAP:-15000}"
LIMIT="${LIMIT:-520}"
SEEDS="${SEEDS:-222,224,231,237,246,247,255,258}"
NGPUS="${NGPUS:-4}"
GPU_OFFSET="${GPU_OFFSET:-0}"   # the first GPU of the NGPUS used (another job may hold the others)
PY="${PYTHON:-python3}"
mkdir -p "$OUT" "$WORK"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sed 's/^/device: /'
git rev-parse --short HEAD 2>/dev/null | sed 's/^/code: /'
echo "call $CALL seeds $SEEDS work $WORK cap $CAP limit ${LIMIT}s"
# Warp's kernel cache built once before the workers start (not by eight processes at the same time)
$PY -c "from physinteract_usd import simulation; simulation.warm_kernels('$DEVICE')" > /dev/null 2>&1 || true
k=0
for s in ${SEEDS//,/ }; do
  gpu=$(( GPU_OFFSET + k % NGPUS )); k=$(( k + 1 ))
  [ "$DEVICE" = cuda ] && export CUDA_VISIBLE_DEVICES=$gpu
  case "$CALL" in
    gen)   timeout -s TERM "$LIMIT" $PY benchmarks/world_suite.py generate --split dev --seeds "$s" --work "$WORK" \
             --device "$DEVICE" > "$OUT/gen_$s.log" 2>&1 & ;;
    # one process per rule, one after the other (a process writes its rows when it ends: what the limit cuts is one rule)
    sim)   ( for r in default band gain1; do
               [ $(( LIMIT - SECONDS )) -gt 5 ] && timeout -s TERM $(( LIMIT - SECONDS )) $PY benchmarks/world_simcheck.py --work "$WORK" --seeds "$s" \
                 --cap "$CAP" --factors 0.25,0.5,1,2 --rules $r --device "$DEVICE" --scratch "$WORK/sc_$s" \
                 --json "$OUT/simcheck.jsonl"; done ) > "$OUT/sim_$s.log" 2>&1 & ;;
    fine)  ( for v in "default 1.5 fit" "band 1.5 fit" "default 1 truth" "band 1 truth"; do
               set -- $v
               [ $(( LIMIT - SECONDS )) -gt 5 ] && timeout -s TERM $(( LIMIT - SECONDS )) $PY benchmarks/world_simcheck.py --work "$WORK" --seeds "$s" \
                 --cap "$CAP" --factors 0.25,0.5,1,2 --rules $1 --grid-scales $2 --steps $3 --device "$DEVICE" \
                 --scratch "$WORK/scf_$s" --json "$OUT/simcheck_fine.jsonl"; done ) > "$OUT/fine_$s.log" 2>&1 & ;;
    sweep) ( for r in default band gain1; do
               [ $(( LIMIT - SECONDS )) -gt 5 ] && timeout -s TERM $(( LIMIT - SECONDS )) $PY benchmarks/world_bias.py --work "$WORK" --seeds "$s" \
                 --caps "$CAP" --rules $r --device "$DEVICE" --scratch "$WORK/sw_$s" --json "$OUT/sweep.jsonl"
             done ) > "$OUT/sweep_$s.log" 2>&1 & ;;
    *) echo "CALL must be gen, sim, fine or sweep" >&2; exit 2 ;;
  esac
done
wait
[ "$CALL" = gen ] && { cat "$OUT"/gen_*.log | grep -v Warp; exit 0; }
$PY - "$OUT" "$CALL" <<'PYEOF'
import json, sys
from pathlib import Path
sys.path.insert(0, "benchmarks")
out, call = Path(sys.argv[1]), sys.argv[2]
name = {"sim": "simcheck.jsonl", "fine": "simcheck_fine.jsonl", "sweep": "sweep.jsonl"}[call]
rows = [json.loads(l) for l in (out / name).read_text().splitlines() if l.strip()] if (out / name).exists() else []
if call == "sweep":
    import world_bias
    print(world_bias.table(rows))
else:
    import world_simcheck
    print(world_simcheck.table(rows))
PYEOF
