#!/usr/bin/env bash
# The Blender tests: make .venv-blender (scripts/setup-blender.sh), then run tests/blender inside it
# against the project's CLI. Extra arguments go to pytest.
#
# Env: PHYSINTERACT_CLI (default <repo>/.venv/bin/physinteract-usd), PHYSINTERACT_PYTHON (default:
# the python beside it), BLENDER_VENV (default <repo>/.venv-blender).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
bash scripts/setup-blender.sh
VENV="${BLENDER_VENV:-$REPO/.venv-blender}"
export PHYSINTERACT_CLI="${PHYSINTERACT_CLI:-$REPO/.venv/bin/physinteract-usd}"
if [ ! -x "$PHYSINTERACT_CLI" ]; then
    echo "test-blender: error: $PHYSINTERACT_CLI: the project's CLI is missing (install the project into" \
         ".venv first, or set PHYSINTERACT_CLI)" >&2
    exit 2
fi
exec "$VENV/bin/python" -m pytest tests/blender "$@"
