#!/bin/bash
# session 35, lease A run 2: the paper row with the trend start extended (#24, #26); then the settled truth's
# prestressed scan (#23): 3 held dev worlds generated both ways on CUDA, fitted from their true contacts (60 iterations)
export PYTHONUNBUFFERED=1
fit_row() {   # $1 tag, $2 capture, $3 stage, $4.. fit args
  local tag=$1 cap=$2 st=$3; shift 3
  local T=$(date +%s.%N)
  python3 -m physinteract_usd fit $st --contact-from $cap/gt --device cuda --json --yes "$@" > $OUT/${tag}_fit.log 2>&1
  echo "=== $tag: CLI wall $(python3 -c "import time;print(round(time.time()-$T,1))") s"
  python3 -c "import json; t=open('$OUT/${tag}_fit.log').read(); d=json.loads(t[t.index('\n{'):]); print('runtime', round(d['runtime_s'],1), 'iterations', d['iterations'], 'phases', {k: round(v,1) for k,v in d['phases_s'].items()})"
  grep "starts:\|parts start\|trend start" $OUT/${tag}_fit.log | cut -c1-300
  python3 -m physinteract_usd evaluate $st --gt $cap/gt --device cuda --json 2>/dev/null | python3 -c "import json,sys; t=sys.stdin.read(); d=json.loads(t[t.index('{'):]); print('MA', d.get('ma'), 'masked PSNR', d.get('psnr_masked'))"
}
C3=/tmp/pp/cap; S3=/tmp/pp/scene.usda; mkdir -p /tmp/pp
python3 -m physinteract_usd synth hemp_rope $C3 --size paper --device cuda --force > $OUT/psynth.log 2>&1
python3 -m physinteract_usd init $S3 --capture $C3 --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/pinit.log 2>&1
fit_row paper $C3 $S3 --iterations 20 --fresh
SEEDS=546,549,534
T=$(date +%s)
python3 benchmarks/world_suite.py generate --split dev --seeds $SEEDS --work /tmp/wdef --device cuda > $OUT/gen_def.log 2>&1
python3 benchmarks/world_suite.py generate --split dev --seeds $SEEDS --work /tmp/wset --device cuda --settle > $OUT/gen_set.log 2>&1
echo "generated $(( $(date +%s) - T )) s"; cat $OUT/gen_def.log $OUT/gen_set.log | grep -v Warning | tail -8
for W in wdef wset; do
  python3 benchmarks/world_suite.py extract --work /tmp/$W --json $OUT/$W.rows.json --device cuda > $OUT/$W.ext.log 2>&1
  python3 -c "import json; [print('$W', r['scene'], 'pre', round(r.get('pre_contact_pct') or -1, 2)) for r in json.load(open('$OUT/$W.rows.json'))]"
done
echo "extracted $(( $(date +%s) - T )) s"
for W in wdef wset; do
  timeout 170 python3 benchmarks/world_fit.py --work /tmp/$W --json $OUT/$W.fit.json --iterations 60 --device cuda --true-contacts > $OUT/$W.fit.log 2>&1
  python3 -c "
import json
for r in json.load(open('$OUT/$W.fit.json')):
    print('$W', r.get('scene'), 'MA', r.get('ma'), 'PSNRm', r.get('psnr_masked'), 'e_ratio', r.get('e_ratio'), 'ma_u', r.get('ma_best_uniform'), r.get('error', '')[:100])"
done
echo "fitted $(( $(date +%s) - T )) s"
cd $OUT && tar czf raw2.tgz *_fit.log *.log *.json 2>/dev/null; rm -f *_fit.log
