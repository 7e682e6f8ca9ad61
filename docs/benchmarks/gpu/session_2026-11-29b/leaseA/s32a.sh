#!/bin/bash
# session 32, lease A (a fresh H200): the warm-up's block-size fix measured (benchmarks/gpu_first_fit.sh, module loads
# logged); then the paper row's first-fit overhead: synth + init at paper size, two fits under cProfile, module loads logged
export PYTHONUNBUFFERED=1 PHYSINTERACT_WARP_LOG=info
OUT0=$OUT
OUT=$OUT0/first bash benchmarks/gpu_first_fit.sh
echo "=== module loads compiled in fit 1 / fit 2:"
for k in 1 2; do echo "fit $k: $(cat $OUT0/first/fit_$k.json $OUT0/first/fit_$k.err | grep -c '(compiled)') compiled, $(cat $OUT0/first/fit_$k.json $OUT0/first/fit_$k.err | grep -c '(cached)') cached"; done
cat $OUT0/first/fit_1.json $OUT0/first/fit_1.err | grep "(compiled)" | head
C=/tmp/pp/cap; S=/tmp/pp/scene.usda; mkdir -p /tmp/pp
T=$(date +%s.%N)
python3 -m physinteract_usd synth hemp_rope $C --size paper --device cuda --force > $OUT0/psynth.log 2>&1
echo "synth $(python3 -c "import time;print(round(time.time()-$T,1))") s"
python3 -m physinteract_usd init $S --capture $C --grid 100 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > $OUT0/pinit.log 2>&1
for k in 1 2; do
  T=$(date +%s.%N)
  python3 -m cProfile -o $OUT0/paper_$k.prof -m physinteract_usd fit $S --contact-from $C/gt --device cuda --json --yes --fresh --iterations 20 > $OUT0/paper_$k.log 2>&1
  echo "paper fit $k: CLI wall $(python3 -c "import time;print(round(time.time()-$T,1))") s; compiled $(grep -c '(compiled)' $OUT0/paper_$k.log), cached $(grep -c '(cached)' $OUT0/paper_$k.log)"
  grep "(compiled)" $OUT0/paper_$k.log | head -5
  python3 -c "import json; t=open('$OUT0/paper_$k.log').read(); i=t.rindex('\"phases_s\"'); print(t[i:i+300])"
  grep -o '"runtime_s": [0-9.]*\|"final_loss": [0-9.e-]*' $OUT0/paper_$k.log
done
python3 - $OUT0 <<'PY'
import pstats, sys
for k in (1, 2):
    print(f"=== paper fit {k}: top by tottime")
    st = pstats.Stats(f"{sys.argv[1]}/paper_{k}.prof"); st.sort_stats("tottime").print_stats(18)
PY
cd $OUT0 && tar czf raw.tgz first paper_*.log paper_*.prof psynth.log pinit.log && rm -rf first paper_*.prof
