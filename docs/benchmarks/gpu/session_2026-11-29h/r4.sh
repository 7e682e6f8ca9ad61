# lease run 4 (x4 host): the one-run table on GPU 0 (#26) beside the validation split's settled-draw generation and
# extraction on GPUs 1-3 (#23; read with --final by gpu_world.sh)
set -u
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=index,name,driver_version --format=csv,noheader
git log --oneline -1 2>/dev/null || true
T0=$(date +%s)
CUDA_VISIBLE_DEVICES=0 python3 -c "from physinteract_usd.simulation import warm_kernels; print('compiled the CUDA kernels:', ', '.join(warm_kernels('cuda')))" > $OUT/warm.log 2>&1
echo "warm-up $(( $(date +%s) - T0 )) s"; tail -2 $OUT/warm.log
( CUDA_VISIBLE_DEVICES=0 timeout -s INT 530 python3 benchmarks/gpu_bench.py --out $OUT/bench --deadline 515 --probes .dev/probes > $OUT/bench.log 2>&1 ) &
( GPUS=1,2,3 NOFIT=1 JOBS=6 OUT=$OUT/val WORK=/tmp/world_validation bash benchmarks/gpu_world.sh validation 0-23 505 > $OUT/val_extract.log 2>&1 ) &
wait
echo "run 4: $(( $(date +%s) - T0 )) s"
tail -45 $OUT/bench.log
tail -45 $OUT/val_extract.log
