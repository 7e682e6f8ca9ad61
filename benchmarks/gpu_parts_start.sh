#!/usr/bin/env bash
# #24: the cheaper parts start (fit/parts_start.py since 5378eef: probes 3 (m + 1) for m parts, two-sided first simplex,
# stall stop after m + 1 probes without a new best, no start where the simplex found nothing, every probe under
# substep.kept_rung) against the default bumps
# fit on the 12 suite scenes, as the H200 rows of docs/benchmarks/gpu/session_2026-11-27/stall_suite_*.jsonl were run
# (development data: small size, 14 frames, 20 iterations, true contacts, grid auto; the truth at --synth-fit-grid 128
# for foam_bar, balloon_dog, hemp_rope, toy_rope, telephone_cable, tow_rope, at the suite's usual cell for the others).
# "old" = the suite's CLI fit with the CLI's default (--parts-start 0 today); VARIANT = the in-process fit with the
# other setting (default "new:parts_start=20"; once the default is 20, pass VARIANT=off:parts_start=0).
# Four calls, each under 9 min on one H200 (16 cores), rows appended to $OUT/parts_start_<CALL>.jsonl as they finish:
#
#     OUT=/dir CALL=A bash benchmarks/gpu_parts_start.sh     # foam_bar, balloon_dog         (~6 min: synth at 128)
#     OUT=/dir CALL=B bash benchmarks/gpu_parts_start.sh     # hemp_rope, toy_rope           (~7.5 min)
#     OUT=/dir CALL=C bash benchmarks/gpu_parts_start.sh     # telephone_cable, tow_rope     (~7.5 min)
#     OUT=/dir CALL=D bash benchmarks/gpu_parts_start.sh     # the other six, usual truth    (~5 min)
#
# Expected wall from the 2026-11-27 rows (old fit + one variant per scene, scenes at once). A call cut by its time
# limit keeps its rows; rerun the table with `python benchmarks/stall_suite.py --out FILE --table-only`.
# CPU smoke: PATH=.venv/bin:$PATH OUT=/tmp/gps DEVICE=cpu CALL=smoke bash benchmarks/gpu_parts_start.sh
set -u
OUT="${OUT:-out/gpu_parts_start}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
CALL="${CALL:-A}"
DEVICE="${DEVICE:-cuda}"
VARIANT="${VARIANT:-new:parts_start=20}"
LIMIT="${LIMIT:-530}"
TRUTH="--synth-fit-grid 128"
SIZE="--size small --frames 14 --grid auto --iterations 20"
case "$CALL" in
  A) SCENES=foam_bar,balloon_dog ;;
  B) SCENES=hemp_rope,toy_rope ;;
  C) SCENES=telephone_cable,tow_rope ;;
  D) SCENES=balloon,bow_tie,knit_cap,basketball,glove,flower; TRUTH="" ;;
  smoke) SCENES=foam_bar; TRUTH="--synth-fit-grid 12"; SIZE="--size small --frames 4 --grid 12 --iterations 2" ;;
  *) echo "CALL must be A, B, C, D or smoke" >&2; exit 2 ;;
esac
NJOBS=$(echo "$SCENES" | tr ',' '\n' | wc -l)
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sed 's/^/device: /'
git rev-parse --short HEAD 2>/dev/null | sed 's/^/code: /'
timeout "$LIMIT" python benchmarks/stall_suite.py --scenes "$SCENES" --variants "$VARIANT" --device "$DEVICE" \
  $SIZE $TRUTH --work "/tmp/gps_$CALL" --out "$OUT/parts_start_$CALL.jsonl" --jobs "$NJOBS" \
  > "$OUT/parts_start_$CALL.log" 2>&1
echo "exit $? after ${SECONDS}s"
python benchmarks/stall_suite.py --out "$OUT/parts_start_$CALL.jsonl" --table-only
# each row's levers.parts_start: forwards (probes + 2), used, parts, parts_gain, stalled
python - "$OUT/parts_start_$CALL.jsonl" <<'EOF'
import json, sys
for line in open(sys.argv[1]):
    r = json.loads(line)
    p = (r.get("levers") or {}).get("parts_start")
    if p:
        print(f"{r['scene']:16s} {r['variant']:5s} forwards {p['forwards']:3d} used {p['used']!s:5s} parts {p['parts']} "
              f"gain {p.get('parts_gain', float('nan')):.5f} stalled {p.get('stalled')} wall {r.get('wall_s')} s")
EOF
