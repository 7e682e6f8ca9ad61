#!/bin/bash
# session 36, lease A run 2: the two first-half suite scenes the 35th session's suite did not reach (#24), the suite's
# standard (gpu_suite12.sh's first half: 14 frames, 20 iterations, true contacts, synth fit grid 128, grid auto)
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
timeout -s INT 540 python3 benchmarks/stall_suite.py --scenes telephone_cable,tow_rope --device cuda --size small \
  --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --work /tmp/ss1 --out $OUT/suite1.jsonl --jobs 2 \
  --variants "" > $OUT/suite1.out 2>&1
tail -5 $OUT/suite1.out
python3 - $OUT <<'PY'
import json, os, sys
p = os.path.join(sys.argv[1], "suite1.jsonl")
for l in (open(p) if os.path.exists(p) else []):
    r = json.loads(l)
    print(r["scene"], "MA", r.get("ma"), "best single E", r.get("ma_best_uniform"), "fit s", r.get("fit_s"), "PSNRm", r.get("psnr_masked"), r.get("error") or "")
PY
