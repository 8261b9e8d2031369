# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender side of Translucency: operators, panels, PropertyGroups, handlers.

Each module has one ``CLASSES`` tuple.  ``register()`` registers the modules in
``MODULES`` order (so PropertyGroups exist before anything that points at them)
and ``unregister()`` does the reverse.  To add a module, import it here and put
it in ``MODULES``.

Nothing here touches the ``gpu`` module or imports a bundled wheel (scipy,
pytetwild, fast_simplification) at import or register time.
"""

from __future__ import annotations

import bpy

from . import dependencies, panels, properties

MODULES = (properties, dependencies, panels)

# (bpy type, attribute name, PropertyGroup class)
POINTERS = (
    (bpy.types.Object, "translucency", properties.TranslucencyObjectSettings),
    (bpy.types.Scene, "translucency", properties.TranslucencySceneSettings),
)


def _classes():
    for module in MODULES:
        yield from module.CLASSES


def register() -> None:
    for cls in _classes():
        bpy.utils.register_class(cls)
    for owner, attr, group in POINTERS:
        setattr(owner, attr, bpy.props.PointerProperty(
            type=group,
            name="Translucency",
            description="Translucency subsurface scattering settings",
        ))


def unregister() -> None:
    for owner, attr, _group in reversed(POINTERS):
        if hasattr(owner, attr):
            delattr(owner, attr)
    for cls in reversed(tuple(_classes())):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
    dependencies.clear_cache()
