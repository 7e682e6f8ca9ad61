#!/usr/bin/env bash
# #24: the parts start's simplex uncut on CUDA (the cap's probes, no stall stop; the CPU keeps the cut one of acf1acc)
# on a host of 4 GPUs (H200 or H100), two calls:
#
#   OUT=/dir CALL=suite NGPUS=4 bash benchmarks/gpu_parts_simplex.sh   # the 12 suite scenes, old (the CLI default) vs
#        parts20 (this code), as docs/benchmarks/gpu/session_2026-11-27b/stall_suite_cheap_parts.jsonl was run
#        (development data: small, 14 frames, 20 iterations, true contacts, grid auto; six truths at grid 128, six at
#        the suite's usual cell), both halves at once over the 4 GPUs (~8 min: the 2026-11-27b rows took 430 s)
#   OUT=/dir CALL=trace NGPUS=4 bash benchmarks/gpu_parts_simplex.sh   # on the stages the suite call left under
#        out/gps24e (same machine, right after): foam_bar, flower, telephone_cable, balloon_dog, one per GPU: the
#        simplex probe by probe for the 20-probe start (p20, code f6a2cc6), the cut one (cheap, acf1acc, the CPU's
#        rule), this code's on CUDA (cuda) and cuda with the parabola bracket (an option), then the fit from each of
#        cuda, p20, cheap and none with the code's take rule (benchmarks/parts_simplex_trace.py; ~5 min)
#
# A call cut by its limit keeps its rows. CPU smoke of the trace: DEVICE=cpu CALL=smoke (foam_bar at grid 12).
set -u
OUT="${OUT:-out/gpu_parts_simplex}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 OMP_NUM_THREADS="${OMP_NUM_THREADS:-2}"
CALL="${CALL:-suite}"
PY="${PY:-python3}"
DEVICE="${DEVICE:-cuda}"
LIMIT="${LIMIT:-560}"
WORK="${WORK:-out/gps24e}"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sort | uniq -c | sed 's/^/device: /'
git rev-parse --short HEAD 2>/dev/null | sed 's/^/code: /'
T0=$(date +%s)
case "$CALL" in
  suite)
    ( timeout -k 10 "$LIMIT" "$PY" benchmarks/stall_suite.py \
        --scenes foam_bar,hemp_rope,balloon_dog,toy_rope,telephone_cable,tow_rope --variants parts20 --device "$DEVICE" \
        --size small --frames 14 --synth-fit-grid 128 --grid auto --iterations 20 --work "$WORK/a" \
        --out "$OUT/stall_suite.jsonl" --jobs 6 > "$OUT/suite_a.log" 2>&1; echo "truth-128 half: exit $? $(( $(date +%s) - T0 )) s" ) &
    ( GPU_OFFSET=2 timeout -k 10 "$LIMIT" "$PY" benchmarks/stall_suite.py \
        --scenes balloon,bow_tie,glove,flower,basketball,knit_cap --variants parts20 --device "$DEVICE" \
        --size small --frames 14 --grid auto --iterations 20 --work "$WORK/b" \
        --out "$OUT/stall_suite.jsonl" --jobs 6 > "$OUT/suite_b.log" 2>&1; echo "usual-truth half: exit $? $(( $(date +%s) - T0 )) s" ) &
    wait
    "$PY" benchmarks/stall_suite.py --out "$OUT/stall_suite.jsonl" --table-only
    "$PY" - "$OUT/stall_suite.jsonl" <<'EOF'
import json, sys
for line in open(sys.argv[1]):
    r = json.loads(line)
    p = (r.get("levers") or {}).get("parts_start")
    if p:
        print(f"{r['scene']:16s} forwards {p['forwards']:3d} used {p['used']!s:5s} parts {p['parts']} "
              f"gain {p.get('parts_gain', float('nan')):.5f} stalled {p.get('stalled')} E {[round(v, 3) for v in p['log_e']]}")
EOF
    ;;
  trace|smoke)
    if [ "$CALL" = smoke ]; then
      SCENES="foam_bar:${SMOKE_STAGE:-/tmp/p24e/fb12/foam_bar.usda}:${SMOKE_GT:-/tmp/p24e/fb12/foam_bar/gt}"; ITER=4
    else
      SCENES="foam_bar:$WORK/a/foam_bar/foam_bar.usda:$WORK/a/foam_bar/foam_bar/gt
flower:$WORK/b/flower/flower.usda:$WORK/b/flower/flower/gt
telephone_cable:$WORK/a/telephone_cable/telephone_cable.usda:$WORK/a/telephone_cable/telephone_cable/gt
balloon_dog:$WORK/a/balloon_dog/balloon_dog.usda:$WORK/a/balloon_dog/balloon_dog/gt"; ITER=20
    fi
    k=0
    for entry in $SCENES; do
      IFS=: read -r name stage gt <<< "$entry"
      g=$("$PY" -c "import sys; sys.path.insert(0, 'benchmarks'); from gpu_spread import gpu_for; print(gpu_for($k) or '')")
      ( [ -n "$g" ] && export CUDA_VISIBLE_DEVICES=$g
        for ap in cuda p20 cheap none; do
          v=""; [ "$ap" = cuda ] && v="p20,cheap,cuda,cuda:bracket=true"
          timeout -k 10 "$LIMIT" "$PY" benchmarks/parts_simplex_trace.py "$stage" "$gt" --device "$DEVICE" \
            --iterations "$ITER" --variants "$v" --apply "$ap" --out "$OUT/trace_${name}_$ap.json" \
            > "$OUT/trace_${name}_$ap.log" 2>&1 || echo "$name $ap: exit $?"
        done; echo "$name done $(( $(date +%s) - T0 )) s" ) &
      k=$((k + 1))
    done
    wait
    "$PY" - "$OUT" <<'EOF'
import glob, json, os, sys
print("| scene | start from | forwards | taken | parts' gain | final loss | MA |")
print("|---|---|---:|---|---:|---:|---:|")
for f in sorted(glob.glob(os.path.join(sys.argv[1], "trace_*_*.json"))):
    r = json.load(open(f))
    name, ap = os.path.basename(f)[6:-5].rsplit("_", 1)
    fit = r.get("fit") or {}
    p = fit.get("parts_start") or {}
    print(f"| {name} | {ap} | {p.get('forwards', '-')} | {p.get('used', '-')} | {p.get('parts_gain', float('nan')):.5f} | "
          f"{fit.get('final_loss', float('nan')):.5f} | {fit.get('ma', float('nan')):.3f} |")
    for v, t in (r.get("variants") or {}).items():
        print(f"    trace {v}: {t['forwards']} forwards, gain {100 * t['gain_share']:.2f}% of the loss, 90% of it by "
              f"probe {t['probe_reaching_90pct_gain']}, E {[round(e) for e in t['e']]}, the parts field's MA {t['ma_parts']:.3f}")
EOF
    ;;
  *) echo "CALL must be suite, trace or smoke" >&2; exit 2 ;;
esac
echo "total $(( $(date +%s) - T0 )) s"
