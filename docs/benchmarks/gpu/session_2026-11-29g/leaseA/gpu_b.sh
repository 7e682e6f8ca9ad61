# lease run B: the settled world captures 0546 0549 0534 through the product path with the choice (no --preload)
set -u
export PYTHONUNBUFFERED=1
T0=$(date +%s)
timeout -s INT 570 python3 .dev/s37/world_auto.py /tmp/wb $OUT/world_settled.jsonl settled 546,549,534 60 > $OUT/world_settled.log 2>&1
echo "all $(( $(date +%s) - T0 )) s"
grep '^{' $OUT/world_settled.log | cut -c1-600
