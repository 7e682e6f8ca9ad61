# lease run 6: the fits the deadlines stopped or did not reach, both splits (done rows are kept and skipped)
set -u
export PYTHONUNBUFFERED=1
D=${D:-400}
T0=$(date +%s)
( GPUS=0,1 JOBS=4 OUT=$OUT/val WORK=/tmp/world_validation bash benchmarks/gpu_world.sh validation 0-23 $D > $OUT/val_fit.log 2>&1 ) &
( GPUS=2,3 JOBS=4 OUT=$OUT/dev WORK=/tmp/world_dev bash benchmarks/gpu_world.sh dev 500-511 $D > $OUT/dev.log 2>&1 ) &
wait
echo "run 6: $(( $(date +%s) - T0 )) s"
tail -60 $OUT/val_fit.log
tail -60 $OUT/dev.log
