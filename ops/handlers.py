# SPDX-License-Identifier: GPL-3.0-or-later
"""Application handlers: live re-solves, renders, file loads, undo.

* ``depsgraph_update_post``: something changed (a light moved or changed
  power/colour, the world, a texture, the object's settings, transform or
  mesh, another object that casts shadows).  It only *schedules* a check
  with :func:`.live.request_update` (throttled, coalesced; see :mod:`.live`).
  Every check compares a signature of the solve's inputs with the last
  solve's, so our own attribute writes (which cause depsgraph updates too)
  never trigger another solve.
* ``frame_change_post``: re-solve for the new frame (Fluid sources too: a
  fresh solve of their particles every frame; while the viewport plays, a
  fluid slower than ``status.FLUID_LIVE_BUDGET`` per frame is left to the
  throttled live check, ``live.announce_fluids``).  With a *render*
  depsgraph (``depsgraph.mode == 'RENDER'``: F12, ``-f``/``-a``, and
  ``bpy.ops.render.render``) the radiance is evaluated towards the render
  camera.  Measured in Blender 5.0: in ``frame_change_pre`` neither the
  original nor the evaluated data hold the new frame's animated values yet
  (a light keyed from 10 W to 100 W still reads 10 W at frame 10), and during
  ``render(animation=True)`` the originals are never updated at all; only the
  depsgraph passed to ``frame_change_post`` has them, and an attribute
  written there is picked up by the frame being rendered (Cycles, tested).
  ``frame_change_pre`` therefore only invalidates cached geometry.
  An object animated by an armature, shape keys or deform modifiers needs
  nothing else here: each solve compares the evaluated mesh with the bake
  (``cache_files``) and solves a pose on the deformed graph
  (``deformation``), or reports a change of topology.
* a render (any of the above) never bakes and never writes a cache, and a
  frame's pass is computed from a valid bake and this frame's inputs or not
  at all: an object whose solve fails for the frame (its cache is missing,
  unreadable or from another version of the extension, its bake is stale --
  ``runtime`` refuses to solve a bake that no longer matches the mesh --, the
  deformation check refuses its pose, or any other error) loses its radiance
  attribute for the frame, and the scene's ``missing_cache_in_render``
  decides: ``FAIL`` stops a background render with exit code 1 and the
  reason as the log's last line (a farm marks the frame failed), ``SKIP``
  renders it without the pass (:func:`_render_without_cache`).  Never a pass
  from another frame, another pose or a stale bake, whatever the worker
  rendered before.
* ``render_init``/``render_pre``/``render_post``/``render_cancel``/
  ``render_complete``: track whether a render is running (for the log).
* ``load_post``: drop all runtime state (GPU memory too), move the status a
  file older than ``ops.status`` saved among the settings, look for every
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
Timers never fire in background mode; :func:`.live.flush` runs a pending
check at once (tests, scripts).

These functions are where Blender calls in; they call down (``live``,
``runtime``, ``cache_files``, ``status``, ``state``), never the reverse.
"""

from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

from . import attributes, cache_files, live, runtime, state, status

_MARK = "_translucency_handler"

_state = {"rendering": False}


def _mark(fn):
    setattr(fn, _MARK, True)
    return fn


# ------------------------------------------------------------------ handlers


@persistent
def on_depsgraph_update_post(scene, depsgraph=None):
    if depsgraph is None or not hasattr(scene, "translucency") or not scene.translucency.live_update:
        return
    own = state.take_own_writes()
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
                state.bump_geometry_epoch(orig.name)
            relevant = True
        elif isinstance(orig, bpy.types.Mesh):
            continue  # reported through its object (or one of ours)
        else:
            relevant = True  # lights, world, textures, scene settings, materials, collections ...
    if relevant and (state.baked_objects(scene) or state.fluid_objects(scene)):
        live.request_update()


@persistent
def on_frame_change_pre(scene, depsgraph=None):
    # Animated values are not evaluated yet here (see the module docstring):
    # only forget cached geometry so vertex-group fields are re-read.
    state.bump_geometry_epoch()


@persistent
def on_frame_change_post(scene, depsgraph=None):
    if not hasattr(scene, "translucency"):
        return
    rendering = depsgraph is not None and getattr(depsgraph, "mode", "VIEWPORT") == 'RENDER'
    if not rendering and not scene.translucency.live_update:
        return
    failed = []
    reports = runtime.solve_scene(scene, depsgraph, use_camera=rendering, playback=not rendering and status.playing(),
                                  failed=failed)
    if rendering:
        for r in reports:
            state.log(f"frame {scene.frame_current}: {r.describe()}, view towards the camera")
        if failed:  # a cache problem, a stale bake, a refused pose, any error: never another frame's pass
            _render_without_cache(scene, [(name, message) for name, message, _cache in failed])
    else:
        live.announce_fluids(reports)
    live.report_info()


FARM_EXIT_CODE = 1  # a background render stopped by a frame that cannot be solved (render farms read it)


def _render_without_cache(scene, problems: list[tuple[str, str]]) -> None:
    """A render could not solve some objects for this frame (a farm worker without the cache folder, a stale
    bake, a refused pose, an error).

    Nothing is baked here.  Each object's radiance attribute is removed, so the frame can never carry the
    values the .blend was saved with (another frame's).  ``missing_cache_in_render``: ``FAIL`` (default)
    stops a background render (``blender -b``, the bpy module) with :data:`FARM_EXIT_CODE` before the frame
    is written, so Flamenco or Deadline marks the frame failed, with the reason as the last lines of the
    log; in the UI (where a render cannot be stopped from here) and with ``SKIP`` the frame renders without
    the objects' pass and the log says so.
    """
    import os
    import sys

    frame = scene.frame_current
    for name, _message in problems:
        obj = bpy.data.objects.get(name)
        if obj is not None and obj.type == 'MESH':
            attributes.remove_attribute(obj)
            attributes.remove_attribute(obj, attributes.SS_ATTRIBUTE_NAME)
    reasons = "; ".join(f"'{name}': {message}" for name, message in problems)
    if scene.translucency.missing_cache_in_render == 'FAIL' and bpy.app.background:
        text = (f"Translucency: frame {frame} FAILED, the render stops with exit code {FARM_EXIT_CODE} and writes "
                f"no image: {reasons}. (Scene > Translucency > Cache Missing in Render = 'Render Without' renders "
                "such frames without the pass instead.)")
        for stream in (sys.stdout, sys.stderr):
            print(text, file=stream, flush=True)
        os._exit(FARM_EXIT_CODE)  # a handler cannot cancel a render; SystemExit would be printed and ignored
    for name, message in problems:
        state.log(f"frame {frame}: '{name}' renders WITHOUT its Translucency pass: {message}",
                  once_key=("render-without", name, message, frame))


@persistent
def on_render_init(scene, *_args):
    _state["rendering"] = True


@persistent
def on_render_end(scene, *_args):
    _state["rendering"] = False


@persistent
def on_load_post(*_args):
    state.clear()
    for sc in bpy.data.scenes:
        if hasattr(sc, "translucency"):
            status.migrate_legacy_scene(sc)
    scene = bpy.context.scene
    depsgraph = None
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    except Exception:  # noqa: BLE001 - no view layer (e.g. an empty file)
        pass
    for obj in bpy.data.objects:
        if obj.type != 'MESH' or not hasattr(obj, "translucency"):
            continue
        status.migrate_legacy(obj)  # a file saved before the status had its own group
        if not obj.translucency.cache_filepath:
            continue
        in_scene = scene is not None and obj.name in scene.objects
        found = cache_files.check_cache(obj, depsgraph if in_scene else None)
        baked = found.startswith("Baked")
        state.set_cache_problem(obj.name, None if baked else found)  # shown by the panel; the .blend is not modified
        if not baked:
            state.log(f"'{obj.name}': {found}")


@persistent
def on_undo_redo(*_args):
    state.invalidate_views()
    for st in state.object_states():
        name = st.name
        obj = bpy.data.objects.get(name)
        if obj is None or obj.type != 'MESH' or obj.translucency.bake_key != st.key:
            state.drop_state(name)
    scene = bpy.context.scene
    if scene is not None and hasattr(scene, "translucency") and scene.translucency.live_update:
        live.request_update()


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
    live.enable()


def unregister_handlers() -> None:
    live.disable()
    _remove_marked()
    state.clear()


def on_register() -> None:
    register_handlers()


def on_unregister() -> None:
    unregister_handlers()


CLASSES = ()
