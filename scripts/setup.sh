#!/usr/bin/env bash
# Set up the project's environment in .venv (idempotent): the CPU build of torch first, so that no
# multi-GB CUDA build is pulled in, then the package (editable) with its test extra.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
stamp=.venv/.physinteract-setup
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  python -m pip install -q --upgrade pip
  python -m pip install -q "torch==2.13.0"
  python -m pip install -q -e ".[test]"
  # after an install, import them all once (this also checks that the install works)
  python -c "import physinteract_usd, warp, torch; print('installed: torch', torch.__version__, '| warp', warp.__version__)"
  # compile the fit's CPU kernels into Warp's kernel cache once, here, not in the first demo's fit
  # (~15 s of CPU, two modules at a time; a kernel changed later compiles at its first launch: #26)
  python -c "from physinteract_usd.simulation import warm_kernels; print('compiled the CPU kernels:', ', '.join(warm_kernels()))" \
    || echo "note: the CPU kernels were not compiled ahead; the first fit compiles them"
  # and where Warp sees a CUDA GPU, the CUDA kernels too (a fresh H200's first fit: 59.8 s against 10.7 s; #26)
  if python -c "import warp as wp; wp.config.quiet = True; wp.init(); raise SystemExit(0 if wp.is_cuda_available() else 1)" >/dev/null 2>&1; then
    python -c "from physinteract_usd.simulation import warm_kernels; print('compiled the CUDA kernels:', ', '.join(warm_kernels('cuda')))" \
      || echo "note: the CUDA kernels were not compiled ahead; the first fit on the GPU compiles them"
  fi
  touch "$stamp"
fi
# set up already: check that the packages are there without importing them (importing torch and warp
# costs ~2.5 s of CPU, a share of the demo's 3 minutes: #26)
python -c "import importlib.metadata as md, importlib.util as u
missing = [m for m in ('physinteract_usd', 'warp', 'torch') if u.find_spec(m) is None]
assert not missing, f'.venv lacks {missing}: remove .venv/.physinteract-setup and run scripts/setup.sh again'
print('physinteract-usd ready: torch', md.version('torch'), '| warp', md.version('warp-lang'))"
