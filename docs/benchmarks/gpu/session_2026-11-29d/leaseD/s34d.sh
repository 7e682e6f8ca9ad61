#!/bin/bash
# session 34, lease D: flower's fields at a finer fit grid (80 against auto's 58): does the truth's field render better
# than the softer-petals one there (the resolution's bias, #24)?
export PYTHONUNBUFFERED=1
C=/tmp/fl/flower; mkdir -p /tmp/fl
python3 -m physinteract_usd synth flower $C --size small --device cuda --force --frames 14 --fit-grid 58 > $OUT/fsynth.log 2>&1
for G in 80; do
  S=/tmp/fl/flower_$G.usda
  python3 -m physinteract_usd init $S --capture $C --grid $G --padding 0.3 --youngs-range 1000.0,60000.0 --max-poisson 0.4 --density 150.0 > $OUT/finit_$G.log 2>&1
  grep "particles\|simulation" $OUT/finit_$G.log | head -3
  timeout 200 python3 .dev/flower_fields.py $S $C 2>&1 | grep -v Warning
done
