# SPDX-License-Identifier: GPL-3.0-or-later
"""Demo: bake the shipped Spot mesh with the engine's command line.

    bash tools/setup.sh && .venv/bin/python demo/demo.py [extra arguments for `bake`]

Runs ``python -m translucency_addon bake ../shared/meshes/spot.obj``.  Until the
engine's command line exists, it says so and exits 0.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MESH = ROOT.parent / "shared" / "meshes" / "spot.obj"


def main() -> int:
    if not (ROOT / "translucency_addon" / "__main__.py").exists():
        print("demo: the solver is not built yet (translucency_addon has no command line);"
              " nothing to bake.")
        return 0
    if not MESH.exists():
        print(f"demo: {MESH} not found; the demo expects ../shared beside the checkout.", file=sys.stderr)
        return 1
    cmd = [sys.executable, "-m", "translucency_addon", "bake", str(MESH), *sys.argv[1:]]
    print("demo:", " ".join(cmd), flush=True)
    return subprocess.call(cmd, cwd=ROOT)


if __name__ == "__main__":
    sys.exit(main())
