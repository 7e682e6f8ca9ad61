#!/usr/bin/env bash
# #24: does a global damping fitted with E (`fit --nuisance-damping`) remove the E bias of the truth's and the
# fit's different numerical dissipation? (docs/benchmarks/fit.md, "A fitted damping as a nuisance"). One call:
#
#     OUT=/dir [SCENES=telephone_cable,balloon,foam_bar,hemp_rope] [SYNTH_FIT_GRID=44] [ITERATIONS=20] \
#         bash benchmarks/gpu_damp24.sh [SECONDS]
#
# Per scene at once (one process each, each under SECONDS - 30): synth (--synth-fit-grid 44: the truth's cell ~ the
# fit's at grid auto, ~4x its substeps: gpu_dt24.sh's setting, where balloon's E was 1.94x and telephone_cable's
# 1.47x) + init --grid auto, then benchmarks/damp24.py's two pinned-path bumps fits from true contacts (base: E only;
# damp: + the nuisance damping) and the truth's E under a scan of c at the fit's step. Rows in $OUT/damp24_rows.jsonl
# as each finishes; the table at the end. Expected on one H200: synth ~1-2 min, each fit ~1.5-3 min: ~6-8 min.
# CPU smoke: PATH=.venv/bin:$PATH DEVICE=cpu FRAMES=4 SYNTH_FIT_GRID=12 GRID=12 ITERATIONS=2 SCENES=foam_bar \
#     W=/tmp/damp24_smoke OUT=/tmp/damp24_smoke_out bash benchmarks/gpu_damp24.sh 900
set -u
OUT="${OUT:-out/gpu_damp24}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
LIMIT="${1:-530}"
SCENES="${SCENES:-telephone_cable,balloon,foam_bar,hemp_rope}"
W="${W:-/tmp/damp24}"
mkdir -p "$W"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sed 's/^/device: /'
START=$(date +%s)
for sc in ${SCENES//,/ }; do
  timeout "$(( LIMIT - 30 ))" python3 benchmarks/damp24.py --scene "$sc" --work "$W" --size small \
    --frames "${FRAMES:-14}" --synth-fit-grid "${SYNTH_FIT_GRID:-44}" --grid "${GRID:-auto}" \
    --iterations "${ITERATIONS:-20}" --device "${DEVICE:-cuda}" --cscan "${CSCAN:-0,0.5,1,2,4,8,16}" \
    --out "$OUT/damp24_rows.jsonl" > "$OUT/damp24_$sc.log" 2>&1 &
done
wait
echo "all scenes done at $(( $(date +%s) - START )) s"
cp "$W"/*.log "$OUT"/ 2>/dev/null
python3 benchmarks/damp24.py --table-only --out "$OUT/damp24_rows.jsonl"
