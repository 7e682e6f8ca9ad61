#!/usr/bin/env bash
# Generate paper-size synthetic captures on a GPU (ground truth simulated on CUDA), one after another,
# each with a time limit; copies each gt.json and a downscaled contact sheet to $OUT:
#     OUT=/dir bash benchmarks/gpu_paper_synth.sh "balloon glove flower" [SECONDS_EACH]
# The captures stay in /tmp/paper/<scene> (benchmarks/gpu_paper.sh reuses them while the machine is warm).
set -u
OUT="${OUT:-out/gpu_paper}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
W=/tmp/paper
mkdir -p $W
for S in $1; do
  t0=$(date +%s)
  if timeout "${2:-150}" python3 -m physinteract_usd synth "$S" "$W/$S" --size paper --device cuda --force > "$W/$S.synth.log" 2>&1; then
    echo "$S: generated in $(( $(date +%s) - t0 )) s: $(grep -v Warp "$W/$S.synth.log" | tail -2 | tr '\n' ' ')"
    cp "$W/$S/gt/gt.json" "$OUT/gt_$S.json"
    python3 -c "import cv2,sys; im=cv2.imread(sys.argv[1]); s=1400/im.shape[1]; cv2.imwrite(sys.argv[2], cv2.resize(im,None,fx=s,fy=s,interpolation=cv2.INTER_AREA), [cv2.IMWRITE_JPEG_QUALITY, 85])" "$W/$S/preview.png" "$OUT/preview_$S.jpg"
  else
    echo "$S: FAILED after $(( $(date +%s) - t0 )) s: $(grep -v Warp "$W/$S.synth.log" | tail -3 | tr '\n' ' ')"
  fi
done
