set -u
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
T0=$(date +%s)
timeout -s INT 60 python3 -c "from physinteract_usd.simulation import warm_kernels; print('warm-up:', len(warm_kernels('cuda')), 'modules')" 2>&1 | tail -1
echo "warm-up $(( $(date +%s) - T0 )) s"
OUT=$OUT W=/tmp/paper timeout -s INT 190 bash benchmarks/gpu_paper.sh hemp_rope 20
cat $OUT/paper.md
grep -h "preload\|iterations in\|PSNR\|converged" $OUT/paper_hemp_rope.log | head -8
echo "all $(( $(date +%s) - T0 )) s"
