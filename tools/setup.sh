#!/usr/bin/env bash
# SPDX-License-Identifier: GPL-3.0-or-later
# Create or update the Python environment for tests, benchmarks and the demo.
#
#   bash tools/setup.sh                      -> .venv with requirements-test.txt (bpy 5.0.1)
#   TRANSLUCENCY_BPY=4.5 bash tools/setup.sh -> .venv-bpy45 with only bpy 4.5.x, numpy
#                                               and pytest (used by tests/test_install.py to
#                                               install the extension into Blender 4.5 LTS)
#
# Idempotent: when the environment was built from the same requirements it
# returns at once.  Needs Python 3.11 (bpy wheels are cp311 only); set PYTHON
# to choose the interpreter.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

# --- which environment -------------------------------------------------------
BPY_PIN_45="4.5.15"   # Blender 4.5 LTS release used for the second install test
if [[ -n "${TRANSLUCENCY_BPY:-}" ]]; then
    want="$TRANSLUCENCY_BPY"
    [[ "$want" == "4.5" || "$want" == "4.5.x" ]] && want="$BPY_PIN_45"
    if ! [[ "$want" =~ ^[0-9]+\.[0-9]+\.[0-9]+$ ]]; then
        echo "setup.sh: TRANSLUCENCY_BPY must be a bpy version such as 4.5 or 4.5.4, not '$TRANSLUCENCY_BPY'" >&2
        exit 2
    fi
    IFS=. read -r major minor _patch <<<"$want"
    VENV="$ROOT/.venv-bpy${major}${minor}"
    # Only what the install test needs: the bundled wheels must come from the
    # extension, not from this environment.
    REQUIREMENTS="bpy==$want
numpy==1.26.4
$(grep -E '^(pytest|iniconfig|packaging|pluggy|Pygments)==' requirements-test.txt)"
else
    VENV="$ROOT/.venv"
    REQUIREMENTS="$(cat requirements-test.txt)"
fi

PYTHON="${PYTHON:-}"
if [[ -z "$PYTHON" ]]; then
    for candidate in python3.11 python3 python; do
        if command -v "$candidate" >/dev/null 2>&1 &&
           "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
            PYTHON="$candidate"
            break
        fi
    done
fi
if [[ -z "$PYTHON" ]]; then
    echo "setup.sh: Python 3.11 is required (bpy is published for CPython 3.11 only); set PYTHON=/path/to/python3.11" >&2
    exit 1
fi

STAMP="$VENV/.translucency-requirements"
wanted="$("$PYTHON" -c 'import sys; print(sys.version.split()[0])')
$REQUIREMENTS"

if [[ -x "$VENV/bin/python" && -f "$STAMP" ]] && [[ "$(cat "$STAMP")" == "$wanted" ]]; then
    echo "setup.sh: $(basename "$VENV") is up to date"
    exit 0
fi

# --- create / update ---------------------------------------------------------
start=$(date +%s)
if [[ ! -x "$VENV/bin/python" ]]; then
    echo "setup.sh: creating $(basename "$VENV") with $PYTHON"
    "$PYTHON" -m venv "$VENV"
fi
req_file="$(mktemp)"
trap 'rm -f "$req_file"' EXIT
printf '%s\n' "$REQUIREMENTS" >"$req_file"
echo "setup.sh: installing pinned requirements into $(basename "$VENV") (bpy is a ~370 MB download the first time)"
"$VENV/bin/python" -m pip install --disable-pip-version-check --quiet --progress-bar off -r "$req_file"
"$VENV/bin/python" -c 'import bpy, numpy; print("setup.sh: bpy", bpy.app.version_string, "numpy", numpy.__version__)'
printf '%s' "$wanted" >"$STAMP"
echo "setup.sh: $(basename "$VENV") ready in $(( $(date +%s) - start )) s"
