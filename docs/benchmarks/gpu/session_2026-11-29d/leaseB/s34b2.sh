#!/bin/bash
# session 34, lease B run 2: where a CUDA fit's process start goes; the issue's small capture (36 frames) and the
# bundled sample through the CLI at head; the paper row once more (#24, #26)
export PYTHONUNBUFFERED=1
python3 .dev/startup_probe.py
fit_row() {   # $1 tag, $2 capture, $3 stage, $4.. fit args
  local tag=$1 cap=$2 st=$3; shift 3
  local T=$(date +%s.%N)
  python3 -m physinteract_usd fit $st --contact-from $cap/gt --device cuda --json --yes "$@" > $OUT/${tag}_fit.log 2>&1
  echo "=== $tag: CLI wall $(python3 -c "import time;print(round(time.time()-$T,1))") s"
  python3 -c "import json; t=open('$OUT/${tag}_fit.log').read(); d=json.loads(t[t.index('\n{'):]); print('runtime', round(d['runtime_s'],1), 'iterations', d['iterations'], 'phases', {k: round(v,1) for k,v in d['phases_s'].items()})"
  grep "starts:\|parts start\|trend start" $OUT/${tag}_fit.log | cut -c1-300
  python3 -m physinteract_usd evaluate $st --gt $cap/gt --device cuda --json 2>/dev/null | python3 -c "import json,sys; t=sys.stdin.read(); d=json.loads(t[t.index('{'):]); print('MA', d.get('ma'), 'masked PSNR', d.get('psnr_masked'))"
}
C=/tmp/s36/cap; S=/tmp/s36/scene.usda; mkdir -p /tmp/s36
python3 -m physinteract_usd synth foam_bar $C --frames 36 --noise 0.015 --blur 3 --device cuda --force > $OUT/s36synth.log 2>&1
python3 -m physinteract_usd init $S --capture $C --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/s36init.log 2>&1
fit_row small36 $C $S --iterations 60
S2=/tmp/s14/scene.usda; mkdir -p /tmp/s14
python3 -m physinteract_usd init $S2 --capture samples/foam_bar --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/s14init.log 2>&1
fit_row small samples/foam_bar $S2
C3=/tmp/pp/cap; S3=/tmp/pp/scene.usda; mkdir -p /tmp/pp
python3 -m physinteract_usd synth hemp_rope $C3 --size paper --device cuda --force > $OUT/psynth.log 2>&1
python3 -m physinteract_usd init $S3 --capture $C3 --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT/pinit.log 2>&1
fit_row paper $C3 $S3 --iterations 20 --fresh
cd $OUT && tar czf raw2.tgz *_fit.log *synth.log *init.log && rm -f *_fit.log
