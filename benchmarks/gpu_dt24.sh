#!/usr/bin/env bash
# #24's time step on a GPU (docs/benchmarks/fit.md, "The time step's dependence is the transfer's dissipation"):
# does the fit recover the truth's E better when its substep matches the synth truth's (whose APIC transfers
# dissipate once per substep, ~4x as often a second as the fit's)? One call, resumable (captures, stages in $W):
#
#     OUT=/dir [SCENES=telephone_cable,foam_bar,hemp_rope,balloon] [CFLS=0.6,0.15] [ITERATIONS=20] \
#         bash benchmarks/gpu_dt24.sh [SECONDS]
#
# 1. the first scene: synth (--synth-fit-grid 44: the truth's cell ~ the fit's at grid auto, so that the step is
#    what differs) + init --grid auto + its pinned-path fit at CFL 0.6, in the foreground (its log comes back).
# 2. the pinned-path bumps fit (true contacts, traj_pin.py --modes pinned) of every scene at each CFL in $CFLS,
#    four scenes at once (synth + init first where not in $W); rows (MA, best single E, masked PSNR, substeps,
#    the truth's loss at the fit's step) appended to $OUT/dt24_fits.jsonl as each finishes.
# 3. forward only: substep_drape.py per scene, the truth's own particles through the fit's simulation at the
#    adaptive step (CFL 0.6) and at the truth's own substep: largest displacement and mean error per frame.
# Then the table. Expected on one H200: step 1 ~1-2 min, step 2 ~2-3 min at CFL 0.6 and ~4x that at 0.15 (the
# substeps), step 3 <1 min: run under SECONDS (default 470; a minute is kept for step 3); what finished is in $OUT.
# CPU smoke: PATH=.venv/bin:$PATH DEVICE=cpu FRAMES=4 SYNTH_FIT_GRID=12 GRID=12 ITERATIONS=2 SCENES=foam_bar \
#     CFLS=0.6,0.3 W=/tmp/dt24_smoke OUT=/tmp/dt24_smoke_out bash benchmarks/gpu_dt24.sh 900
set -u
OUT="${OUT:-out/gpu_dt24}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
LIMIT="${1:-470}"
SCENES="${SCENES:-telephone_cable,foam_bar,hemp_rope,balloon}"
CFLS="${CFLS:-0.6,0.15}"
ITERATIONS="${ITERATIONS:-20}"
DEVICE="${DEVICE:-cuda}"
FRAMES="${FRAMES:-14}"
W="${W:-/tmp/dt24}"
mkdir -p "$W"
START=$(date +%s)
left() { echo $(( LIMIT - ($(date +%s) - START) )); }
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | sed 's/^/device: /'
COMMON="--work $W --size small --frames $FRAMES --synth-fit-grid ${SYNTH_FIT_GRID:-44} --grid ${GRID:-auto} \
  --iterations $ITERATIONS --device $DEVICE"
FIRST="${SCENES%%,*}"
# 1.
timeout "$(( $(left) - 60 ))" python3 benchmarks/traj_pin.py --scene "$FIRST" $COMMON --modes pinned --cfl 0.6 \
  --out "$OUT/dt24_fits.jsonl" --tag "cfl0.6" > "$OUT/first_$FIRST.log" 2>&1
echo "first scene ($FIRST, CFL 0.6) exit $? at $(( $(date +%s) - START )) s"; tail -5 "$OUT/first_$FIRST.log"
# 2.
for cfl in ${CFLS//,/ }; do
  [ "$(left)" -gt 90 ] || break
  if [ "$cfl" = "0.6" ]; then sc_list=$(echo "$SCENES" | tr ',' '\n' | grep -vx "$FIRST" | paste -sd, -)
  else sc_list="$SCENES"; fi
  [ -n "$sc_list" ] || continue
  timeout "$(( $(left) - 60 ))" python3 benchmarks/traj_pin.py --scenes "$sc_list" $COMMON --modes pinned --cfl "$cfl" \
    --jobs 4 --out "$OUT/dt24_fits.jsonl" --tag "cfl$cfl" > "$OUT/fits_cfl$cfl.log" 2>&1
  echo "fits CFL $cfl exit $? at $(( $(date +%s) - START )) s"
done
# 3.
for sc in ${SCENES//,/ }; do
  [ -f "$W/$sc.usda" ] && [ "$(left)" -gt 5 ] || continue
  N=$(python3 -c "import json;print(json.load(open('$W/$sc/gt/gt.json'))['gt_sim']['substeps_per_frame'])")
  timeout "$(left)" python3 benchmarks/substep_drape.py "$W/$sc.usda" "$W/$sc/gt" --frames "$FRAMES" --substeps "0,$N" \
    --particles truth --device "$DEVICE" > "$OUT/drape_$sc.jsonl" 2> "$OUT/drape_$sc.err"
  echo "drape $sc (the truth's substep $N) exit $?"
done
cp "$W"/*.log "$OUT"/ 2>/dev/null
python3 - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
f = out / "dt24_fits.jsonl"
rows = [json.loads(l) for l in f.read_text().splitlines()] if f.exists() else []
print("| scene | CFL | substeps | MA | best single E | median E fit / truth | masked PSNR | truth's loss at the fit's step | fit's loss |")
print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
for r in sorted(rows, key=lambda r: (Path(r["stage"]).stem, -(r["cfl"] or 0.6))):
    print(f"| {Path(r['stage']).stem} | {r['cfl']} | {r['substeps']} | {r['ma']:.3f} | {r['ma_best_uniform']:.3f} | "
          f"{r['median_e_fit'] / r['median_e_truth']:.2f} | {r['psnr_masked']:.2f} | {r['loss_truth']:.5f} | {r['loss_fit']:.5f} |")
for p in sorted(out.glob("drape_*.jsonl")):
    for line in p.read_text().splitlines():
        try:
            d = json.loads(line)
        except ValueError:
            continue
        print(p.stem, "substeps", d["substeps"], "| max mm, last 4 frames", d["model_max_mm"][-4:], "truth",
              d["truth_max_mm"][-4:], "| mean error mm", d["mean_error_mm"][-4:])
PY
