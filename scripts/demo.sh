#!/usr/bin/env bash
# Set up (if needed) and run the main job on the bundled sample: init -> fit -> evaluate -> info.
# Outputs go to out/demo/ (ignored by git). Extra arguments go to `fit` (e.g. --iterations 20).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
SAMPLE=samples/bow_tie
OUT=out/demo
mkdir -p "$OUT"
rm -f "$OUT"/scene.usda "$OUT"/scene.init.usdc "$OUT"/scene.fit.usdc
# the capture's own README.txt names the suggested init settings (grid, E range, density)
physinteract-usd init "$OUT/scene.usda" --capture "$SAMPLE" --grid 24 --padding 0.3 \
  --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150
physinteract-usd fit "$OUT/scene.usda" --contact-from "$SAMPLE/gt" "$@"
physinteract-usd evaluate "$OUT/scene.usda" --gt "$SAMPLE/gt"
physinteract-usd info "$OUT/scene.usda"
physinteract-usd export "$OUT/scene.usda" "$OUT/bow_tie_twin.usdc"
echo "demo done: open $OUT/scene.usda (or $OUT/bow_tie_twin.usdc in Blender)"
