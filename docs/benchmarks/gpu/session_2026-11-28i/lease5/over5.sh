#!/bin/bash
# lease 5 (session 30): where the CLI's time outside the fit goes on the GPU host (imports, CUDA init, exit)
export PYTHONUNBUFFERED=1
S=/tmp/sm/scene.usda; mkdir -p /tmp/sm
python3 -m physinteract_usd init $S --capture samples/foam_bar --grid 24 --padding 0.3 --youngs-range 1e3,6e4 --max-poisson 0.4 --density 150 > /dev/null 2>&1
for i in 1 2; do
python3 - <<'PY'
import time; t=time.perf_counter()
import torch; a=time.perf_counter()
torch.zeros(1, device="cuda"); torch.cuda.synchronize(); b=time.perf_counter()
import warp as wp; wp.config.quiet=True; wp.init(); c=time.perf_counter()
import physinteract_usd.app.fit, physinteract_usd.fit, physinteract_usd.simulation; d=time.perf_counter()
print(f"import torch {a-t:.2f} s; torch CUDA context {b-a:.2f}; import warp + init {c-b:.2f}; our modules {d-c:.2f}")
PY
done
for i in 1 2; do
rm -rf /tmp/sm/scene.fit.usdc /tmp/sm/scene.versions
T0=$(date +%s.%N)
python3 - $S <<'PY' > /tmp/sm/fit.log 2>&1
import sys, time, json
t0 = time.time()
from physinteract_usd.cli import main
code = main(["fit", sys.argv[1], "--contact-from", "samples/foam_bar/gt", "--device", "cuda", "--json", "--yes"])
print("MAIN_RETURNED", time.time(), "STARTED", t0, file=sys.stderr)
PY
T1=$(date +%s.%N)
python3 - $T0 $T1 <<'PY'
import sys, re, json
t0, t1 = map(float, sys.argv[1:3])
txt = open("/tmp/sm/fit.log").read()
m = re.search(r"MAIN_RETURNED (\S+) STARTED (\S+)", txt)
ret, st = float(m.group(1)), float(m.group(2))
i = [x.start() for x in re.finditer(r"^\{", txt, re.M)][-1]
d = json.JSONDecoder().raw_decode(txt[i:])[0]
ph = d["phases_s"]; out = sum(ph[k] for k in ("prepare", "problem", "notes", "write"))
print(f"wall {t1-t0:.2f} s: interpreter start {st-t0:.2f}, main {ret-st:.2f} (fit clock {d['runtime_s']:.2f}, around it {out:.2f}, "
      f"rest of main incl. imports {ret-st-d['runtime_s']-out:.2f}), exit {t1-ret:.2f}")
PY
done
