# SPDX-License-Identifier: GPL-3.0-or-later
"""What the panel reports about an object, kept apart from its settings.

* The **bake status** (``obj.translucency.status``, a
  :class:`~.properties.TranslucencyObjectStatus`): what the last bake
  produced -- node counts per level, graph memory, times, warnings,
  single-scattering samples.  Saved in the .blend (it describes the cache the
  file points to); :func:`set_bake_status` writes it after a bake and
  :func:`clear_bake_status` resets it; nothing else writes it.
* The **solve status** (:func:`solve_status`): where and how fast the last
  solve ran, its residual, the fallback reason or the last error, the
  single-scattering time, backend and staleness, and on a deformed frame the
  pose's worst link stretch (or why the pose was refused).  It changes every frame, so
  it lives in the object's runtime state (:mod:`.state`) and is never saved:
  a solve writes no property and so causes no depsgraph update of its own.
  :func:`publish` tells the panels to redraw after a solve.

A **Fluid source** has no bake: its status is all runtime (:func:`fluid_lines`:
the particles, the radius, what a frame costs stage by stage, why there were
no particles, warnings), and while the viewport plays an animation whose
fluid frames take longer than :data:`FLUID_LIVE_BUDGET`, the status bar says
that the live check, not playback, paces the fluid (:func:`status_bar`).

Files saved before the status had its own group kept these values among the
settings; :func:`migrate_legacy` moves them on load (``handlers.on_load_post``).
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy

from . import inner_parts, state

SS_STAGE_NAMES = {"voxelise": "voxelise", "ddod": "optical depth", "div": "divergence", "pds": "Poisson-disk samples",
                  "rbf": "RBF fit", "sh": "spherical harmonics", "grid": "sample grid"}

# Bake-status names that files older than the status group stored among the settings (moved on
# load), and the per-frame solve outputs they stored there and in the scene (dropped on load).
LEGACY_BAKE_STATUS = ("bake_status", "bake_stats", "bake_memory", "bake_seconds", "bake_warnings", "bake_vertices",
                      "ss_bake_stats", "ss_bake_seconds", "ss_samples_baked", "bake_levels")
LEGACY_SOLVE_STATUS = ("solve_seconds", "solve_residual", "solve_iterations", "solve_backend", "solve_message",
                       "ss_solve_seconds", "ss_backend", "ss_message")
LEGACY_SCENE_STATUS = ("last_solve_time", "last_residual", "last_backend")


# A fluid frame slower than this (seconds) is not solved in the frame-change handler while the viewport plays
# the animation: the throttled live check solves the frame shown when it runs, so playback keeps its pace.
FLUID_LIVE_BUDGET = 0.1


def _format_count(n: int) -> str:
    return f"{n:,}"


# ------------------------------------------------------------------ bake status (saved)


def set_bake_status(obj, bake, *, graph_seconds: float, ss_seconds: float, notes=()) -> list[str]:
    """Write what ``bake`` produced into ``obj.translucency.status``; returns the bake's warnings.

    ``graph_seconds``: the QuadGraph bake's time; ``ss_seconds``: the single-scattering bake's;
    ``notes``: warnings of the Blender side (scale, cache folder) to keep with the mesh's own.
    """
    s = obj.translucency.status
    s.bake_levels.clear()
    for lv in bake.levels:
        item = s.bake_levels.add()
        item.n_surface = int(lv.n_surface)
        item.n_inner = int(lv.n_inner)
    s.bake_memory = bake.graph_bytes() / 2**20
    s.bake_seconds = float(graph_seconds)
    s.bake_vertices = inner_parts.n_outer_vertices(bake)
    s.parts_bake_stats, parts_warnings = inner_parts.bake_summary(bake)
    warnings = list(bake.stats.get("mesh", {}).get("warnings", [])) + parts_warnings + list(notes)
    s.bake_stats = (
        "N_s " + " / ".join(_format_count(lv.n_surface) for lv in bake.levels)
        + "; N_i " + " / ".join(_format_count(lv.n_inner) for lv in bake.levels)
        + f"; {s.bake_memory:.1f} MiB; {graph_seconds:.1f} s"
    )
    ss = bake.single_scattering
    if ss is not None:
        t = ss.stats.get("time", {})
        s.ss_samples_baked = int(ss.n_samples)
        s.ss_bake_seconds = float(ss_seconds)
        s.ss_bake_stats = (f"{ss.n_samples:,} samples, {ss.n_dirs} directions, SH order {ss.order}, voxels "
                           + "x".join(str(v) for v in ss.stats.get("voxels", [])) + f"; {ss_seconds:.1f} s ("
                           + ", ".join(f"{SS_STAGE_NAMES.get(k, k)} {v:.1f}" for k, v in t.items()) + ")")
        mfp = ss.stats.get("mean_free_path_voxels")
        if mfp is not None and mfp < 0.5:
            warnings.append(f"single scattering: the mean free path is {mfp:.2f} voxel; the voxels cannot "
                            "resolve it, so the term comes out too dark (raise SS Quality or check the scale)")
    else:
        s.ss_samples_baked = 0
        s.ss_bake_seconds = 0.0
        s.ss_bake_stats = ""
    s.bake_warnings = "\n".join(warnings)
    s.bake_status = "Baked"
    state.set_solve_error(obj.name, None)
    return warnings


def clear_bake_status(obj) -> None:
    """Reset ``obj.translucency.status`` to "Not baked" (every value to its default)."""
    s = obj.translucency.status
    s.bake_levels.clear()
    for prop in s.bl_rna.properties:
        if prop.identifier not in ("rna_type", "bake_levels"):
            s.property_unset(prop.identifier)
    state.set_solve_error(obj.name, None)


def migrate_legacy(obj) -> bool:
    """Move the status an older file saved among ``obj``'s settings into its status group.

    The old names are no longer properties of the settings, but the file still holds their values
    as ID properties; the bake status is copied, the per-frame solve outputs are dropped.  Returns
    whether anything was moved.
    """
    s = obj.translucency
    keys = set(s.keys())
    old = keys & set(LEGACY_BAKE_STATUS + LEGACY_SOLVE_STATUS)
    if not old:
        return False
    status = s.status
    for name in LEGACY_BAKE_STATUS:
        if name not in keys:
            continue
        value = s[name]
        if name == "bake_levels":
            status.bake_levels.clear()
            for lv in value:
                item = status.bake_levels.add()
                item.n_surface = int(lv.get("n_surface", 0))
                item.n_inner = int(lv.get("n_inner", 0))
        else:
            setattr(status, name, value)
    for name in old:
        del s[name]
    return True


def migrate_legacy_scene(scene) -> None:
    """Drop the per-frame solve outputs an older file saved among the scene's settings."""
    s = scene.translucency
    for name in set(s.keys()) & set(LEGACY_SCENE_STATUS):
        del s[name]


# ------------------------------------------------------------------ solve status (runtime only)


@dataclass(frozen=True)
class SolveStatus:
    """The last solve of one object, as the panel shows it (from the runtime state; never saved)."""

    backend: str  # where the diffusion solver runs: GPU or CPU ('' before the first solve)
    seconds: float  # the last solve's wall-clock time
    residual: float
    iterations: int
    message: str  # the last error, else why the solver is not on the GPU, and a stale bake
    ss_backend: str  # where the last single-scattering ray pass ran ('' when it did not run)
    ss_seconds: float
    ss_message: str  # why single scattering needs a re-bake, else why it is not on the GPU
    deformation: str = ""  # a deformed frame: the pose's worst link stretch, or that it was refused
    vnm_backend: str = ""  # where the Voxel Number Map's transport last ran ('' when it did not run)
    vnm_seconds: float = 0.0
    vnm_message: str = ""  # why the map's transport is not on the GPU


def solve_status(obj) -> SolveStatus:
    """The object's solve status (empty before its first solve in this session)."""
    st = state.get_state(obj)
    error = state.solve_error(obj.name)
    if st is None:
        return SolveStatus("", 0.0, 0.0, 0, error, "", 0.0, "")
    message = st.frame_backend_message
    if st.stale_message:
        message = (message + "; " if message else "") + "stale bake: " + st.stale_message
    ss_ran = st.ss_rgb is not None
    return SolveStatus(
        backend=st.frame_backend, seconds=float(st.seconds), residual=float(st.residual),
        iterations=int(st.iterations), message=error or message, ss_backend=st.ss_backend if ss_ran else "",
        ss_seconds=float(st.ss_seconds), ss_message=st.ss_stale or (st.ss_backend_message if ss_ran else ""),
        deformation=st.deformation.describe() if st.pose is not None else "",
        vnm_backend=st.vnm_backend, vnm_seconds=float(st.vnm_seconds),
        vnm_message=st.vnm_backend_message if st.vnm_backend else "")


def world_line(obj) -> tuple[str, bool]:
    """The World's line for the panel and whether it is a warning: the fallback's reason when the object's last
    frame fell back, else what the World became (``ops.world.status_line``: SH order, the HDRI's sun)."""
    from . import world

    st = state.get_state(obj)
    for w in (st.warnings if st is not None else ()):
        if w.startswith("world '"):
            return w, True
    return world.status_line(), False


def last_solve() -> dict:
    """The last solve of any object: ``{"name", "seconds", "residual", "backend"}`` (empty before one)."""
    return state.last_solve()


def plan_summary(name: str) -> str:
    """The last plan of an object as text for the panel ('' when it has not been solved)."""
    from ..translucency_addon.planner import describe_plan

    plan = state.last_plan(name)
    return describe_plan(plan) if plan is not None else ""


def publish(st: state.ObjectState) -> None:
    """After a solve on the main thread: record it as the scene's last and redraw the panels showing it."""
    state.set_solve_error(st.name, None)
    state.set_last_solve(name=st.name, seconds=float(st.seconds), residual=float(st.residual),
                         backend=st.frame_backend)
    state.set_cache_problem(st.name, f"Stale: {st.stale_message}" if st.stale_message else None)
    tag_redraw()


def report_error(name: str, message: str) -> None:
    """The last solve of ``name`` failed: the panel shows ``message`` until a solve succeeds.

    A new message also goes to Blender's Info log (``state.queue_info``, handed on by ``live.report_info``).
    """
    if state.set_solve_error(name, message):
        state.queue_info('ERROR', f"'{name}': {message}")
    tag_redraw()


def fluid_lines(obj) -> list[str]:
    """What the panel says about a Fluid source's last frame (runtime state; empty before its first)."""
    st = state.fluid_state_of(obj.name)
    if st is None or not st.sig:
        return []
    lines = [f"Frame {st.frame}: {st.particles:,} particles ({st.source}) -> {st.output}"
             + (" through the Translucency Radiance modifier" if st.carried else "")]
    if st.empty:
        lines.append(f"{st.empty}: radiance 0")
        return lines
    if st.radius > 0:
        lines.append(f"Radius {st.radius:.4g} scene units" + (" (auto: the particle spacing)"
                                                               if obj.translucency.fluid_radius_auto else ""))
    if st.stages:
        stages = ", ".join(f"{k} {st.stages[k]:.2f}" for k in ("cells", "light", "solve", "output") if k in st.stages)
        lines.append(f"A frame costs {st.seconds:.2f} s on the {st.backend} ({stages} s); {st.cells:,} cells, "
                     f"{st.surface_cells:,} at the surface")
        lines.append(f"{st.iterations} sweeps, residual {st.residual:.2e}"
                     + (", warm-started from the last frame" if st.warm_started else ", cold start"))
        if st.backend_message:  # why not on the GPU (a fallback, or the GPU cannot run here)
            lines.append(f"Diffusion on the CPU: {st.backend_message}")
    if st.seconds > FLUID_LIVE_BUDGET:
        lines.append(f"Playback: frames over {FLUID_LIVE_BUDGET:g} s are left to the live check, which solves the "
                     f"frame shown about every {min(st.seconds, 1.0):.1f} s; renders solve every frame")
    return lines


def playing() -> bool:
    """The viewport is playing the animation."""
    screen = getattr(bpy.context, "screen", None)
    return bool(screen is not None and screen.is_animation_playing)


def status_bar(text: str | None) -> None:
    """Put ``text`` in the status bar (``None``: give it back to Blender); nothing without a window."""
    workspace = getattr(bpy.context, "workspace", None)
    if workspace is not None and getattr(bpy.context, "window", None) is not None:
        workspace.status_text_set(text)


def tag_redraw() -> None:
    """Redraw the areas that show the Translucency panel (Properties and the 3D View's sidebar)."""
    wm = getattr(bpy.context, "window_manager", None)
    for window in getattr(wm, "windows", ()):
        for area in getattr(window.screen, "areas", ()):
            if area.type in {'PROPERTIES', 'VIEW_3D'}:
                area.tag_redraw()
