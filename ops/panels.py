# SPDX-License-Identifier: GPL-3.0-or-later
"""The "Translucency" panel, in Properties > Object and in the 3D View sidebar.

Both panels share :func:`draw_translucency`.  If a bundled dependency does not
import, the panel lists what is missing (with the import error) and draws
nothing else, so a broken wheel never breaks the UI.
"""

from __future__ import annotations

import bpy

from . import dependencies


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


def _draw_object_settings(layout, obj) -> None:
    settings = obj.translucency
    layout.prop(settings, "enabled")

    col = layout.column()
    col.active = settings.enabled

    box = col.box()
    box.label(text="Bake", icon='MOD_REMESH')
    box.prop(settings, "quality")
    box.prop(settings, "levels")
    row = box.row(heading="Scale")
    row.prop(settings, "use_mm_per_unit_override", text="Override")
    sub = box.row()
    sub.active = settings.use_mm_per_unit_override
    sub.prop(settings, "mm_per_unit")

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
    elif settings.field_source == 'ATTRIBUTE':
        if obj.type == 'MESH':
            sub.prop_search(settings, "field_attribute", obj.data, "attributes")
        else:
            sub.prop(settings, "field_attribute")
    else:
        sub.prop_search(settings, "field_vertex_group", obj, "vertex_groups")

    box = col.box()
    box.label(text="Cache", icon='FILE_CACHE')
    box.prop(settings, "cache_filepath")
    box.label(text=f"Status: {settings.bake_status}")
    if settings.bake_stats:
        box.label(text=settings.bake_stats)


def _draw_scene_settings(layout, scene) -> None:
    settings = scene.translucency
    box = layout.box()
    box.label(text="Scene", icon='SCENE_DATA')
    box.prop(settings, "cache_directory")
    box.prop(settings, "solver_backend")
    box.prop(settings, "tolerance")
    box.prop(settings, "overlay_enabled")
    sub = box.row()
    sub.active = settings.overlay_enabled
    sub.prop(settings, "overlay_mode")
    if settings.last_solve_time > 0.0:
        box.label(text=f"Last solve: {settings.last_solve_time:.3f} s, residual {settings.last_residual:.2e}")


def _draw_actions(layout, context) -> None:
    """=== Operator buttons go here (bake, solve, clear cache; later issues). ===

    Add ``layout.operator("translucency.<name>")`` rows; this function is
    called from :func:`draw_translucency` after the object settings.
    """


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
        _draw_object_settings(layout, obj)
        _draw_actions(layout, context)
    if context.scene is not None:
        _draw_scene_settings(layout, context.scene)


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
