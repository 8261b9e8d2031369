#!/usr/bin/env bash
# SPDX-License-Identifier: GPL-3.0-or-later
# Create or update the Python environment for tests, benchmarks and the demo.
#
#   bash tools/setup.sh                      -> .venv: requirements-test.txt on Python 3.13
#                                               (bpy 5.2 LTS, the current Blender)
#   TRANSLUCENCY_BPY=4.5 bash tools/setup.sh -> .venv-bpy45 with only bpy 4.5.x, numpy
#                                               and pytest (tests/test_install.py uses it to
#                                               install the extension into another Blender);
#                                               4.2, 4.5, 5.0, 5.1 and 5.2 are known
#
# Idempotent: when the environment was built from the same requirements it
# returns at once.  bpy 5.1+ is published for CPython 3.13 only, bpy 4.2-5.0
# for 3.11 only; the script finds that Python on PATH or under pyenv (set
# PYTHON to choose the interpreter yourself).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

# --- which environment -------------------------------------------------------
# Release of each Blender series used when TRANSLUCENCY_BPY names only the series.
declare -A BPY_PINS=([4.2]=4.2.23 [4.5]=4.5.15 [5.0]=5.0.1 [5.1]=5.1.2 [5.2]=5.2.3)
if [[ -n "${TRANSLUCENCY_BPY:-}" ]]; then
    want="${TRANSLUCENCY_BPY%.x}"
    [[ -n "${BPY_PINS[$want]:-}" ]] && want="${BPY_PINS[$want]}"
    if ! [[ "$want" =~ ^[0-9]+\.[0-9]+\.[0-9]+$ ]]; then
        echo "setup.sh: TRANSLUCENCY_BPY must be a bpy version such as 4.5 or 4.5.4 (known series: ${!BPY_PINS[*]}), not '$TRANSLUCENCY_BPY'" >&2
        exit 2
    fi
    IFS=. read -r major minor _patch <<<"$want"
    VENV="$ROOT/.venv-bpy${major}${minor}"
    if (( major > 5 || (major == 5 && minor >= 1) )); then
        PY_WANT="3.13"
        NUMPY_PIN="$(grep -E '^numpy==' requirements-test.txt)"
    else
        PY_WANT="3.11"
        NUMPY_PIN="numpy==1.26.4"  # what Blender 4.2-5.0 ship (bpy 5.0.1 and 4.5 pull it too)
    fi
    # Only what the install test needs: the bundled wheels must come from the
    # extension, not from this environment.
    REQUIREMENTS="bpy==$want
$NUMPY_PIN
$(grep -E '^(pytest|iniconfig|packaging|pluggy|Pygments)==' requirements-test.txt)"
else
    VENV="$ROOT/.venv"
    PY_WANT="3.13"
    REQUIREMENTS="$(cat requirements-test.txt)"
fi

python_ok() {  # python_ok CMD VERSION: CMD runs and is that Python
    "$1" -c "import sys; sys.exit(sys.version_info[:2] != tuple(map(int, '$2'.split('.'))))" 2>/dev/null
}

PYTHON="${PYTHON:-}"
if [[ -z "$PYTHON" ]]; then
    candidates=("python$PY_WANT" python3 python)
    if command -v pyenv >/dev/null 2>&1; then
        # pyenv's shims refuse a version that is installed but not selected; call it directly.
        for dir in $(ls -d "$(pyenv root)/versions/$PY_WANT".* 2>/dev/null | sort -V -r); do
            candidates+=("$dir/bin/python3")
        done
    fi
    for candidate in "${candidates[@]}"; do
        if command -v "$candidate" >/dev/null 2>&1 && python_ok "$candidate" "$PY_WANT"; then
            PYTHON="$candidate"
            break
        fi
    done
fi
if [[ -z "$PYTHON" ]] || ! python_ok "$PYTHON" "$PY_WANT"; then
    echo "setup.sh: Python $PY_WANT is required for $(basename "$VENV") (bpy wheels exist for one CPython each:" \
         "3.13 for bpy 5.1+, 3.11 for 4.2-5.0); install it (e.g. pyenv install $PY_WANT) or set PYTHON=/path/to/python$PY_WANT" >&2
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
if [[ -x "$VENV/bin/python" ]] && ! python_ok "$VENV/bin/python" "$PY_WANT"; then
    echo "setup.sh: $(basename "$VENV") was made with another Python; recreating it with Python $PY_WANT"
    rm -rf "$VENV"
fi
if [[ ! -x "$VENV/bin/python" ]]; then
    echo "setup.sh: creating $(basename "$VENV") with $PYTHON"
    "$PYTHON" -m venv "$VENV"
fi
req_file="$(mktemp)"
trap 'rm -f "$req_file"' EXIT
printf '%s\n' "$REQUIREMENTS" >"$req_file"
echo "setup.sh: installing pinned requirements into $(basename "$VENV") with Python $PY_WANT (bpy is a ~400 MB download the first time)"
"$VENV/bin/python" -m pip install --disable-pip-version-check --quiet --progress-bar off -r "$req_file"
"$VENV/bin/python" -c 'import bpy, numpy; print("setup.sh: bpy", bpy.app.version_string, "numpy", numpy.__version__)'
printf '%s' "$wanted" >"$STAMP"
echo "setup.sh: $(basename "$VENV") ready in $(( $(date +%s) - start )) s"
