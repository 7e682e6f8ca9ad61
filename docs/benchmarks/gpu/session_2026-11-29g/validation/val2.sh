set -u
export PYTHONUNBUFFERED=1
JOBS=4 OUT=$OUT bash benchmarks/gpu_world.sh validation 0-23 545 > $OUT/val_fit.log 2>&1
tail -70 $OUT/val_fit.log
