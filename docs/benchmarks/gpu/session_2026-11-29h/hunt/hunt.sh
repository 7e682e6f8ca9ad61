# lease 2: dev analogues of the validation fits refused at every uniform E (sheets on a floor, clamped bars; seeds
# 560-760 as drawn), generated, extracted and fitted (3 iterations: the start search is where a refusal happens)
set -u
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=index,name,driver_version --format=csv,noheader
T0=$(date +%s)
CUDA_VISIBLE_DEVICES=0 python3 -c "from physinteract_usd.simulation import warm_kernels; print('compiled the CUDA kernels:', ', '.join(warm_kernels('cuda')))" > $OUT/warm.log 2>&1
echo "warm-up $(( $(date +%s) - T0 )) s"
NGPUS=2 JOBS=6 ITER=3 OUT=$OUT/hunt WORK=/tmp/world_hunt bash benchmarks/gpu_world.sh dev 592,606,568,595,604,663,695,586,587,614,649,701,575,700 520 > $OUT/hunt.log 2>&1
echo "hunt: $(( $(date +%s) - T0 )) s"
mkdir -p $OUT/hunt_logs && cp /tmp/world_hunt/rows/*.log $OUT/hunt_logs/ 2>/dev/null
tar czf $OUT/hunt_logs.tgz -C $OUT hunt_logs && rm -rf $OUT/hunt_logs
grep -v "^|" $OUT/hunt.log | head -80
