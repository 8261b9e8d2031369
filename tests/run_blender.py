# SPDX-License-Identifier: GPL-3.0-or-later
"""Run the test suite inside a Blender binary instead of the bpy module.

    blender -b --factory-startup --python-exit-code 1 --python tests/run_blender.py -- [pytest args]

for example ``... --python tests/run_blender.py -- -q tests/test_registration.py``.
The exit code is pytest's.

pytest must be importable from Blender's own Python (3.13 for Blender 5.1-5.2, 3.11 for 4.2-5.0).
Either install it there::

    <blender dir>/<version>/python/bin/python3.X -m ensurepip
    <blender dir>/<version>/python/bin/python3.X -m pip install pytest hypothesis

or run ``bash tools/setup.sh`` first: if pytest is not importable, this script
appends the repo's ``.venv`` site-packages to ``sys.path`` (after Blender's own
paths, so Blender's numpy and bpy still win).  Engine tests also need scipy,
pytetwild and fast_simplification, which that fallback provides too.

If ``BLENDER_USER_RESOURCES`` is not set, Blender is restarted with a temporary
one, so the tests (the install test in particular) never touch your profile.
The same script also works with plain Python and the bpy module
(``.venv/bin/python tests/run_blender.py -- -q``).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _pytest_args() -> list[str]:
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []


def main() -> int:
    inside_blender = "bpy" in sys.modules
    if not os.environ.get("BLENDER_USER_RESOURCES"):
        user_dir = tempfile.mkdtemp(prefix="translucency-blender-user-")
        if inside_blender:
            import bpy
            binary = bpy.app.binary_path
            if binary:
                print(f"run_blender.py: restarting Blender with BLENDER_USER_RESOURCES={user_dir}", flush=True)
                os.execve(binary, [binary] + sys.argv[1:], dict(os.environ, BLENDER_USER_RESOURCES=user_dir))
        else:
            os.environ["BLENDER_USER_RESOURCES"] = user_dir
    # conftest.py sees bpy already imported and leaves the user directories alone.
    import bpy  # noqa: F401

    try:
        import pytest
    except ImportError:
        venv_site = ROOT / ".venv" / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
        if venv_site.is_dir():
            print(f"run_blender.py: pytest is not installed in Blender's Python; using {venv_site}", flush=True)
            sys.path.append(str(venv_site))
        try:
            import pytest
        except ImportError:
            print("run_blender.py: pytest is not importable from Blender's Python.\n"
                  "Install it: <blender>/<version>/python/bin/python3.X -m pip install pytest hypothesis\n"
                  "or run `bash tools/setup.sh` so the repo's .venv can be used.", file=sys.stderr)
            return 2

    os.chdir(ROOT)
    return int(pytest.main(_pytest_args()))


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    # Inside Blender, SystemExit from a --python script ends Blender with this code.
    sys.exit(code)
