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
  touch "$stamp"
fi
python -c "import physinteract_usd, warp, torch; print('physinteract-usd ready: torch', torch.__version__, '| warp', warp.__version__)"
