#!/bin/bash
# session 31, lease A: the 12 named suite scenes at the new default (starts_order "screened"), one H200
export PYTHONUNBUFFERED=1
echo REV $(git rev-parse --short HEAD 2>/dev/null || cat .rev 2>/dev/null)
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
T0=$(date +%s)
C="--device cuda --size small --frames 14 --grid auto --iterations 20 --variants \"\""
timeout -s INT 520 python3 benchmarks/stall_suite.py --scenes foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope \
  --device cuda --size small --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --work /tmp/ss1 \
  --out $OUT/suite1.jsonl --jobs 3 --variants "" > $OUT/suite1.out 2>&1 &
timeout -s INT 520 python3 benchmarks/stall_suite.py --scenes balloon,bow_tie,glove,flower,basketball,knit_cap \
  --device cuda --size small --frames 14 --synth-fit-grid auto --grid auto --iterations 20 --work /tmp/ss2 \
  --out $OUT/suite2.jsonl --jobs 3 --variants "" > $OUT/suite2.out 2>&1 &
wait
echo "suite done $(( $(date +%s) - T0 )) s"
mkdir -p $OUT/logs
for d in /tmp/ss1 /tmp/ss2; do for f in $d/*/*.log; do cp $f $OUT/logs/$(basename $(dirname $f))_$(basename $f) 2>/dev/null; done; done
grep -h "starts:\|parts start\|trend start" $OUT/logs/*.log | cut -c1-260
python3 - <<'PY'
import json, os
out = os.environ["OUT"]
for fn in ("suite1.jsonl", "suite2.jsonl"):
    p = os.path.join(out, fn)
    if os.path.exists(p):
        for l in open(p):
            r = json.loads(l); print(r["scene"], r["variant"], r.get("ma"), r.get("fit_s"), r.get("error"))
PY
