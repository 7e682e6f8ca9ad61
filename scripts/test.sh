#!/usr/bin/env bash
# Set up (if needed) and run the test suite on the CPU. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
# the report's browser test renders the HTML page in headless Chromium (Debian's `chromium`)
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo -n"
  if ! ($SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium) >/dev/null 2>&1; then
    echo "note: could not install chromium (apt-get): the report's browser test will be skipped" >&2
  fi
fi
# two workers per two cores (pytest-xdist; a file's tests stay on one worker, so its module fixtures
# are built once); PYTEST_WORKERS=0 runs in one process
python -m pytest -m "not slow" -q -n "${PYTEST_WORKERS:-auto}" --dist loadfile --durations=15 "$@" tests --ignore=tests/blender
if [ -x scripts/test-blender.sh ] && [ -z "${SKIP_BLENDER:-}" ]; then
  bash scripts/test-blender.sh
fi
