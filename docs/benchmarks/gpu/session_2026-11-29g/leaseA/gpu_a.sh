# lease run A: the preload choice on the 12 suite scenes (stress-free truths); the default (unsettled) world captures
# 0546 0549 0534 through the product path with the choice, 60 iterations from true contacts
set -u
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
export PYTHONUNBUFFERED=1
T0=$(date +%s)
timeout -s INT 250 python3 .dev/s37/suite_choice.py /tmp/sc1 $OUT/suite_choice.jsonl foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope > $OUT/suite_choice1.log 2>&1 &
timeout -s INT 250 python3 .dev/s37/suite_choice.py /tmp/sc2 $OUT/suite_choice.jsonl balloon,bow_tie,glove,flower,basketball,knit_cap > $OUT/suite_choice2.log 2>&1 &
wait
echo "suite choice $(( $(date +%s) - T0 )) s"
cat $OUT/suite_choice.jsonl | cut -c1-400
timeout -s INT $(( 570 - ($(date +%s) - T0) )) python3 .dev/s37/world_auto.py /tmp/wa $OUT/world_default.jsonl default 546,549,534 60 > $OUT/world_default.log 2>&1
echo "all $(( $(date +%s) - T0 )) s"
grep '^{' $OUT/world_default.log | cut -c1-600
