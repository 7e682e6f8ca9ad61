#!/usr/bin/env bash
# Create (or reuse) .venv-blender: Blender 5.0.1 as a Python module (pip bpy), for the Blender
# add-on's tests. Idempotent: a venv that already has the right bpy and pytest is left alone.
#
# Why its own venv: bpy 5.0.1 needs Python 3.11 and pins numpy<2, while the project venv has
# numpy>=2 and usd-core; bpy bundles its own USD (pxr 25.08), which usd-core would shadow. So
# never install usd-core (or the project) here: the add-on and its tests call the project's
# `physinteract-usd` CLI from the project venv, as they do for users.
#
# Env: BLENDER_VENV (default <repo>/.venv-blender), PYTHON311 (default: python3.11 on PATH).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${BLENDER_VENV:-$REPO/.venv-blender}"
PY="${PYTHON311:-python3.11}"
BPY_VERSION="5.0.1"

have() {
    [ -x "$VENV/bin/python" ] && "$VENV/bin/python" - "$BPY_VERSION" <<'PYEOF' 2>/dev/null
import sys
from importlib.metadata import version
assert version("bpy") == sys.argv[1]
import pytest  # noqa: F401
PYEOF
}

if have; then
    echo "setup-blender: $VENV ready (bpy $BPY_VERSION, pytest)"
    exit 0
fi

if ! command -v "$PY" >/dev/null 2>&1; then
    echo "setup-blender: error: $PY not found: bpy $BPY_VERSION needs Python 3.11 (set PYTHON311)" >&2
    exit 2
fi
if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "setup-blender: error: $PY is $("$PY" --version 2>&1), bpy $BPY_VERSION needs Python 3.11" >&2
    exit 2
fi

start=$(date +%s)
if [ -x "$VENV/bin/python" ] && ! "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
    echo "setup-blender: $VENV is not a working Python 3.11 venv: recreating it"
    "$PY" -m venv --clear "$VENV"
elif [ ! -x "$VENV/bin/python" ]; then
    echo "setup-blender: creating $VENV"
    "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet "bpy==$BPY_VERSION" pytest
if ! have; then
    echo "setup-blender: error: $VENV: bpy $BPY_VERSION or pytest still missing after pip install" >&2
    exit 1
fi
echo "setup-blender: $VENV ready in $(( $(date +%s) - start )) s ($(du -sh "$VENV" | cut -f1))"
