#!/bin/bash
# session 33, lease C run 1: the 12 named suite scenes at head (the parts by thickness; the confidence reuses the final pass),
# one H200, the 22nd session's standard (stall_suite --variants ""), to compare with the 32nd session's lease D rows
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
T0=$(date +%s)
timeout -s INT 505 python3 benchmarks/stall_suite.py --scenes foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope \
  --device cuda --size small --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --work /tmp/ss1 \
  --out $OUT/suite1.jsonl --jobs 3 --variants "" > $OUT/suite1.out 2>&1 &
timeout -s INT 505 python3 benchmarks/stall_suite.py --scenes balloon,bow_tie,glove,flower,basketball,knit_cap \
  --device cuda --size small --frames 14 --synth-fit-grid auto --grid auto --iterations 20 --work /tmp/ss2 \
  --out $OUT/suite2.jsonl --jobs 3 --variants "" > $OUT/suite2.out 2>&1 &
wait
echo "suite done $(( $(date +%s) - T0 )) s"
mkdir -p $OUT/logs
for d in /tmp/ss1 /tmp/ss2; do for f in $d/*/*.log; do cp $f $OUT/logs/$(basename $(dirname $f))_$(basename $f) 2>/dev/null; done; done
grep -h "level 1\|starts:\|parts start\|trend start\|interleaved" $OUT/logs/*.log | cut -c1-200
python3 - <<'PY'
import json, os
out = os.environ["OUT"]
for fn in ("suite1.jsonl", "suite2.jsonl"):
    p = os.path.join(out, fn)
    if os.path.exists(p):
        for l in open(p):
            r = json.loads(l); print(r["scene"], r["variant"], r.get("ma"), r.get("ma_best_uniform"), r.get("fit_s"), r.get("error"))
PY
cd $OUT && tar czf logs.tgz logs && rm -rf logs
