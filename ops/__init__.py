# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender side of Translucency: operators, panels, PropertyGroups, handlers.

Each module has one ``CLASSES`` tuple.  ``register()`` registers the modules in
``MODULES`` order (so PropertyGroups exist before anything that points at them)
and ``unregister()`` does the reverse.  To add a module, import it here and put
it in ``MODULES``.

A module may also define ``on_register()`` and ``on_unregister()``: they are
called after all classes are registered (in ``MODULES`` order) and before any
class is unregistered (in reverse order).  Use them for application handlers,
timers and draw handlers (``handlers`` adds its ``bpy.app.handlers`` there);
``on_unregister`` must remove everything ``on_register`` added.

Nothing here touches the ``gpu`` module or imports a bundled wheel (scipy,
pytetwild, fast_simplification) at import or register time.
"""

from __future__ import annotations

import traceback

import bpy

from . import (  # the modules that register something; they import the rest (docs/architecture.md, the house)
    dependencies,
    handlers,
    operators_bake,
    operators_parts,
    operators_solve,
    overlay,
    panels,
    properties,
    render_pass,
)

MODULES = (properties, dependencies, operators_bake, operators_parts, operators_solve, overlay, render_pass, handlers,
           panels)

# (bpy type, attribute name, PropertyGroup class)
POINTERS = (
    (bpy.types.Object, "translucency", properties.TranslucencyObjectSettings),
    (bpy.types.Scene, "translucency", properties.TranslucencySceneSettings),
)


def _classes():
    for module in MODULES:
        yield from getattr(module, "CLASSES", ())


def register() -> None:
    for cls in _classes():
        bpy.utils.register_class(cls)
    for owner, attr, group in POINTERS:
        setattr(owner, attr, bpy.props.PointerProperty(
            type=group,
            name="Translucency",
            description="Translucency subsurface scattering settings",
        ))
    for module in MODULES:
        hook = getattr(module, "on_register", None)
        if callable(hook):
            hook()


def unregister() -> None:
    for module in reversed(MODULES):
        hook = getattr(module, "on_unregister", None)
        if callable(hook):
            try:
                hook()
            except Exception:  # noqa: BLE001 - keep unregistering the rest
                traceback.print_exc()
    for owner, attr, _group in reversed(POINTERS):
        if hasattr(owner, attr):
            delattr(owner, attr)
    for cls in reversed(tuple(_classes())):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
    dependencies.clear_cache()
