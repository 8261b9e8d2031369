# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Translucency" panel, in Properties > Object and in the 3D View sidebar.

Both panels share :func:`draw_translucency`.  If a bundled dependency does not
import, the panel lists what is missing (with the import error) and draws
nothing else, so a broken wheel never breaks the UI.

Sections: the source (a baked Mesh, or a Fluid: where its particles come
from, their radius, what a frame costs; no bake), bake settings, the terms (multiple scattering, single scattering
with its bake settings and Split Pass), Bake / Free Bake / Bake Single
Scattering, bake status and statistics (the saved ``translucency.status``: N_s
and N_i per level, graph memory, bake time, single-scattering samples and time
per stage, warnings; cache problems found after a file load), material,
heterogeneity field, the inner parts (the list with each part's object, role and
a medium's material; the Voxel Number Map's settings; what the last bake made of
them), Solve with the last solve time, iterations, residual,
backend and fallback message, on a deformed frame the pose's worst link
stretch (or that it was refused), the single-scattering and Voxel Number Map
times and backends and why single scattering
needs a re-bake (``status.solve_status``: runtime state, never saved), the
cache file, then the hooks of the optional modules (``overlay.draw_settings``
and ``render_pass.draw_settings``, see :func:`_draw_hooks`) and the scene
settings.
"""

from __future__ import annotations

import bpy

from . import dependencies, state, status


def _draw_missing_dependencies(layout, problems) -> None:
    box = layout.box()
    box.alert = True
    box.label(text="Missing dependencies", icon='ERROR')
    for name, error in problems:
        col = box.column(align=True)
        col.label(text=f"{name} does not import:")
        # Long import errors are split so they stay readable in a narrow panel.
        for start in range(0, len(error), 60):
            col.label(text="    " + error[start:start + 60])
    box.label(text="Reinstall the extension zip built for this platform.")
    box.operator("translucency.check_dependencies", icon='FILE_REFRESH')


def _draw_multiline(layout, text: str, icon='NONE', width: int = 70) -> None:
    first = True
    for line in text.splitlines():
        for start in range(0, max(len(line), 1), width):
            layout.label(text=line[start:start + width], icon=icon if first else 'BLANK1')
            first = False


def _draw_terms(layout, settings) -> None:
    """Which terms are added, and the single-scattering bake settings."""
    col = layout.column()
    col.prop(settings, "use_multiple_scattering")
    col.prop(settings, "use_single_scattering")
    col.prop(settings, "pass_planning")
    sub = col.column()
    sub.active = settings.use_single_scattering
    sub.prop(settings, "ss_quality")
    sub.prop(settings, "ss_directions")
    sub.prop(settings, "ss_samples")
    sub.prop(settings, "ss_sh_order")
    sub.prop(settings, "ss_split_pass")


def _draw_object_settings(layout, obj, context=None) -> None:
    settings = obj.translucency
    layout.prop(settings, "enabled")

    col = layout.column()
    col.active = settings.enabled
    if obj.type in {'MESH', 'POINTCLOUD'}:
        col.row().prop(settings, "source", expand=True)
    if state.is_fluid(obj):
        _draw_fluid(col, obj, context)
        return
    if obj.type == 'POINTCLOUD':
        col.label(text="A point cloud is translucent as a Fluid: set Source to Fluid", icon='INFO')

    # -- bake --------------------------------------------------------------------
    box = col.box()
    box.label(text="Bake", icon='MOD_REMESH')
    box.prop(settings, "quality")
    box.prop(settings, "levels")
    box.prop(settings, "sky_occlusion")
    _draw_scale(box, obj, context)
    _draw_terms(box, settings)
    if obj.type == 'MESH':
        row = box.row(align=True)
        row.operator("translucency.bake", icon='RENDER_STILL',
                     text="Re-Bake" if settings.bake_key else "Bake")
        row.operator("translucency.free_bake", icon='TRASH', text="Free Bake")
        if settings.use_single_scattering:
            row = box.row()
            row.enabled = bool(settings.bake_key)
            row.operator("translucency.bake_single_scattering", icon='LIGHT_SUN')
    baked = settings.status
    box.label(text=f"Status: {baked.bake_status}")
    problem = state.cache_problem(obj.name)
    if problem:
        _draw_multiline(box, problem, icon='ERROR')
    if len(baked.bake_levels):
        grid = box.column(align=True)
        grid.label(text="Level     N_s (surface)     N_i (inner)")
        for i, lv in enumerate(baked.bake_levels):
            grid.label(text=f"{i}            {lv.n_surface:,}            {lv.n_inner:,}")
        box.label(text=f"Graph memory {baked.bake_memory:.1f} MiB, bake time {baked.bake_seconds:.1f} s")
    elif baked.bake_stats:
        box.label(text=baked.bake_stats)
    if baked.ss_samples_baked:
        _draw_multiline(box, "Single scattering: " + baked.ss_bake_stats, icon='LIGHT_SUN')
    if baked.bake_warnings:
        _draw_multiline(box, baked.bake_warnings, icon='ERROR')

    _draw_material(col, obj)
    _draw_inner_parts(col, obj)

    # -- solve ---------------------------------------------------------------------------
    box = col.box()
    box.label(text="Solve", icon='LIGHT')
    if obj.type == 'MESH':
        box.operator("translucency.solve", icon='PLAY')
    solved = status.solve_status(obj)  # runtime state: never saved, so a solve writes no property
    if solved.backend:
        box.label(text=f"Last solve: {solved.seconds * 1000:.1f} ms on the {solved.backend}, "
                       f"{solved.iterations} iterations, residual {solved.residual:.2e}")
    if solved.deformation:  # the current frame's pose (runtime state, like the rest of the solve status)
        sub = box.column()
        sub.alert = "refused" in solved.deformation
        _draw_multiline(sub, solved.deformation, icon='MOD_ARMATURE')
    if solved.message:
        _draw_multiline(box, solved.message, icon='INFO')
    if solved.ss_backend:
        box.label(text=f"Single scattering: {solved.ss_seconds * 1000:.1f} ms on the {solved.ss_backend}")
    if solved.vnm_backend:
        box.label(text=f"Voxel Number Map: {solved.vnm_seconds * 1000:.1f} ms on the {solved.vnm_backend}")
    if solved.vnm_message:
        _draw_multiline(box, solved.vnm_message, icon='INFO')
    _draw_world(box, obj)
    _draw_plan(box, obj)
    if solved.ss_message:
        stale = "re-bake" in solved.ss_message or "not baked" in solved.ss_message
        sub = box.column()
        sub.alert = stale
        _draw_multiline(sub, solved.ss_message, icon='ERROR' if stale else 'INFO')

    box = col.box()
    box.label(text="Cache", icon='FILE_CACHE')
    box.prop(settings, "cache_filepath")
    if settings.packed_cache:
        row = box.row()
        row.label(text="Packed into the .blend (render farms that take one file)", icon='PACKAGE')
        row.operator("translucency.pack_cache", text="", icon='X').unpack = True
    else:
        box.operator("translucency.pack_cache", icon='PACKAGE')


def _draw_scale(box, obj, context) -> None:
    """Scale override and the scale in use (mm per object unit)."""
    settings = obj.translucency
    row = box.row(heading="Scale")
    row.prop(settings, "use_mm_per_unit_override", text="Override")
    sub = box.row()
    sub.active = settings.use_mm_per_unit_override
    sub.prop(settings, "mm_per_unit")
    scene = getattr(context, "scene", None) if context is not None else None
    if scene is not None and not settings.use_mm_per_unit_override:
        try:
            from .scene_inputs import mm_per_unit

            mm, warning = mm_per_unit(obj, scene)
            box.label(text=f"1 object unit = {mm:.4g} mm (scene unit scale x object scale)")
            if warning:
                _draw_multiline(box, warning, icon='ERROR')
        except Exception:  # noqa: BLE001 - drawing must never fail
            pass


def _draw_material(col, obj) -> None:
    """The material and its heterogeneity field (meshes and fluids alike)."""
    settings = obj.translucency
    box = col.box()
    box.label(text="Material", icon='MATERIAL')
    box.prop(settings, "material_preset")
    if settings.material_preset == 'CUSTOM':
        box.prop(settings, "sigma_a")
        box.prop(settings, "sigma_s")
    box.prop(settings, "eta")

    box = col.box()
    box.prop(settings, "use_heterogeneity")
    sub = box.column()
    sub.active = settings.use_heterogeneity
    sub.prop(settings, "second_preset")
    sub.prop(settings, "field_source")
    if settings.field_source == 'TEXTURE':
        sub.prop(settings, "field_texture")
        sub.prop(settings, "field_scale")
    elif settings.field_source == 'ATTRIBUTE':
        if obj.type == 'MESH' and not state.is_fluid(obj):
            sub.prop_search(settings, "field_attribute", obj.data, "attributes")
        else:
            sub.prop(settings, "field_attribute")
    elif state.is_fluid(obj):
        sub.label(text="A fluid has no vertex groups: use a texture or a point attribute", icon='ERROR')
    else:
        sub.prop_search(settings, "field_vertex_group", obj, "vertex_groups")



def _draw_world(box, obj) -> None:
    """What the World became (SH order, an HDRI's sun as a light), or why it fell back."""
    try:
        text, warning = status.world_line(obj)
    except Exception:  # noqa: BLE001 - drawing must never fail
        text, warning = "", False
    if text:
        sub = box.column()
        sub.alert = warning
        _draw_multiline(sub, text, icon='ERROR' if warning else 'WORLD')


def _draw_plan(box, obj) -> None:
    try:
        plan_text = status.plan_summary(obj.name)
    except Exception:  # noqa: BLE001 - drawing must never fail
        plan_text = ""
    if plan_text:
        sub = box.box()
        sub.label(text="Passes this frame (planner)", icon='PRESET')
        _draw_multiline(sub, plan_text, width=90)  # the first line says whether it runs, or why not


def _draw_fluid(col, obj, context) -> None:
    """A Fluid source: where its particles come from, their radius, the material, and what a frame costs."""
    settings = obj.translucency
    box = col.box()
    box.label(text="Fluid: Voronoi-fluid cells every frame, no bake", icon='MOD_FLUIDSIM')
    box.prop(settings, "fluid_kind")
    box.prop(settings, "fluid_object")
    source = settings.fluid_object or obj
    if settings.fluid_kind == 'PARTICLES' and len(source.particle_systems):
        box.prop_search(settings, "fluid_particle_system", source, "particle_systems")
    box.prop(settings, "fluid_radius_auto")
    row = box.row()
    row.active = not settings.fluid_radius_auto
    row.prop(settings, "fluid_radius")
    _draw_scale(box, obj, context)

    _draw_material(col, obj)

    box = col.box()
    box.label(text="Solve (every frame)", icon='LIGHT')
    box.operator("translucency.solve", icon='PLAY')
    for line in status.fluid_lines(obj):  # runtime state: never saved
        _draw_multiline(box, line, icon='INFO')
    error = state.solve_error(obj.name)
    if error:
        sub = box.column()
        sub.alert = True
        _draw_multiline(sub, error, icon='ERROR')
    fluid = state.fluid_state_of(obj.name)
    for warning in (fluid.warnings if fluid is not None else ()):
        _draw_multiline(box, warning, icon='ERROR')
    _draw_plan(box, obj)


def _draw_inner_parts(layout, obj) -> None:
    """The inner-part list (object, role, a medium's material), the Voxel Number Map's settings and what
    the last bake made of the parts."""
    settings = obj.translucency
    box = layout.box()
    box.label(text="Inner Parts", icon='MOD_BOOLEAN')
    row = box.row()
    row.template_list("TRANSLUCENCY_UL_inner_parts", "", settings, "inner_parts", settings, "inner_parts_index",
                      rows=3)
    buttons = row.column(align=True)
    buttons.operator("translucency.inner_part_add", icon='ADD', text="")
    buttons.operator("translucency.inner_part_remove", icon='REMOVE', text="")
    box.operator("translucency.inner_parts_from_children", icon='OUTLINER_OB_MESH')
    parts = settings.inner_parts
    if not len(parts):
        box.label(text="None: the object is one medium (cavities, other media and opaque parts go here)")
        return
    item = parts[min(max(int(settings.inner_parts_index), 0), len(parts) - 1)]
    sub = box.column()
    sub.prop(item, "object")
    sub.prop(item, "role")
    if item.role == 'MEDIUM':
        sub.prop(item, "material_preset")
        if item.material_preset == 'CUSTOM':
            sub.prop(item, "sigma_a")
            sub.prop(item, "sigma_s")
    box.prop(settings, "use_voxel_number_map")
    sub = box.column()
    sub.active = settings.use_voxel_number_map
    sub.prop(settings, "vnm_quality")
    sub.prop(settings, "vnm_resolution")
    if settings.status.parts_bake_stats:
        _draw_multiline(box, settings.status.parts_bake_stats, icon='INFO')


def _draw_scene_settings(layout, scene, overlay_drawn: bool = False) -> None:
    settings = scene.translucency
    box = layout.box()
    box.label(text="Scene", icon='SCENE_DATA')
    box.prop(settings, "cache_directory")
    box.prop(settings, "missing_cache_in_render")
    box.prop(settings, "solver_backend")
    box.prop(settings, "tolerance")
    box.prop(settings, "live_update")
    row = box.row(align=True)
    row.active = settings.live_update
    row.prop(settings, "progressive")
    sub = row.row(align=True)
    sub.active = settings.progressive
    sub.prop(settings, "frame_budget_ms", text="Budget ms")
    if not overlay_drawn:
        box.prop(settings, "overlay_enabled")
        sub = box.row()
        sub.active = settings.overlay_enabled
        sub.prop(settings, "overlay_mode")
    last = status.last_solve()
    if last.get("seconds", 0.0) > 0.0 or last.get("backend"):
        backend = f" on the {last['backend']}" if last.get("backend") else ""
        box.label(text=f"Last solve{backend}: {last['seconds']:.3f} s, residual {last['residual']:.2e}")


# === Hooks for the viewport overlay and the render pass (ops/overlay.py, ops/render_pass.py) ===
# Each module may define ``draw_settings(layout, context)``; it is imported lazily and a
# missing module or function is ignored, so the panel never depends on them.
HOOK_MODULES = ("overlay", "render_pass")


def _draw_hooks(layout, context) -> set:
    """Call ``draw_settings`` of the optional modules; returns the names that drew."""
    import importlib

    drawn = set()
    for name in HOOK_MODULES:
        try:
            module = importlib.import_module(f"{__package__}.{name}")
            draw = module.draw_settings
        except (ImportError, AttributeError):
            continue
        try:
            draw(layout, context)
            drawn.add(name)
        except Exception as ex:  # noqa: BLE001 - another module's bug must not break the panel
            layout.label(text=f"{name}: {type(ex).__name__}: {ex}", icon='ERROR')
    return drawn


def draw_translucency(layout, context) -> None:
    """Shared draw function of both Translucency panels."""
    problems = dependencies.missing()
    if problems:
        _draw_missing_dependencies(layout, problems)
        return

    layout.use_property_split = True
    layout.use_property_decorate = False
    obj = context.object
    if obj is None:
        layout.label(text="No active object", icon='INFO')
    else:
        _draw_object_settings(layout, obj, context)
    drawn = _draw_hooks(layout, context)
    if context.scene is not None:
        _draw_scene_settings(layout, context.scene, overlay_drawn="overlay" in drawn)


class OBJECT_PT_translucency(bpy.types.Panel):
    bl_label = "Translucency"
    bl_idname = "OBJECT_PT_translucency"
    bl_space_type = 'PROPERTIES'
    bl_region_type = 'WINDOW'
    bl_context = "object"
    bl_options = {'DEFAULT_CLOSED'}

    @classmethod
    def poll(cls, context):
        return context.object is not None

    def draw(self, context):
        draw_translucency(self.layout, context)


class VIEW3D_PT_translucency(bpy.types.Panel):
    bl_label = "Translucency"
    bl_idname = "VIEW3D_PT_translucency"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Translucency"

    def draw(self, context):
        draw_translucency(self.layout, context)


PANELS = (OBJECT_PT_translucency, VIEW3D_PT_translucency)
CLASSES = PANELS
