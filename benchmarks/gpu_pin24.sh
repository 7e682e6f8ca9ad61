#!/bin/bash
# #24: the clamp band in truth AND fit on the 12 suite scenes, for real this time. The 19th session's A/B
# (docs/benchmarks/fit.md, "The clamp band in truth and fit") set PHYSINTERACT_PIN_RULE=band only: the synth's
# truth never read it (synth.generate.GroundTruth.model took SimModel.create's (4, 0)), so its band column was
# band fits against default-rule truths. PHYSINTERACT_TRUTH_PIN_RULE now sets the truth's rule.
# On 4 GPUs: GPU 0/1 truth band + fit band (halves a/b), GPU 2/3 truth band + fit default (the control: the
# default fit of a band truth). The default/default column is stall_default.jsonl of session_2026-11-27f
# (deterministic across sessions: that section). On 2 GPUs: the band/band halves only.
#   OUT=/tmp/o bash benchmarks/gpu_pin24.sh            # from the repo root; ~400-550 s on 4 x H200
set -u
cd "$(dirname "$0")/.."
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | sort | uniq -c; nproc
NG=$(nvidia-smi -L | wc -l)
T0=$(date +%s)
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=2 PHYSINTERACT_TRUTH_PIN_RULE=band
W=${WORK:-/tmp/gpin24}; mkdir -p $OUT/suite
L=$(( ${LIM:-570} - ($(date +%s) - T0) ))
A=foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope
B=balloon,bow_tie,glove,flower,basketball,knit_cap
run() { # fit-rule gpu half cores
  local rule=$1 g=$2 half=$3 cores=$4 sc extra
  if [ $half = a ]; then sc=$A; extra="--synth-fit-grid 128"; else sc=$B; extra=""; fi
  ( PHYSINTERACT_PIN_RULE=$rule GPU_LIST=$g timeout -k 10 $L taskset -c $cores python3 benchmarks/stall_suite.py \
    --scenes $sc --variants "" --device cuda --size small --frames 14 $extra --grid auto --iterations 20 \
    --work $W/tb_$rule$half --out $OUT/suite/stall_tb_$rule.jsonl --jobs 6 > $OUT/suite/suite_tb_${rule}_$half.log 2>&1
    echo "truth band, fit $rule, $half: exit $? $(( $(date +%s) - T0 )) s" ) &
}
if [ "$NG" -ge 4 ]; then
  C=$(( $(nproc --all) / 4 ))
  run band 0 a 0-$((C-1)); run band 1 b $C-$((2*C-1)); run default 2 a $((2*C))-$((3*C-1)); run default 3 b $((3*C))-$((4*C-1))
else
  C=$(( $(nproc --all) / 2 ))
  run band 0 a 0-$((C-1)); run band 1 b $C-$((2*C-1))
fi
wait
for r in band default; do [ -f $OUT/suite/stall_tb_$r.jsonl ] && { echo "== truth band, fit $r"; python3 benchmarks/stall_suite.py --out $OUT/suite/stall_tb_$r.jsonl --table-only; }; done
echo "total $(( $(date +%s) - T0 )) s"
