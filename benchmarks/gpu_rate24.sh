#!/usr/bin/env bash
# #24: the rate transfer in the kernels (SimModel.transfer_tau, docs/sim.md) on a GPU. Per scene, the synth truth
# and the fit (true contacts, the path pinned: traj_pin.py --modes pinned, CFL 0.6, grid auto) both with the rate
# transfer at TAU, against both with APIC (tau 0; the baseline, rerun in the same call). One call, resumable
# (captures and stages in $W/rate and $W/apic):
#
#     OUT=/dir [TAU=0.01] [SCENES=telephone_cable,foam_bar,hemp_rope] [ITERATIONS=20] bash benchmarks/gpu_rate24.sh [SECONDS]
#
# Rows (MA, best single E, median E fit / truth, masked PSNR, substeps) go to $OUT/rate24_fits.jsonl; the table is
# printed at the end. Expected on one H200: the rate rows first (~3 min for three scenes at once: synth ~1 min, fits
# ~+50% a substep over APIC's), then the APIC rows (~2-3 min); run under SECONDS (default 470).
# CPU smoke (docs/benchmarks/fit.md): PATH=.venv/bin:$PATH DEVICE=cpu FRAMES=4 SYNTH_FIT_GRID=12 GRID=12 \
#     ITERATIONS=1 SCENES=foam_bar W=/tmp/rate24_smoke OUT=/tmp/rate24_smoke_out bash benchmarks/gpu_rate24.sh 1500
set -u
OUT="${OUT:-out/gpu_rate24}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
LIMIT="${1:-470}"
TAU="${TAU:-0.01}"
SCENES="${SCENES:-telephone_cable,foam_bar,hemp_rope}"
ITERATIONS="${ITERATIONS:-20}"
DEVICE="${DEVICE:-cuda}"
FRAMES="${FRAMES:-14}"
W="${W:-/tmp/rate24}"
START=$(date +%s)
left() { echo $(( LIMIT - ($(date +%s) - START) )); }
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sed 's/^/device: /'
NJOBS=$(echo "$SCENES" | tr ',' '\n' | wc -l)
COMMON="--scenes $SCENES --size small --frames $FRAMES --synth-fit-grid ${SYNTH_FIT_GRID:-44} --grid ${GRID:-auto} \
  --iterations $ITERATIONS --device $DEVICE --modes pinned --cfl 0.6 --jobs $NJOBS --out $OUT/rate24_fits.jsonl"
for run in rate apic; do
  [ "$(left)" -gt 30 ] || break
  mkdir -p "$W/$run"
  if [ "$run" = rate ]; then extra="--transfer-tau $TAU"; else extra=""; fi
  timeout "$(( $(left) - 10 ))" python3 benchmarks/traj_pin.py $COMMON --work "$W/$run" --tag "$run" $extra \
    > "$OUT/fits_$run.log" 2>&1
  echo "$run: exit $? at $(( $(date +%s) - START )) s"; tail -3 "$OUT/fits_$run.log"
  cp "$W/$run"/*.log "$OUT/" 2>/dev/null
done
python3 - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
f = out / "rate24_fits.jsonl"
rows = [json.loads(l) for l in f.read_text().splitlines()] if f.exists() else []
print("| scene | transfer (truth and fit) | substeps | MA | best single E | median E fit / truth | masked PSNR | fit's loss | truth's loss at the fit's step |")
print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
for r in sorted(rows, key=lambda r: (Path(r["stage"]).stem, r.get("transfer_tau", 0.0))):
    tr = f"rate, tau {r['transfer_tau']:g} s" if r.get("transfer_tau") else "APIC"
    print(f"| {Path(r['stage']).stem} | {tr} | {r['substeps']} | {r['ma']:.3f} | {r['ma_best_uniform']:.3f} | "
          f"{r['median_e_fit'] / r['median_e_truth']:.2f} | {r['psnr_masked']:.2f} | {r['loss_fit']:.5f} | {r['loss_truth']:.5f} |")
PY
