#!/bin/bash
# A fresh GPU machine's first fit after the set-up's CUDA warm-up (#26). Run it on a machine that has never compiled
# our kernels (a fresh lease): it times `warm_kernels('cuda')` (what scripts/setup.sh runs where Warp sees a GPU), then
# the bundled sample's fit twice (`--fresh`), and prints one table. A first fit within a few seconds of the second
# means the warm-up compiled what the fit launches (unwarmed, the 30th session measured 59.8 s against 10.7 s).
#   OUT=/dir bash benchmarks/gpu_first_fit.sh      (PYTHONPATH set as for gpu_bench.py on the device)
set -u
OUT=${OUT:-out/gpu_first_fit}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || true
t0=$(date +%s.%N)
python3 -c "from physinteract_usd.simulation import warm_kernels; print('compiled:', ', '.join(warm_kernels('cuda')))"
t1=$(date +%s.%N)
warm=$(python3 -c "print(round($t1 - $t0, 1))")
S=/tmp/gpu_first_fit/scene.usda
rm -rf /tmp/gpu_first_fit && mkdir -p /tmp/gpu_first_fit
python3 -m physinteract_usd init $S --capture samples/foam_bar --grid 24 --padding 0.3 --youngs-range 1e3,6e4 \
  --max-poisson 0.4 --density 150 --no-preload > "$OUT/init.log" 2>&1
for k in 1 2; do
  a=$(date +%s.%N)
  python3 -m physinteract_usd fit $S --contact-from samples/foam_bar/gt --device cuda --json --yes --fresh \
    > "$OUT/fit_$k.json" 2> "$OUT/fit_$k.err"
  b=$(date +%s.%N)
  echo "$k $(python3 -c "print(round($b - $a, 1))")" >> "$OUT/walls.txt"
done
python3 - "$OUT" "$warm" <<'PY'
import json, sys
from pathlib import Path
out, warm = Path(sys.argv[1]), sys.argv[2]
walls = dict(l.split() for l in (out / "walls.txt").read_text().splitlines())
print(f"\n| run | CLI wall (s) | fit clock (s) | start search | starts | iterations | confidence |")
print("|---|---:|---:|---:|---:|---:|---:|")
print(f"| warm_kernels('cuda') | {warm} | - | - | - | - | - |")
for k in ("1", "2"):
    t = (out / f"fit_{k}.json").read_text()
    d = json.loads(t[t.index("{"):])
    p = d.get("phases_s") or {}
    print(f"| fit {k} ({'first' if k == '1' else 'second'}) | {walls[k]} | {d['runtime_s']:.1f} | "
          f"{p.get('start_search', 0):.1f} | {p.get('starts', 0):.1f} | {p.get('iterations', 0):.1f} | "
          f"{p.get('confidence', 0):.1f} |")
PY
