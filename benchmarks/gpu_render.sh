#!/usr/bin/env bash
# GPU benchmark of the Warp Gaussian-splat renderer against gsplat 1.5.3, run from the repo root on
# the GPU host (python3 with torch, warp, usd-core and gsplat on PYTHONPATH; no network).
# Writes to $OUT (default ./out/gpu_render): gsplat.txt, bench_cuda.md (incl. the CPU-vs-CUDA check),
# bench_cuda_nolockstep.md, bench_cuda_tiled.md, render_cuda.png, pytest_cuda.txt, summary.md. Every part is time-limited and
# a failing part does not stop the others. Budget: < 4 minutes.
set -u
OUT="${OUT:-out/gpu_render}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1
S="$OUT/summary.md"
: > "$S"
log() { echo "$@" | tee -a "$S"; }

PROBE=""
for p in .dev/probes/gsplat_probe.py shared/device/gsplat_probe.py ../shared/device/gsplat_probe.py; do
  if [ -f "$p" ]; then PROBE="$p"; break; fi
done

log "# Renderer GPU benchmark ($(date -u +%FT%TZ))"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | sed 's/^/device: /' | tee -a "$S"
$PY -c "import torch, warp; print('torch', torch.__version__, 'cuda', torch.version.cuda, '| warp', warp.__version__)" 2>&1 | tail -1 | tee -a "$S"

# 1. gsplat reference (the first call compiles gsplat's CUDA extension, ~50 s)
log ""
log "## gsplat 1.5.3 (probe: ${PROBE:-not found})"
: > "$OUT/gsplat.txt"
if [ -n "$PROBE" ]; then
  first=1
  for N in 10000 100000; do
    for SIZE in 256 512; do
      lim=40; [ $first = 1 ] && lim=150; first=0
      r=$(timeout $lim $PY "$PROBE" $N $SIZE 2>&1 | tee -a "$OUT/gsplat.txt" | grep -E "median" | tail -1)
      log "- gsplat N=$N ${SIZE}^2: ${r:-FAILED (see gsplat.txt)}"
    done
  done
else
  log "- gsplat probe not found: skipped"
fi

# 2. this renderer on CUDA (default: tile 16, lockstep backward), same scene, same sizes
log ""
log "## physinteract_usd.render on CUDA (float32, fwd+bwd incl. all gradients)"
timeout 100 $PY benchmarks/bench_render.py --device cuda --sizes 10000x256,10000x512,100000x256,100000x512,15000x512,2000x128 \
  --reps 20 --warmup 3 --json --png "$OUT/render_cuda.png" --check-cpu $([ -f .dev/probes/render_cpu_ref.npz ] && echo --cpu-ref .dev/probes/render_cpu_ref.npz) > "$OUT/bench_cuda.md" 2>&1
echo "exit $?" >> "$OUT/bench_cuda.md"
grep -E "^device|^\||saved|exit|Error|error|CPU vs CUDA|^  " "$OUT/bench_cuda.md" | tee -a "$S"

# 3. the per-pixel (non-lockstep) backward on CUDA, for comparison
log ""
log "## same, backward without lockstep"
timeout 45 $PY benchmarks/bench_render.py --device cuda --sizes 10000x512,100000x512 --reps 20 --warmup 3 \
  --lockstep 0 > "$OUT/bench_cuda_nolockstep.md" 2>&1
echo "exit $?" >> "$OUT/bench_cuda_nolockstep.md"
grep -E "^\||exit|Error|error" "$OUT/bench_cuda_nolockstep.md" | tee -a "$S"

# 3b. the block-reduction ("tiled") backward on CUDA, for comparison, plus its own consistency check
log ""
log "## same, tiled backward (block reduction per Gaussian and tile)"
timeout 60 $PY benchmarks/bench_render.py --device cuda --sizes 10000x256,10000x512,100000x256,100000x512,15000x512 \
  --reps 20 --warmup 3 --backward tiled --check-cpu $([ -f .dev/probes/render_cpu_ref.npz ] && echo --cpu-ref .dev/probes/render_cpu_ref.npz) > "$OUT/bench_cuda_tiled.md" 2>&1
echo "exit $?" >> "$OUT/bench_cuda_tiled.md"
grep -E "^\||exit|Error|error|grad_|rgb|alpha|depth" "$OUT/bench_cuda_tiled.md" | grep -v '^{' | tee -a "$S"

# 4. the render tests on CUDA (they parametrise over cuda when it is there), if pytest is installed
log ""
log "## render tests with CUDA"
if $PY -c "import pytest" 2>/dev/null; then
  T="tests/test_render_reference.py tests/test_render_gradcheck.py"
  $PY -c "import cv2" 2>/dev/null && T="$T tests/test_render_geometry.py"
  timeout 60 $PY -m pytest -q -p no:cacheprovider $T -k cuda > "$OUT/pytest_cuda.txt" 2>&1
  echo "exit $?" >> "$OUT/pytest_cuda.txt"
  tail -n 3 "$OUT/pytest_cuda.txt" | tee -a "$S"
else
  log "pytest not installed: skipped"
fi
log ""
log "files: $(ls "$OUT" | tr '\n' ' ')"
