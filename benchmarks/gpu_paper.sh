#!/usr/bin/env bash
# Paper-scale scenes on a GPU: synth (ground truth on CUDA) -> init (grid 100) -> fit (CUDA) ->
# evaluate, with wall-clock times. Run from the repo root on the GPU host:
#     OUT=/dir bash benchmarks/gpu_paper.sh "hemp_rope bow_tie" ITERATIONS
# Needs python3 with torch, warp, usd-core, opencv, trimesh on PYTHONPATH. Writes $OUT/paper_<scene>.log,
# a JSON summary per scene and $OUT/paper.md.
set -u
OUT="${OUT:-out/gpu_paper}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
SCENES="${1:-hemp_rope}"
ITERS="${2:-20}"
W="${W:-/tmp/paper}"   # the work folder (two variants side by side take their own)
mkdir -p $W
echo "| scene | particles | substeps/frame | synth s | fit s | iterations | MA | best uniform MA | PSNR | PSNR masked | SSIM | position error mm |" > "$OUT/paper.md"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|" >> "$OUT/paper.md"
for S in $SCENES; do
  L="$OUT/paper_$S.log"
  t0=$(date +%s)
  if [ -f "$W/$S/gt/gt.json" ]; then echo "reusing $W/$S" > "$L"; else
  timeout 240 python3 -m physinteract_usd synth "$S" "$W/$S" --size paper --device cuda --force > "$L" 2>&1 || { echo "synth $S failed" | tee -a "$L"; continue; }
  fi
  t1=$(date +%s)
  rm -f $W/$S.usda $W/$S.init.usdc $W/$S.fit.usdc
  python3 -m physinteract_usd init "$W/$S.usda" --capture "$W/$S" --grid 100 --padding 0.3 --youngs-range 1e3,6e4 \
    --max-poisson 0.4 --density 150 --no-preload >> "$L" 2>&1 || { echo "init $S failed" | tee -a "$L"; continue; }
  P=$(python3 -m physinteract_usd info "$W/$S.usda" --json | python3 -c "import json,sys; d=json.load(sys.stdin); print(d['particles']['count'], d['simulation']['substeps_per_frame'])")
  t2=$(date +%s)
  timeout 400 python3 -m physinteract_usd fit "$W/$S.usda" --contact-from "$W/$S/gt" --iterations "$ITERS" --device cuda >> "$L" 2>&1
  t3=$(date +%s)
  python3 -m physinteract_usd evaluate "$W/$S.usda" --gt "$W/$S/gt" --device cuda --json > "$OUT/eval_$S.json" 2>> "$L"
  python3 - "$OUT/eval_$S.json" "$S" "$P" $((t1 - t0)) $((t3 - t2)) "$ITERS" >> "$OUT/paper.md" <<'PY'
import json, sys
try:
    d = json.load(open(sys.argv[1]))
except Exception:
    d = {}
f = lambda k, m=1.0, n=3: (f"{d[k] * m:.{n}f}" if k in d else "-")
p, s = sys.argv[3].split()
print(f"| {sys.argv[2]} | {p} | {s} | {sys.argv[4]} | {sys.argv[5]} | {sys.argv[6]} | {f('ma')} | {f('ma_best_uniform')} | "
      f"{f('psnr', n=2)} | {f('psnr_masked', n=2)} | {f('ssim')} | {f('position_error_m', 1000, 2)} |")
PY
  cp "$W/$S/preview.png" "$OUT/preview_$S.png" 2>/dev/null
done
nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | sed 's/^/device: /' >> "$OUT/paper.md"
cat "$OUT/paper.md"
