# SPDX-License-Identifier: GPL-3.0-or-later
"""``translucency.solve``: solve the diffusion for the active (or every) baked object or fluid now.

A Fluid source (no bake) is solved for the current frame's particles
(``runtime.solve_object`` hands it to ``fluid_runtime``); its errors and warnings
are reported here like a baked object's.  ``translucency.report`` is internal:
the live updates (handlers and timers, which are not operators) hand their
messages to it so that they reach the Info log.

The result goes into the ``translucency_radiance`` attribute of the object's
mesh (see :mod:`.runtime`): the diffusion term (when "Multiple Scattering" is
on) plus the single-scattering term (when "Single Scattering" is on and
baked; also alone in ``translucency_radiance_ss`` with "Split Pass").  A
single-scattering bake that no longer matches the material, field, scale or
its settings is reported as a warning that asks for a re-bake.  Loading a cache that is missing, truncated or
stale is retried here (the live handlers do not retry a failed load until the
file changes) and reported as an error.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from . import runtime, state


class TRANSLUCENCY_OT_solve(bpy.types.Operator):
    """Solve subsurface scattering for the active baked object and write its radiance attribute"""

    bl_idname = "translucency.solve"
    bl_label = "Solve"
    bl_options = {'REGISTER', 'UNDO'}

    all_objects: BoolProperty(
        name="All Objects",
        description="Solve every enabled, baked object of the scene instead of only the active one",
        default=False,
    )
    use_camera: BoolProperty(
        name="Towards Camera",
        description="Evaluate the radiance towards the scene camera instead of along the surface normal",
        default=False,
    )

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and (obj.type == 'MESH' or state.is_fluid(obj))

    def execute(self, context):
        from ..translucency_addon.errors import TranslucencyError

        scene = context.scene
        if self.all_objects:
            objects = state.baked_objects(scene) + state.fluid_objects(scene)
        else:
            objects = [context.active_object]
        if not objects:
            self.report({'WARNING'}, _nothing_to_solve(scene))
            return {'CANCELLED'}
        depsgraph = context.evaluated_depsgraph_get()
        failed = 0
        for obj in objects:
            try:
                report = runtime.solve_object(obj, scene, depsgraph, use_camera=self.use_camera, force=True,
                                              retry_load=True)
            except TranslucencyError as ex:
                failed += 1
                self.report({'ERROR'}, f"Cannot solve '{obj.name}': {ex}")
                continue
            if report is None:  # object in Edit Mode
                self.report({'WARNING'}, f"'{obj.name}' is in Edit Mode: switch to Object Mode to solve it")
                continue
            self.report({'WARNING'} if report.skipped or getattr(report, "empty", "") else {'INFO'}, report.describe())
            if state.is_fluid(obj):
                fluid = state.fluid_state_of(obj.name)
                for warning in (fluid.warnings if fluid is not None else ()):
                    self.report({'WARNING'}, f"'{obj.name}': {warning}")
                continue
            st = state.get_state(obj)
            if st is not None and st.frame_backend_message and not getattr(st, "_message_reported", False):
                self.report({'INFO'}, f"'{obj.name}': {st.frame_backend_message}")
                st._message_reported = True
            for warning in (st.warnings if st is not None else ()):
                self.report({'WARNING'}, f"'{obj.name}': {warning}")
        return {'CANCELLED'} if failed == len(objects) else {'FINISHED'}


def _nothing_to_solve(scene) -> str:
    """Why Solve All found nothing, in counts, and what to change."""
    meshes = [ob for ob in scene.objects if ob.type == 'MESH' and hasattr(ob, "translucency")]
    enabled = [ob for ob in meshes if ob.translucency.enabled]
    unbaked = [ob.name for ob in enabled if not state.is_baked(ob) and not state.is_fluid(ob)]
    disabled = [ob.name for ob in meshes if not ob.translucency.enabled and state.is_baked(ob)]
    parts = [f"{len(meshes)} mesh objects in the scene, {len(enabled)} with Translucency enabled"]
    if unbaked:
        more = " ..." if len(unbaked) > 5 else ""
        parts.append(f"not baked: {', '.join(unbaked[:5])}{more} (select one, press Bake)")
    if disabled:
        parts.append(f"baked but disabled: {', '.join(disabled[:5])} (turn on Enabled)")
    if not enabled and not disabled:
        parts.append("turn on Enabled in a mesh's Translucency panel and press Bake, or set its Source to Fluid")
    return "No enabled, baked object or fluid to solve: " + "; ".join(parts)


class TRANSLUCENCY_OT_report(bpy.types.Operator):
    """Show a message of the live updates in the Info log (handlers and timers are not operators)"""

    bl_idname = "translucency.report"
    bl_label = "Translucency Message"
    bl_options = {'INTERNAL'}

    level: EnumProperty(items=(("ERROR", "Error", ""), ("WARNING", "Warning", ""), ("INFO", "Info", "")),
                        default="INFO")
    message: StringProperty(default="")

    def execute(self, _context):
        self.report({self.level}, f"Translucency: {self.message}")
        return {'FINISHED'}


CLASSES = (TRANSLUCENCY_OT_solve, TRANSLUCENCY_OT_report)
