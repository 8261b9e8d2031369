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

Fluid sources (no bake, a fresh solve every frame) that take longer per
frame than ``status.FLUID_LIVE_BUDGET`` are not solved by the frame-change
handler while the viewport plays the animation: :func:`announce_fluids`
leaves them to this throttled check and says in the status bar what a frame
costs; the text goes once playback has stopped and no fluid frame is slow.

Handlers and timers are not operators, so they cannot write to Blender's
Info log themselves: :func:`report_info` hands the messages the runtime
queued (``state.queue_info``: a failed solve, a fluid without particles) to the
``translucency.report`` operator from a one-shot timer.

Progressive frames (Scene › Translucency › *Progressive*, on by default): a
live check gives each diffusion solve the scene's *Frame Budget* (1/30 s),
writes the solution so far (:mod:`translucency_addon.progressive`) and, while
any object is still refining, schedules the next step at once from a timer
(:func:`_refine_timer`), so the viewport redraws between steps and never waits
for a whole solve; the status bar says which objects are refining.  Only the
viewport's live checks are progressive: renders, frame changes and checks in
background mode (``blender -b`` scripts, :func:`flush`) solve to convergence,
unless a caller asks for it (``check_now(progressive=True)``, the tests).

Nothing is scheduled while the add-on is not registered (:func:`enable` /
:func:`disable`, called by ``handlers``).
"""

from __future__ import annotations

import time

import bpy

from . import runtime, state, status
from .fluid_runtime import FluidReport

MIN_INTERVAL = 0.05  # seconds between live checks at least
MAX_INTERVAL = 1.0

_state = {"enabled": False, "last_check": 0.0, "checks": 0, "status_bar": False, "refining": False}


def enable() -> None:
    _state["enabled"] = True


def disable() -> None:
    _state["enabled"] = False
    for timer in (_on_timer, _report_timer, _refine_timer):
        if bpy.app.timers.is_registered(timer):
            bpy.app.timers.unregister(timer)


def request_update(delay: float | None = None) -> None:
    """Schedule a throttled check of every enabled, baked object of the active scene.

    Calls while a check is pending coalesce into it.  The delay is at least
    :data:`MIN_INTERVAL` and at least the last solve's time (capped at
    :data:`MAX_INTERVAL`), so re-solving never takes more than about half of
    Blender's time while the user drags a light; with progressive frames a
    check runs one slice of the frame budget, so the delay is :data:`MIN_INTERVAL`.
    """
    if not _state["enabled"] or bpy.app.timers.is_registered(_on_timer):
        return
    if delay is None and budget(bpy.context.scene) is not None:
        delay = MIN_INTERVAL  # a progressive check runs one slice, not a whole solve
    if delay is None:
        last = max((st.seconds for st in state.all_states()), default=0.0)
        delay = min(MAX_INTERVAL, max(MIN_INTERVAL, last))
    bpy.app.timers.register(_on_timer, first_interval=delay)


def pending() -> bool:
    return bpy.app.timers.is_registered(_on_timer)


def budget(scene, progressive: bool | None = None) -> float | None:
    """The progressive step's time budget in seconds for a live check of ``scene``, or None (converge).

    ``progressive``: None follows the scene's *Progressive* setting in the viewport and converges in
    background mode; True or False decides (tests, scripts)."""
    settings = getattr(scene, "translucency", None)
    if progressive is False or settings is None or not settings.progressive:
        return None
    if progressive is None and bpy.app.background:
        return None
    return max(float(settings.frame_budget_ms), 1.0) / 1000.0


def refining() -> bool:
    """Whether a progressive step is scheduled (an object's solve has not converged yet)."""
    return bpy.app.timers.is_registered(_refine_timer)


def check_now(scene=None, depsgraph=None, progressive: bool | None = None) -> list:
    """Run one live check now (the timer's body); returns the solve reports.  ``progressive``: see
    :func:`budget`."""
    for timer in (_on_timer, _refine_timer):  # this check is the one they would run
        if bpy.app.timers.is_registered(timer):
            bpy.app.timers.unregister(timer)
    scene = scene or bpy.context.scene
    if scene is None or not hasattr(scene, "translucency"):
        return []
    _state["checks"] += 1
    _state["last_check"] = time.perf_counter()
    state.prune(o.name for o in bpy.data.objects)
    reports = runtime.solve_scene(scene, depsgraph, budget=budget(scene, progressive))
    announce_refining(reports)
    announce_fluids(reports)
    report_info()
    return reports


def announce_refining(reports) -> None:
    """Schedule the next progressive step while an object refines, and say so in the status bar."""
    names = [r.name for r in reports if getattr(r, "refining", False)]
    if names:
        if _state["enabled"] and not bpy.app.timers.is_registered(_refine_timer):
            bpy.app.timers.register(_refine_timer, first_interval=0.0)
        status.status_bar("Translucency: refining " + ", ".join(f"'{n}'" for n in names[:3])
                          + (f" and {len(names) - 3} more" if len(names) > 3 else "")
                          + ": the viewport shows the solve so far")
        _state["refining"] = True
    elif _state["refining"]:
        status.status_bar(None)
        _state["refining"] = False


def _refine_timer():
    try:
        check_now()
    except Exception as ex:  # noqa: BLE001 - a timer must not raise
        state.log(f"progressive step failed: {type(ex).__name__}: {ex}")
    return None  # one-shot; a check that still refines schedules the next


def announce_fluids(reports) -> None:
    """Say in the status bar when fluid frames are slow: what one costs, and that playback does not wait for
    them (the frames ``runtime.solve_scene(playback=True)`` deferred, scheduled here for this check).  The
    text goes away at the first check or frame change without a slow fluid once playback has stopped."""
    deferred = [r for r in reports if getattr(r, "deferred", False)]
    slow = [r for r in reports if isinstance(r, FluidReport) and r.seconds > status.FLUID_LIVE_BUDGET]
    if deferred:
        request_update()
    if slow:
        r = max(slow, key=lambda r: r.seconds)
        status.status_bar(f"Translucency: a frame of the fluid '{r.name}' takes {r.seconds:.1f} s ({r.particles:,} "
                          "particles); while the animation plays, its radiance follows about every "
                          f"{min(r.seconds, MAX_INTERVAL):.1f} s instead of every frame (renders solve every frame)")
        _state["status_bar"] = True
    elif _state["status_bar"] and not status.playing():
        status.status_bar(None)
        _state["status_bar"] = False


def report_info() -> None:
    """Hand the queued Info-log messages to the ``translucency.report`` operator (from a timer)."""
    if state.has_info() and _state["enabled"] and not bpy.app.timers.is_registered(_report_timer):
        bpy.app.timers.register(_report_timer, first_interval=0.0)


def _report_timer():
    for level, message in state.take_info():
        try:
            bpy.ops.translucency.report(level=level, message=message)
        except Exception as ex:  # noqa: BLE001 - no window to report to: the console has it already
            state.log(f"could not show in the Info log ({type(ex).__name__}): {message}")
    return None


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
