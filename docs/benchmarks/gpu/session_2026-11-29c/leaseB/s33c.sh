#!/bin/bash
# session 33, lease B: (1) the three suite scenes the shape parts can change (colours a pattern, a thickness split that
# lies apart: glove, toy_rope, knit_cap), the 22nd session's standard; every other scene unchanged by construction
# (colour regions, or no shape parts, or balloon_dog's interleaved ones); (2) the paper row through the CLI twice
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
T0=$(date +%s)
timeout -s INT 300 python3 benchmarks/stall_suite.py --scenes toy_rope \
  --device cuda --size small --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --work /tmp/ss1 \
  --out $OUT/suite1.jsonl --jobs 1 --variants "" > $OUT/suite1.out 2>&1 &
timeout -s INT 300 python3 benchmarks/stall_suite.py --scenes glove,knit_cap \
  --device cuda --size small --frames 14 --synth-fit-grid auto --grid auto --iterations 20 --work /tmp/ss2 \
  --out $OUT/suite2.jsonl --jobs 2 --variants "" > $OUT/suite2.out 2>&1 &
wait
echo "suite done $(( $(date +%s) - T0 )) s"
mkdir -p $OUT/logs
for d in /tmp/ss1 /tmp/ss2; do for f in $d/*/*.log; do cp $f $OUT/logs/$(basename $(dirname $f))_$(basename $f) 2>/dev/null; done; done
grep -h "uniform E\|starts:\|parts start\|trend start\|interleaved\|iterations in\|E .* Pa (median" $OUT/logs/*.log | cut -c1-220
python3 - <<'PY'
import json, os
out = os.environ["OUT"]
for fn in ("suite1.jsonl", "suite2.jsonl"):
    p = os.path.join(out, fn)
    if os.path.exists(p):
        for l in open(p):
            r = json.loads(l); print(r["scene"], r["variant"], r.get("ma"), r.get("ma_best_uniform"), r.get("fit_s"), r.get("error"))
PY
cd $OUT && tar czf logs.tgz logs && rm -rf logs && cd - > /dev/null
bash .dev/s33b.sh
