# lease C: the three validation captures refused at every uniform E in lease A, again with the floor rule (c3c137e),
# read once (--final), nothing tuned on them
set -u
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=index,name,driver_version --format=csv,noheader
T0=$(date +%s)
NGPUS=2 JOBS=3 OUT=$OUT/val3 WORK=/tmp/world_validation bash benchmarks/gpu_world.sh validation 4,6,9 275 > $OUT/val3.log 2>&1
echo "val3: $(( $(date +%s) - T0 )) s"
grep -v "^|" $OUT/val3.log | grep -v "^  " | head -40
grep "^| validation\|^| \*\*all" $OUT/val3/world_validation.md | cut -c1-300
