#!/bin/bash
# session 34, lease C: flower's loss at the truth's field against the parts start's two simplex ends (#24); the paper
# row once more through the CLI (#26)
export PYTHONUNBUFFERED=1
C=/tmp/fl/flower; S=/tmp/fl/flower.usda; mkdir -p /tmp/fl
python3 -m physinteract_usd synth flower $C --size small --device cuda --force --frames 14 --fit-grid 58 > $OUT/fsynth.log 2>&1
python3 -m physinteract_usd init $S --capture $C --grid auto --padding 0.3 --youngs-range 1000.0,60000.0 --max-poisson 0.4 --density 150.0 > $OUT/finit.log 2>&1
tail -n 2 $OUT/finit.log
timeout 200 python3 .dev/flower_fields.py $S $C 2>&1 | grep -v Warning
C3=/tmp/pp/cap; S3=/tmp/pp/scene.usda; mkdir -p /tmp/pp
python3 -m physinteract_usd synth hemp_rope $C3 --size paper --device cuda --force > $OUT/psynth.log 2>&1
python3 -m physinteract_usd init $S3 --capture $C3 --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/pinit.log 2>&1
T=$(date +%s.%N)
python3 -m physinteract_usd fit $S3 --contact-from $C3/gt --device cuda --json --yes --iterations 20 --fresh > $OUT/paper_fit.log 2>&1
echo "=== paper: CLI wall $(python3 -c "import time;print(round(time.time()-$T,1))") s"
python3 -c "import json; t=open('$OUT/paper_fit.log').read(); d=json.loads(t[t.index('\n{'):]); print('runtime', round(d['runtime_s'],1), 'phases', {k: round(v,1) for k,v in d['phases_s'].items()})"
python3 -m physinteract_usd evaluate $S3 --gt $C3/gt --device cuda --json 2>/dev/null | python3 -c "import json,sys; t=sys.stdin.read(); d=json.loads(t[t.index('{'):]); print('MA', d.get('ma'), 'masked PSNR', d.get('psnr_masked'))"
