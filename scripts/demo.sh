#!/usr/bin/env bash
# Set up (if needed) and run the main job on the bundled sample: init -> fit -> evaluate -> info.
# Outputs go to out/demo/ (ignored by git). Extra arguments go to `fit` (e.g. --iterations 20).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
SAMPLE=samples/foam_bar   # regenerate with: physinteract-usd synth foam_bar samples/foam_bar --frames 14 --force
OUT=out/demo
mkdir -p "$OUT"
rm -rf "$OUT"/scene.usda "$OUT"/scene.init.usdc "$OUT"/scene.fit.usdc "$OUT"/scene.versions "$OUT"/scene.extract
# the capture's README.txt suggests grid 24: ~3 minutes on 2 CPU cores, MA 0.93 (docs/benchmarks/cpu.md;
# grid 20 before the CPU changes: half grid 24's time, MA 0.84; docs/benchmarks/fit.md)
physinteract-usd init "$OUT/scene.usda" --capture "$SAMPLE" --grid 24 --padding 0.3 \
  --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 --no-preload
# no contact sets on the stage yet: fit extracts the hand, contact, supports and T0 from the video
physinteract-usd fit "$OUT/scene.usda" "$@"
physinteract-usd evaluate "$OUT/scene.usda" --gt "$SAMPLE/gt"
physinteract-usd info "$OUT/scene.usda"
physinteract-usd export "$OUT/scene.usda" "$OUT/foam_bar_twin.usdc" --force
echo "demo done: open $OUT/scene.usda (or $OUT/foam_bar_twin.usdc in Blender)"
