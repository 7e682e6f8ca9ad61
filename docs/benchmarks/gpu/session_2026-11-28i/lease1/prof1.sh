#!/bin/bash
# lease 1 (session 30): where the paper row's time goes, and what tiled probes cost at paper size
set -x
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv
C=/tmp/pp/cap; S=/tmp/pp/base/scene.usda
mkdir -p /tmp/pp/base
T0=$(date +%s.%N)
( time python3 -m physinteract_usd synth hemp_rope $C --size paper --device cuda --force ) > $OUT/synth.log 2>&1
( time python3 -m physinteract_usd init $S --capture $C --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 ) > $OUT/init.log 2>&1
( time python3 -m physinteract_usd fit $S --contact-from $C/gt --device cuda --json --yes --iterations 20 ) > $OUT/fit_base.log 2>&1
tail -5 $OUT/fit_base.log
python3 - <<'PY'
import json,re,os
t=open(os.environ['OUT']+'/fit_base.log').read()
i=[m.start() for m in re.finditer(r'^\{',t,re.M)][-1]
d=json.JSONDecoder().raw_decode(t[i:])[0]
print(json.dumps({k:d.get(k) for k in ('runtime_s','psnr_masked','iterations','phases_s')},indent=1))
PY
( time python3 -m physinteract_usd evaluate $S --gt $C/gt --device cuda --json ) > $OUT/eval_base.log 2>&1
grep -E '"ma"|psnr_masked' $OUT/eval_base.log
timeout 150 python3 benchmarks/bench_tiled.py --device cuda --stage $S --gt $C/gt --probes 8 --sizes 15000:100 --copies 1 2 4 8 > $OUT/tiled.log 2>&1
cat $OUT/tiled.log | tail -30
python3 -X importtime -c "import physinteract_usd.cli" 2> $OUT/importtime.log; sort -t'|' -k2 -n $OUT/importtime.log | tail -8
