# SPDX-License-Identifier: GPL-3.0-or-later
"""Live updates: edits schedule one throttled re-solve of the scene.

Setting changes (``properties``' ``update=`` callbacks) and depsgraph updates
(``handlers``) call :func:`request_update`; it registers a one-shot
``bpy.app.timers`` timer, so a burst of edits while dragging coalesces into
one check, and the next check waits at least as long as the last solve took
(Blender stays responsive).  The check, :func:`check_now`, re-solves every
enabled baked object through :func:`.runtime.solve_scene`, which compares a
signature of each solve's inputs with the last one, so a check after an
unrelated edit costs little.  Timers never fire in background mode:
:func:`flush` runs a pending check at once (tests, scripts).

Nothing is scheduled while the add-on is not registered (:func:`enable` /
:func:`disable`, called by ``handlers``).
"""

from __future__ import annotations

import time

import bpy

from . import runtime, state

MIN_INTERVAL = 0.05  # seconds between live checks at least
MAX_INTERVAL = 1.0

_state = {"enabled": False, "last_check": 0.0, "checks": 0}


def enable() -> None:
    _state["enabled"] = True


def disable() -> None:
    _state["enabled"] = False
    if bpy.app.timers.is_registered(_on_timer):
        bpy.app.timers.unregister(_on_timer)


def request_update(delay: float | None = None) -> None:
    """Schedule a throttled check of every enabled, baked object of the active scene.

    Calls while a check is pending coalesce into it.  The delay is at least
    :data:`MIN_INTERVAL` and at least the last solve's time (capped at
    :data:`MAX_INTERVAL`), so re-solving never takes more than about half of
    Blender's time while the user drags a light.
    """
    if not _state["enabled"] or bpy.app.timers.is_registered(_on_timer):
        return
    if delay is None:
        last = max((st.seconds for st in list(state._STATES.values())), default=0.0)
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
    state.prune(o.name for o in bpy.data.objects)
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
        state.log(f"live update failed: {type(ex).__name__}: {ex}")
    return None  # one-shot; the next depsgraph update schedules again
