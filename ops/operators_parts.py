# SPDX-License-Identifier: GPL-3.0-or-later
"""The inner-part list of the Translucency panel: its UI list and the operators that edit it.

* ``TRANSLUCENCY_UL_inner_parts``: one row per part (object, role; a medium's material).
* ``translucency.inner_part_add``: a new entry, for the first mesh child not listed yet
  (else empty, to be picked).
* ``translucency.inner_part_remove``: removes the active entry.
* ``translucency.inner_parts_from_children``: lists every mesh child not listed yet.

All are undoable; the list lives in the .blend (``object.translucency.inner_parts``,
pointers to the part objects).  A change of the list, a role or a part makes the bake stale
(``ops.inner_parts.staleness``); a medium's material re-solves without a re-bake.
"""

from __future__ import annotations

import bpy

from . import inner_parts


def _unlisted_children(obj) -> list:
    taken = inner_parts.part_objects(obj)
    return [c for c in obj.children if c.type == 'MESH' and c.name not in taken]


def _append(settings, objects) -> None:
    """One entry per object (None: an empty entry, to be picked), the last one active."""
    for part in objects:
        item = settings.inner_parts.add()
        if part is not None:
            item.object = part
    settings.inner_parts_index = len(settings.inner_parts) - 1


class TRANSLUCENCY_UL_inner_parts(bpy.types.UIList):
    """The inner parts of an object: object and role (and a medium's material)."""

    bl_idname = "TRANSLUCENCY_UL_inner_parts"

    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index=0, flt_flag=0):
        row = layout.row(align=True)
        row.prop(item, "object", text="", emboss=False, icon='MESH_DATA')
        row.prop(item, "role", text="", emboss=False)
        if item.role == 'MEDIUM':
            row.prop(item, "material_preset", text="", emboss=False)


class _ListOperator:
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH'


class TRANSLUCENCY_OT_inner_part_add(_ListOperator, bpy.types.Operator):
    """Add an inner part to the active object: its first mesh child not listed yet, or an empty entry to fill in"""

    bl_idname = "translucency.inner_part_add"
    bl_label = "Add Inner Part"

    def execute(self, context):
        obj = context.active_object
        part = (_unlisted_children(obj) or [None])[0]
        _append(obj.translucency, [part])
        self.report({'INFO'}, f"'{obj.name}': inner part " + (f"'{part.name}' added" if part else
                                                               "added; pick its object"))
        return {'FINISHED'}


class TRANSLUCENCY_OT_inner_part_remove(_ListOperator, bpy.types.Operator):
    """Remove the active inner part from the list (the object itself stays in the scene)"""

    bl_idname = "translucency.inner_part_remove"
    bl_label = "Remove Inner Part"

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return super().poll(context) and len(obj.translucency.inner_parts) > 0

    def execute(self, context):
        s = context.active_object.translucency
        i = min(max(int(s.inner_parts_index), 0), len(s.inner_parts) - 1)
        s.inner_parts.remove(i)
        s.inner_parts_index = max(0, min(i, len(s.inner_parts) - 1))
        return {'FINISHED'}


class TRANSLUCENCY_OT_inner_parts_from_children(_ListOperator, bpy.types.Operator):
    """List every mesh child of the active object that is not listed yet as an inner part (role Medium; change it in the list)"""

    bl_idname = "translucency.inner_parts_from_children"
    bl_label = "Add Children"

    def execute(self, context):
        obj = context.active_object
        children = _unlisted_children(obj)
        if not children:
            self.report({'INFO'}, f"'{obj.name}' has no mesh child that is not listed already")
            return {'CANCELLED'}
        _append(obj.translucency, children)
        self.report({'INFO'}, f"'{obj.name}': listed {', '.join(c.name for c in children)} as inner parts")
        return {'FINISHED'}


CLASSES = (TRANSLUCENCY_UL_inner_parts, TRANSLUCENCY_OT_inner_part_add, TRANSLUCENCY_OT_inner_part_remove,
           TRANSLUCENCY_OT_inner_parts_from_children)
