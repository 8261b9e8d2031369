# SPDX-License-Identifier: GPL-3.0-or-later
"""Which of the bundled Python dependencies import, checked lazily and cached.

Nothing here imports a dependency at module import time: ``missing()`` does the
imports the first time it is called (usually the first panel draw), so a broken
or absent wheel can never stop the add-on from registering.
"""

from __future__ import annotations

import importlib

import bpy

# Import names, in the order the panel lists them.  numpy ships with Blender;
# scipy, pytetwild and fast_simplification come from the wheels in the manifest.
REQUIRED: tuple[str, ...] = ("numpy", "scipy", "pytetwild", "fast_simplification")

_missing_cache: list[tuple[str, str]] | None = None


def _try_import(name: str) -> str | None:
    """Return None if ``name`` imports, otherwise a one-line error message."""
    try:
        importlib.import_module(name)
    except BaseException as ex:  # noqa: BLE001 - a broken wheel can raise anything (ImportError, OSError, SystemExit)
        if isinstance(ex, KeyboardInterrupt):
            raise
        message = str(ex).strip().splitlines()[0] if str(ex).strip() else ""
        return f"{type(ex).__name__}: {message}" if message else type(ex).__name__
    return None


def missing(refresh: bool = False) -> list[tuple[str, str]]:
    """``[(name, error message), ...]`` for every required module that fails to import.

    The result is cached; pass ``refresh=True`` (or call :func:`clear_cache`)
    to check again, e.g. after installing a wheel.
    """
    global _missing_cache
    if _missing_cache is None or refresh:
        result = []
        for name in REQUIRED:
            error = _try_import(name)
            if error is not None:
                result.append((name, error))
        _missing_cache = result
    return list(_missing_cache)


def clear_cache() -> None:
    global _missing_cache
    _missing_cache = None


class TRANSLUCENCY_OT_check_dependencies(bpy.types.Operator):
    """Check again whether numpy, scipy, pytetwild and fast_simplification import"""

    bl_idname = "translucency.check_dependencies"
    bl_label = "Check Dependencies"
    bl_options = {'REGISTER', 'INTERNAL'}

    def execute(self, context):
        problems = missing(refresh=True)
        if problems:
            for name, error in problems:
                self.report({'ERROR'}, f"Translucency: {name} does not import ({error})")
            return {'CANCELLED'}
        self.report({'INFO'}, "Translucency: all dependencies import")
        return {'FINISHED'}


CLASSES = (TRANSLUCENCY_OT_check_dependencies,)
