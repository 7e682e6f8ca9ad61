# lease run 5: the validation fits (extracted interactions, 25 iterations) on GPUs 0-1; the dev split's settled
# draw (500-511) generated, extracted and fitted on GPUs 2-3 (#23)
set -u
export PYTHONUNBUFFERED=1
T0=$(date +%s)
( GPUS=0,1 JOBS=4 OUT=$OUT/val WORK=/tmp/world_validation bash benchmarks/gpu_world.sh validation 0-23 555 > $OUT/val_fit.log 2>&1 ) &
( GPUS=2,3 JOBS=5 OUT=$OUT/dev WORK=/tmp/world_dev bash benchmarks/gpu_world.sh dev 500-511 555 > $OUT/dev.log 2>&1 ) &
wait
echo "run 5: $(( $(date +%s) - T0 )) s"
tail -60 $OUT/val_fit.log
tail -60 $OUT/dev.log
