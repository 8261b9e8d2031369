# SPDX-License-Identifier: GPL-3.0-or-later
"""The project's own data: the meshes the demo, the tests and the benchmarks use.

Every file lives in this folder (``data/meshes/*.obj``; where each comes from, its licence and
what makes it hard: ``data/README.md``), so a clone with nothing beside it runs the README's two
commands.  The extension zip leaves ``data/`` out (``blender_manifest.toml``'s exclude list).

:func:`mesh_path` is the one place that finds a mesh: ``tests/bakes.py``, ``tests/hard_cases``,
``bench/`` and ``demo/`` all resolve through it, and a missing file is an error that names it.
"""

from __future__ import annotations

from pathlib import Path

DATA = Path(__file__).resolve().parent
MESHES = DATA / "meshes"


def mesh_names() -> list[str]:
    """The names :func:`mesh_path` accepts (the OBJ files in ``data/meshes`` without ``.obj``)."""
    return sorted(p.stem for p in MESHES.glob("*.obj"))


def mesh_path(name: str) -> Path:
    """The path of the project's mesh ``name`` (``"stanford-bunny"`` or ``"stanford-bunny.obj"``).

    Raises ``FileNotFoundError`` naming the file and the meshes that are there, so a test that
    needs a missing mesh fails with the reason instead of skipping.
    """
    stem = name[:-4] if name.endswith(".obj") else name
    path = MESHES / f"{stem}.obj"
    if not path.is_file():
        raise FileNotFoundError(
            f"mesh {name!r}: {path} is not in the repository (data/meshes has: "
            f"{', '.join(mesh_names()) or 'nothing'}); restore it with `git checkout -- data/meshes` "
            "or add the OBJ there and list it in data/README.md")
    return path
