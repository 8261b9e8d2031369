# SPDX-License-Identifier: GPL-3.0-or-later
"""Application handlers: live re-solves, renders, file loads, undo.

* ``depsgraph_update_post``: something changed (a light moved or changed
  power/colour, the world, a texture, the object's settings, transform or
  mesh, another object that casts shadows).  It only *schedules* a check
  with :func:`request_update`; the check runs from a ``bpy.app.timers`` timer,
  so a burst of updates while dragging coalesces into one solve, and the
  next check waits at least as long as the last solve took (Blender stays
  responsive).  Every check compares a signature of the solve's inputs with
  the last solve's, so our own attribute writes (which cause depsgraph
  updates too) never trigger another solve.
* ``frame_change_post``: re-solve for the new frame.  With a *render*
  depsgraph (``depsgraph.mode == 'RENDER'``: F12, ``-f``/``-a``, and
  ``bpy.ops.render.render``) the radiance is evaluated towards the render
  camera.  Measured in Blender 5.0: in ``frame_change_pre`` neither the
  original nor the evaluated data hold the new frame's animated values yet
  (a light keyed from 10 W to 100 W still reads 10 W at frame 10), and during
  ``render(animation=True)`` the originals are never updated at all; only the
  depsgraph passed to ``frame_change_post`` has them, and an attribute
  written there is picked up by the frame being rendered (Cycles, tested).
  ``frame_change_pre`` therefore only invalidates cached geometry.
* ``render_init``/``render_pre``/``render_post``/``render_cancel``/
  ``render_complete``: track whether a render is running (for the log).
* ``load_post``: drop all runtime state (GPU memory too), look for every
  baked object's cache and report missing or stale ones in the panel.
* ``undo_post``/``redo_post``: states of objects whose bake key changed are
  dropped and re-loaded lazily; the attribute is rewritten on the next check.

All handlers are ``@persistent`` (they survive file loads), carry a marker
attribute, and :func:`unregister_handlers` removes every marked function, so
no duplicates survive a re-register or a module reload.

Headless (``blender -b scene.blend -f 1`` or bpy from PyPI with
``scene.frame_set(f)`` and ``bpy.ops.render.render(write_still=True)``): the
render depsgraph's ``frame_change_post`` solves every enabled baked object,
on the GPU when Blender has a GPU context and on the CPU otherwise, and the
console log says which (``Translucency: 'Obj' solves on the CPU (...)``).
Timers never fire in background mode; :func:`flush` runs a pending check
at once (tests, scripts).
"""

from __future__ import annotations

import time

import bpy
from bpy.app.handlers import persistent

from . import runtime

MIN_INTERVAL = 0.05  # seconds between live checks at least
MAX_INTERVAL = 1.0
_MARK = "_translucency_handler"

_state = {"registered": False, "rendering": False, "last_check": 0.0, "checks": 0}


def _mark(fn):
    setattr(fn, _MARK, True)
    return fn


# ------------------------------------------------------------------ scheduling


def request_update(delay: float | None = None) -> None:
    """Schedule a throttled check of every enabled, baked object of the active scene.

    Calls while a check is pending coalesce into it.  The delay is at least
    :data:`MIN_INTERVAL` and at least the last solve's time (capped at
    :data:`MAX_INTERVAL`), so re-solving never takes more than about half of
    Blender's time while the user drags a light.
    """
    if not _state["registered"] or bpy.app.timers.is_registered(_on_timer):
        return
    if delay is None:
        last = max((st.seconds for st in list(runtime._STATES.values())), default=0.0)
        delay = min(MAX_INTERVAL, max(MIN_INTERVAL, last))
    bpy.app.timers.register(_on_timer, first_interval=delay)


def pending() -> bool:
    return bpy.app.timers.is_registered(_on_timer)


def check_now(scene=None, depsgraph=None) -> list:
    """Run one live check now (the timer's body); returns the solve reports."""
    if bpy.app.timers.is_registered(_on_timer):
        bpy.app.timers.unregister(_on_timer)
    scene = scene or bpy.context.scene
    if scene is None or not hasattr(scene, "translucency"):
        return []
    _state["checks"] += 1
    _state["last_check"] = time.perf_counter()
    runtime.prune(o.name for o in bpy.data.objects)
    return runtime.solve_scene(scene, depsgraph)


def flush() -> list:
    """Run a pending check at once (background mode has no event loop for timers)."""
    if not pending():
        return []
    return check_now()


def _on_timer():
    try:
        check_now()
    except Exception as ex:  # noqa: BLE001 - a timer must not raise
        runtime.log(f"live update failed: {type(ex).__name__}: {ex}")
    return None  # one-shot; the next depsgraph update schedules again


# ------------------------------------------------------------------ handlers


@persistent
def on_depsgraph_update_post(scene, depsgraph=None):
    if depsgraph is None or not hasattr(scene, "translucency") or not scene.translucency.live_update:
        return
    own = runtime.OWN_WRITES
    updates = list(depsgraph.updates)
    # Some edits (a texture's settings) send an update with an empty list: check anyway.
    relevant = not updates
    for update in updates:
        ident = update.id
        orig = getattr(ident, "original", None) or ident
        if isinstance(orig, bpy.types.Object):
            if orig.name in own and not update.is_updated_transform:
                continue  # the geometry update our own attribute write caused
            if update.is_updated_geometry:
                runtime.GEOMETRY_EPOCH[orig.name] = runtime.GEOMETRY_EPOCH.get(orig.name, 0) + 1
            relevant = True
        elif isinstance(orig, bpy.types.Mesh):
            continue  # reported through its object (or one of ours)
        else:
            relevant = True  # lights, world, textures, scene settings, materials, collections ...
    own.clear()
    if relevant and runtime.baked_objects(scene):
        request_update()


@persistent
def on_frame_change_pre(scene, depsgraph=None):
    # Animated values are not evaluated yet here (see the module docstring):
    # only forget cached geometry so vertex-group fields are re-read.
    runtime.GEOMETRY_EPOCH[runtime.FRAME_EPOCH] = runtime.GEOMETRY_EPOCH.get(runtime.FRAME_EPOCH, 0) + 1


@persistent
def on_frame_change_post(scene, depsgraph=None):
    if not hasattr(scene, "translucency"):
        return
    rendering = depsgraph is not None and getattr(depsgraph, "mode", "VIEWPORT") == 'RENDER'
    if not rendering and not scene.translucency.live_update:
        return
    reports = runtime.solve_scene(scene, depsgraph, use_camera=rendering)
    if rendering:
        for r in reports:
            runtime.log(f"frame {scene.frame_current}: {r.describe()}, view towards the camera")


@persistent
def on_render_init(scene, *_args):
    _state["rendering"] = True


@persistent
def on_render_end(scene, *_args):
    _state["rendering"] = False


@persistent
def on_load_post(*_args):
    runtime.clear()
    scene = bpy.context.scene
    depsgraph = None
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    except Exception:  # noqa: BLE001 - no view layer (e.g. an empty file)
        pass
    for obj in bpy.data.objects:
        if obj.type != 'MESH' or not hasattr(obj, "translucency") or not obj.translucency.cache_filepath:
            continue
        in_scene = scene is not None and obj.name in scene.objects
        status = runtime.check_cache(obj, depsgraph if in_scene else None)
        if status.startswith("Baked"):
            runtime.CACHE_STATUS.pop(obj.name, None)
        else:
            runtime.CACHE_STATUS[obj.name] = status  # shown by the panel; the .blend is not modified
            runtime.log(f"'{obj.name}': {status}")


@persistent
def on_undo_redo(*_args):
    runtime.invalidate_views()
    for name, st in list(runtime._STATES.items()):
        obj = bpy.data.objects.get(name)
        if obj is None or obj.type != 'MESH' or obj.translucency.bake_key != st.key:
            runtime.drop_state(name)
    scene = bpy.context.scene
    if scene is not None and hasattr(scene, "translucency") and scene.translucency.live_update:
        request_update()


HANDLERS = (
    ("depsgraph_update_post", on_depsgraph_update_post),
    ("frame_change_pre", on_frame_change_pre),
    ("frame_change_post", on_frame_change_post),
    ("render_init", on_render_init),
    ("render_pre", on_render_init),
    ("render_post", on_render_end),
    ("render_cancel", on_render_end),
    ("render_complete", on_render_end),
    ("load_post", on_load_post),
    ("undo_post", on_undo_redo),
    ("redo_post", on_undo_redo),
)
for _name, _fn in HANDLERS:
    _mark(_fn)


def _remove_marked() -> None:
    for name, _fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        for fn in list(lst):
            if getattr(fn, _MARK, False):
                lst.remove(fn)


def registered_handlers() -> list[tuple[str, object]]:
    """Every handler of ours currently in ``bpy.app.handlers`` (for tests)."""
    out = []
    for name in dir(bpy.app.handlers):
        lst = getattr(bpy.app.handlers, name)
        if isinstance(lst, list):
            out.extend((name, fn) for fn in lst if getattr(fn, _MARK, False))
    return out


def register_handlers() -> None:
    _remove_marked()  # never twice, even after a module reload
    for name, fn in HANDLERS:
        getattr(bpy.app.handlers, name).append(fn)
    _state["registered"] = True


def unregister_handlers() -> None:
    _state["registered"] = False
    _remove_marked()
    if bpy.app.timers.is_registered(_on_timer):
        bpy.app.timers.unregister(_on_timer)
    runtime.clear()


def on_register() -> None:
    register_handlers()


def on_unregister() -> None:
    unregister_handlers()


CLASSES = ()
