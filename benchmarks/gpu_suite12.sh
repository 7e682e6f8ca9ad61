#!/usr/bin/env bash
# The 12 named suite scenes in the suite's standard since the 22nd session (docs/benchmarks/fit.md, top;
# benchmarks/stall_suite.py's doc): the two halves at once on one GPU, 3 jobs each, 14 frames, 20 iterations, true
# contacts, the default fit (`--variants ""`), under one deadline (SIGINT: a fit stopped keeps its best iterate):
#     OUT=/dir [LIMIT=505] [DEVICE=cuda] bash benchmarks/gpu_suite12.sh
# Writes $OUT/suite1.jsonl, suite2.jsonl (one row a scene), suite*.out, logs.tgz (every scene's synth/init/fit log)
# and prints each scene's MA against its best single E, the starts' log lines and the mean. Needs python3 with
# torch, warp, usd-core, opencv, trimesh on PYTHONPATH (the sessions' run scripts called this by hand before).
set -u
OUT="${OUT:-out/gpu_suite12}"
LIMIT="${LIMIT:-505}"
DEVICE="${DEVICE:-cuda}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sed 's/^/device: /'
T0=$(date +%s)
run_half() {   # $1: 1|2, $2: scenes, $3: --synth-fit-grid
  timeout -s INT "$LIMIT" python3 benchmarks/stall_suite.py --scenes "$2" --device "$DEVICE" --size small --frames 14 \
    --synth-fit-grid "$3" --grid auto --iterations 20 --work "/tmp/ss$1" --out "$OUT/suite$1.jsonl" --jobs 3 \
    --variants "" > "$OUT/suite$1.out" 2>&1
}
run_half 1 foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope 128 &
run_half 2 balloon,bow_tie,glove,flower,basketball,knit_cap auto &
wait
echo "suite done $(( $(date +%s) - T0 )) s"
mkdir -p "$OUT/logs"
for d in /tmp/ss1 /tmp/ss2; do for f in "$d"/*/*.log; do
  [ -f "$f" ] && cp "$f" "$OUT/logs/$(basename "$(dirname "$f")")_$(basename "$f")"; done; done
grep -h "starts:\|parts start\|trend start\|interleaved" "$OUT"/logs/*.log 2>/dev/null | cut -c1-200
python3 - "$OUT" <<'PY'
import json, os, sys
rows = []
for fn in ("suite1.jsonl", "suite2.jsonl"):
    p = os.path.join(sys.argv[1], fn)
    if os.path.exists(p):
        rows += [json.loads(l) for l in open(p) if l.strip()]
for r in rows:
    print(r["scene"], "MA", r.get("ma"), "best single E", r.get("ma_best_uniform"), "fit s", r.get("fit_s"), r.get("error") or "")
done = [r for r in rows if r.get("ma") is not None]
if done:
    print(f"{len(done)} scenes: mean MA {sum(r['ma'] for r in done) / len(done):.3f}, >= 0.9 on "
          f"{sum(r['ma'] >= 0.9 for r in done)}, below the best single E on "
          f"{sum(r['ma'] < r['ma_best_uniform'] for r in done if r.get('ma_best_uniform') is not None)}")
PY
(cd "$OUT" && tar czf logs.tgz logs && rm -rf logs)
