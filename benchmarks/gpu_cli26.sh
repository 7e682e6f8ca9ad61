#!/usr/bin/env bash
# Issue #26, "the GPU small fit in seconds": the CLI's fixed costs. One run on one GPU:
#   1. init samples/foam_bar with the demo's flags (grid $GRID), one warm-up CLI fit (kernel caches; not counted);
#   2. the CLI small fit (`fit --contact-from samples/foam_bar/gt --iterations $ITERS --device $DEVICE`) timed
#      $REPEATS times with /usr/bin/time, for each variant in $VARIANTS:
#        host      the host's environment as it is (the GPU host compiles every module from source in every process
#                  when it cannot write bytecode: PYTHONDONTWRITEBYTECODE / read-only site-packages; session 12's
#                  28.9 s was measured so)
#        pyc       bytecode cached (PYTHONPYCACHEPREFIX=$W/pyc, PYTHONDONTWRITEBYTECODE unset; filled by a warm-up
#                  run first): what an ordinary install has
#        preload   pyc + PHYSINTERACT_CUDA_PRELOAD=1 (the opt-in CUDA preload measured here in session 17: no gain,
#                  22.3 s with and without; removed in session 18, the variable is ignored now: equal to pyc)
#        bdN       pyc + PHYSINTERACT_SIM_BLOCK_DIM=N (opt-in, #26: the solver's launches at N threads per block, e.g.
#                  bd64, bd32; a warm-up fit each compiles the variant): VARIANTS="pyc bd64 bd32" ~4 min
#        torch_adamw  host, with torch.optim.AdamW in place of fit/adamw.py (the code before 67b4008: its first step
#                  imports torch._dynamo), through a launcher that calls the CLI's main as `python -m` does
#   (after the warm-ups: benchmarks/cuda_init_probe.py, a fresh process's start-up costs step by step)
#   3. the per-phase breakdown and the in-process fit (benchmarks/cli_phases.py: two fits in one process, the first
#      paying the imports, the second the "in-process" fit), with bytecode cached.
# Development data (the bundled sample). Prints a table; writes $OUT/cli26.json, cli26.tsv, phases.json, cuda_init.json,
# device.txt and logs.tgz (every log). Usage, from the repository root on the GPU machine (Warp, usd-core on PYTHONPATH):
#     OUT=/tmp/out bash benchmarks/gpu_cli26.sh                    # ~6-7 min on an H200 (12 timed fits)
#     VARIANTS="host pyc" OUT=/tmp/out bash benchmarks/gpu_cli26.sh   # ~3.5 min
#     DEVICE=cpu GRID=10 ITERS=1 REPEATS=1 OUT=/tmp/o bash benchmarks/gpu_cli26.sh   # the CPU smoke test
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-out/cli26}
DEVICE=${DEVICE:-cuda}; GRID=${GRID:-24}; ITERS=${ITERS:-60}; REPEATS=${REPEATS:-3}
VARIANTS=${VARIANTS:-host torch_adamw pyc preload}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
W=$(mktemp -d); mkdir -p "$W/base" "$W/pyc"
TIME=/usr/bin/time; [ -x "$TIME" ] || TIME=""
(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || echo "$DEVICE") | tee "$OUT/device.txt"
echo "rev $(git rev-parse --short HEAD 2>/dev/null || cat REV 2>/dev/null)  PYTHONDONTWRITEBYTECODE=${PYTHONDONTWRITEBYTECODE:-unset}" \
  | tee -a "$OUT/device.txt"
$PY -m physinteract_usd init "$W/base/scene.usda" --capture samples/foam_bar --grid "$GRID" --padding 0.3 \
  --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 --no-preload > "$OUT/init.log" 2>&1 || { echo "init failed"; cat "$OUT/init.log"; exit 1; }

variant_env() {   # the environment of a variant, as `env` arguments
  case "$1" in
    host|torch_adamw) echo "PHYSINTERACT_CUDA_PRELOAD=0" ;;
    pyc) echo "-u PYTHONDONTWRITEBYTECODE PYTHONPYCACHEPREFIX=$W/pyc PHYSINTERACT_CUDA_PRELOAD=0" ;;
    preload) echo "-u PYTHONDONTWRITEBYTECODE PYTHONPYCACHEPREFIX=$W/pyc PHYSINTERACT_CUDA_PRELOAD=1" ;;
    bd*) echo "-u PYTHONDONTWRITEBYTECODE PYTHONPYCACHEPREFIX=$W/pyc PHYSINTERACT_CUDA_PRELOAD=0 PHYSINTERACT_SIM_BLOCK_DIM=${1#bd}" ;;
  esac
}

# torch's own AdamW in the fit (the code before 67b4008), then the CLI as `python -m physinteract_usd` runs it
TORCH_ADAMW='import sys, torch
import physinteract_usd.fit.optimize as O
O.AdamW = torch.optim.AdamW
from physinteract_usd.cli import main
main()'

fit_once() {   # variant tag -> one timed CLI fit on a fresh copy of the stage; appends a row to cli26.tsv
  local v=$1 tag=$2 d="$W/$2"
  rm -rf "$d"; cp -r "$W/base" "$d"
  local cmd=(-m physinteract_usd)
  [ "$v" = torch_adamw ] && cmd=(-c "$TORCH_ADAMW")
  local t0=$EPOCHREALTIME
  if [ -n "$TIME" ]; then
    env $(variant_env "$v") $TIME -f "TIME %e %U %S %M" $PY "${cmd[@]}" fit "$d/scene.usda" \
      --contact-from samples/foam_bar/gt --iterations "$ITERS" --device "$DEVICE" > "$OUT/fit_$tag.log" 2>&1
  else
    env $(variant_env "$v") $PY "${cmd[@]}" fit "$d/scene.usda" \
      --contact-from samples/foam_bar/gt --iterations "$ITERS" --device "$DEVICE" > "$OUT/fit_$tag.log" 2>&1
  fi
  local rc=$? t1=$EPOCHREALTIME
  local tl; tl=$(grep "^TIME " "$OUT/fit_$tag.log" | tail -1)
  local line; line=$(grep -m1 "iterations in" "$OUT/fit_$tag.log" | sed 's/^ *//')
  local psnr; psnr=$(grep -m1 "PSNR" "$OUT/fit_$tag.log" | sed 's/^ *//')
  printf "%s\t%s\t%.2f\t%s\t%s\t%s\t%s\t%s\n" "$v" "$tag" "$(awk "BEGIN{print $t1 - $t0}")" \
    "$(echo "$tl" | awk '{print $3}')" "$(echo "$tl" | awk '{print $4}')" "$rc" "$line" "$psnr" >> "$OUT/cli26.tsv"
  rm -rf "$d"
}

printf "variant\trun\twall_s\tuser_s\tsys_s\texit\tfit_line\tpsnr_line\n" > "$OUT/cli26.tsv"
T0=$(date +%s)
# warm-up (not counted): the kernel caches, and the bytecode cache the pyc variants read
fit_once host warm_host
sed -i '$d' "$OUT/cli26.tsv"
case " $VARIANTS " in *" pyc "*|*" preload "*|*" bd"*) fit_once pyc warm_pyc; sed -i '$d' "$OUT/cli26.tsv" ;; esac
for v in $VARIANTS; do   # bdN: the solver's kernels at N threads per block, a module variant compiled on first use
  case "$v" in bd*) fit_once "$v" "warm_$v"; sed -i '$d' "$OUT/cli26.tsv" ;; esac
done
echo "warm-ups done $(( $(date +%s) - T0 )) s"
# a fresh process's start-up costs, step by step (torch's context, cuDNN, cuBLAS, Warp's module loads from the cache)
env -u PYTHONDONTWRITEBYTECODE PYTHONPYCACHEPREFIX="$W/pyc" $PY benchmarks/cuda_init_probe.py --device "$DEVICE" \
  --json "$OUT/cuda_init.json" > "$OUT/cuda_init.log" 2>&1
grep -E "^\||^fresh" "$OUT/cuda_init.log"
for r in $(seq 1 "$REPEATS"); do
  for v in $VARIANTS; do
    fit_once "$v" "${v}_r$r"
  done
done
echo "CLI fits done $(( $(date +%s) - T0 )) s"
# phases + in-process, bytecode cached (what an ordinary install has)
env -u PYTHONDONTWRITEBYTECODE PYTHONPYCACHEPREFIX="$W/pyc" $PY benchmarks/cli_phases.py --stage-dir "$W/base" \
  --contact-from samples/foam_bar/gt --iterations "$ITERS" --device "$DEVICE" --repeats 2 --json "$OUT/phases.json" \
  > "$OUT/phases.log" 2>&1
grep -E "^\||^device|^modules" "$OUT/phases.log"
# what the FitProblem build does on this device (profiled) and Warp's module loads (its info log), in a short fit
env -u PYTHONDONTWRITEBYTECODE PYTHONPYCACHEPREFIX="$W/pyc" PHYSINTERACT_WARP_LOG=info $PY benchmarks/cli_phases.py \
  --stage-dir "$W/base" --contact-from samples/foam_bar/gt --iterations 2 --device "$DEVICE" --repeats 1 \
  --profile-problem > "$OUT/problem_profile.log" 2>&1
grep -E "took .*ms" "$OUT/problem_profile.log" | awk '{n++; for (i = 1; i <= NF; i++) if ($i == "took") s += $(i + 1)}
  END {printf "Warp module loads: %d, %.0f ms in all\n", n, s}'
grep -A14 "^FitProblem build, profiled" "$OUT/problem_profile.log" | cut -c1-160
echo
echo "CLI small fit (grid $GRID, $ITERS iterations, $DEVICE), /usr/bin/time wall:"
column -t -s $'\t' "$OUT/cli26.tsv" | cut -c1-200
$PY - "$OUT" <<'PY'
import csv, json, statistics, sys
out = sys.argv[1]
rows = list(csv.DictReader(open(f"{out}/cli26.tsv"), delimiter="\t"))
summary = {}
for v in dict.fromkeys(r["variant"] for r in rows):
    w = [float(r["wall_s"]) for r in rows if r["variant"] == v and r["exit"] == "0"]
    c = [float(r["user_s"] or 0) + float(r["sys_s"] or 0) for r in rows if r["variant"] == v and r["exit"] == "0"]
    summary[v] = {"runs": len(w), "median_wall_s": statistics.median(w) if w else None, "walls": w,
                  "median_cpu_s": statistics.median(c) if c else None}
ph = json.load(open(f"{out}/phases.json")) if __import__("os").path.exists(f"{out}/phases.json") else None
dev = open(f"{out}/device.txt").read().strip()
print("| variant | runs | median CLI wall s | walls | median user+sys s |")
print("|---|---:|---:|---|---:|")
for v, s in summary.items():
    print(f"| {v} | {s['runs']} | {s['median_wall_s'] if s['median_wall_s'] is None else round(s['median_wall_s'], 2)} | "
          f"{', '.join(f'{x:.1f}' for x in s['walls'])} | "
          f"{'-' if s['median_cpu_s'] is None else round(s['median_cpu_s'], 1)} |")
if ph:
    r1, r2 = ph["runs"][0], ph["runs"][-1]
    print(f"in-process: first fit {r1['main_wall_s']:.1f} s (+ imports {r1['import_cli']['wall_s'] + r1['import_fit']['wall_s']:.1f} s),"
          f" second fit {r2['main_wall_s']:.1f} s; torch._dynamo loaded: {r2['torch_dynamo_loaded']}")
json.dump({"device": dev, "cli": rows, "summary": summary, "phases": ph}, open(f"{out}/cli26.json", "w"), indent=1)
PY
echo "total $(( $(date +%s) - T0 )) s"
rm -rf "$W"
# the device tool brings back at most 8 files: the logs go into one archive
(cd "$OUT" && tar -czf logs.tgz ./*.log && rm -f ./*.log)
ls "$OUT"
