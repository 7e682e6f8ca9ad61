set -u
export PYTHONUNBUFFERED=1
NOFIT=1 JOBS=6 OUT=$OUT bash benchmarks/gpu_world.sh validation 0-23 330 > $OUT/val_extract.log 2>&1
tail -45 $OUT/val_extract.log
