#!/usr/bin/env bash
# Set up (if needed) and run the test suite on the CPU. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
python -m pytest -m "not slow" -q "$@" tests --ignore=tests/blender
if [ -x scripts/test-blender.sh ] && [ -z "${SKIP_BLENDER:-}" ]; then
  bash scripts/test-blender.sh
fi
