# SPDX-License-Identifier: GPL-3.0-or-later
"""Never a black object (issue 21): a thin part does not turn off the only pass that can render.

A marble sphere 15 mm across with a 0.3 mm fin (under one transport mean free
path of marble, 0.33-0.46 mm), in a plain white world, with the add-on's
default settings.  The planner used to mark diffusion invalid for the whole
object because of the fin, and with single scattering not baked the object
rendered black.  Validity is now decided per region: diffusion runs, says
where it is doubtful, and single scattering, once baked, replaces it only
in the fin.
"""

from __future__ import annotations

import bpy
import numpy as np
import pytest

from test_ops_bake import activate, cache_dir, radiance  # noqa: F401

SS_ATTR = "translucency_radiance_ss"


def finned_sphere_object(name="Finned"):
    """The engine's finned sphere as a Blender mesh object, 15 mm across through the scene's unit scale."""
    from translucency.translucency_addon.geometry import primitives

    V, F = primitives.finned_sphere()  # radius 1, fin 0.04 units thick
    me = bpy.data.meshes.new(name)
    me.from_pydata(V.tolist(), [], F.tolist())
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.scene.unit_settings.scale_length = 0.0075  # 1 unit = 7.5 mm: 15 mm across, a 0.3 mm fin
    from translucency.ops.compat import ensure_node_tree

    world = bpy.data.worlds.new("White")
    ensure_node_tree(world).nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bpy.context.scene.world = world
    return obj


def _vertices(obj) -> np.ndarray:
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _solve(obj, planning: str) -> np.ndarray:
    obj.translucency.pass_planning = planning
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    return radiance(obj)


@pytest.mark.slow
def test_thin_fin_is_never_black_and_single_scattering_serves_only_the_fin(blender, addon, cache_dir):
    from translucency.ops import attributes, frame, state, status

    obj = finned_sphere_object()
    activate(obj)
    assert obj.translucency.pass_planning == 'AUTO' and not obj.translucency.use_single_scattering  # defaults
    assert bpy.ops.translucency.bake() == {'FINISHED'}
    x = _vertices(obj)[:, 0]
    body, fin = x < 0.5, x > 1.05  # the fin sticks out along +x beyond the sphere (radius 1)
    assert fin.sum() > 20

    automatic = _solve(obj, 'AUTO')
    plan = state.last_plan(obj.name)
    text = status.plan_summary(obj.name)
    assert plan.run and plan.multiple.channels == (True, True, True), text
    assert "diffusion doubtful where thinner than 0.33 mm" in text and "of the surface" in text, text
    assert "single scattering would be more accurate on" in text and "bake it to use it" in text, text
    everything = _solve(obj, 'ALL')
    assert automatic[body].mean() > 0.1 * everything[body].mean() > 0  # not black
    np.testing.assert_allclose(automatic[body].mean(axis=0), everything[body].mean(axis=0), rtol=0.03)
    np.testing.assert_allclose(automatic[fin].mean(axis=0), everything[fin].mean(axis=0), rtol=0.03)

    # With single scattering baked, Automatic uses it only in the fin, where it replaces diffusion.
    s = obj.translucency
    s.use_single_scattering, s.ss_split_pass = True, True
    s.ss_quality, s.ss_directions, s.ss_samples = 'DRAFT', '32', 500
    s.pass_planning = 'AUTO'
    assert bpy.ops.translucency.bake_single_scattering() == {'FINISHED'}
    combined = _solve(obj, 'AUTO')
    plan = state.last_plan(obj.name)
    assert plan.single.channels == (True, True, True), status.plan_summary(obj.name)
    ss = attributes.read_radiance(obj, SS_ATTR)
    assert np.all(ss[body] == 0.0)  # the body is thick: diffusion alone
    assert ss[fin].mean() > 0.0
    np.testing.assert_allclose(combined[body], automatic[body], rtol=1e-6, atol=1e-9)
    # in the fin the single-scattering weight and the diffusion weight add to one
    mapping = frame.mesh_mapping(obj, state.get_state(obj))
    diffusion_weight = plan.vertex_weights("multiple", mapping.idx, mapping.w)
    ss_weight = plan.vertex_weights("single", mapping.idx, mapping.w)
    np.testing.assert_allclose(diffusion_weight + ss_weight, 1.0, atol=1e-9)
    assert ss_weight[fin].mean() > 0.5 and np.all(ss_weight[body] == 0.0)


def test_a_skipped_object_is_reported_as_skipped_never_as_solved(blender, addon, cache_dir):
    """Both passes turned off: the report says why and never 'solved on the  in 0.000 s'."""
    from translucency.ops import runtime

    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2)
    obj = bpy.context.object
    s = obj.translucency
    s.quality, s.levels, s.use_mm_per_unit_override, s.mm_per_unit = 'DRAFT', 2, True, 10.0
    lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", 'POINT'))
    lamp.data.energy, lamp.location = 1000.0, (3.0, 0.0, 2.0)
    bpy.context.scene.collection.objects.link(lamp)
    assert bpy.ops.translucency.bake() == {'FINISHED'}
    s.use_multiple_scattering = False
    report = runtime.solve_object(obj, bpy.context.scene, bpy.context.evaluated_depsgraph_get(), force=True)
    text = report.describe()
    assert report.skipped and "skipped" in text and "turned off" in text, text
    assert "solved on the" not in text and "on the  " not in text
