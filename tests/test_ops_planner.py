# SPDX-License-Identifier: GPL-3.0-or-later
"""The planner in Blender (issue 10): visible reasons, change tracking that counts solves,
objects outside the camera and unlit objects doing no work."""

from __future__ import annotations

import math

import bpy
import numpy as np

from test_ops_bake import activate, add_light, bake, cache_dir, memo_bakes, radiance, sphere  # noqa: F401


def _solve_scene(use_camera=False):
    from translucency.ops import runtime

    dg = bpy.context.evaluated_depsgraph_get()
    return runtime.solve_scene(bpy.context.scene, dg, use_camera=use_camera)


def test_marble_plan_is_shown_and_single_scattering_is_contained(blender, cache_dir, memo_bakes):
    from translucency.ops import status

    add_light()
    obj = sphere()
    obj.translucency.use_single_scattering = True
    obj.translucency.ss_quality = 'DRAFT'
    obj.translucency.ss_directions = '32'
    obj.translucency.ss_samples = 500
    assert bake(obj) == {'FINISHED'}
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    text = status.plan_summary(obj.name)
    assert "multiple scattering [RGB]" in text
    assert "contained in the diffusion term" in text
    assert status.solve_status(obj).ss_backend == ""  # the single-scattering pass did not run
    assert "not baked" not in status.solve_status(obj).ss_message  # it is baked: the planner chose
    # forcing every pass runs it
    obj.translucency.pass_planning = 'ALL'
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert status.solve_status(obj).ss_backend in {"CPU", "GPU"}


def test_unchanged_frame_does_no_solve_and_a_moved_light_resolves_only_what_it_lights(blender, cache_dir,
                                                                                      memo_bakes):
    from translucency.ops import state

    left = sphere(name="Left", location=(-6.0, 0.0, 0.0))
    right = sphere(name="Right", location=(6.0, 0.0, 0.0))
    # two narrow spots, each aimed straight down at one object
    spot_l = add_light('SPOT', location=(-6.0, 0.0, 4.0), energy=2000.0, name="SpotL")
    spot_r = add_light('SPOT', location=(6.0, 0.0, 4.0), energy=2000.0, name="SpotR")
    for s in (spot_l, spot_r):
        s.data.spot_size = math.radians(30.0)
    for o in (left, right):
        assert bake(o) == {'FINISHED'}
    bpy.context.scene.world = None  # no world light: only the spots
    _solve_scene()
    start = state.counters()["solves"]
    assert _solve_scene() == []  # nothing changed: no work
    assert state.counters()["solves"] == start
    before_r = radiance(right).copy()
    spot_l.location.z = 3.0
    bpy.context.view_layer.update()
    reports = _solve_scene()
    assert [r.name for r in reports if r.solved] == ["Left"]
    assert state.counters()["solves"] == start + 1
    np.testing.assert_array_equal(radiance(right), before_r)
    assert "SpotL" in state.last_plan("Left").facts["lights_reaching"]
    assert "SpotL" not in state.last_plan("Right").facts["lights_reaching"]


def test_objects_outside_the_camera_do_no_work_in_renders(blender, cache_dir, memo_bakes):
    from translucency.ops import state

    add_light()
    seen = sphere(name="Seen")
    hidden = sphere(name="Hidden", location=(0.0, 0.0, 40.0))
    for o in (seen, hidden):
        assert bake(o) == {'FINISHED'}
    cam_data = bpy.data.cameras.new("Cam")
    cam = bpy.data.objects.new("Cam", cam_data)
    bpy.context.scene.collection.objects.link(cam)
    cam.location = (0.0, -10.0, 0.0)
    cam.rotation_euler = (math.radians(90.0), 0.0, 0.0)  # looking along +y at the origin
    bpy.context.scene.camera = cam
    bpy.context.view_layer.update()
    skips = state.counters()["planner_skips"]
    reports = _solve_scene(use_camera=True)
    assert [r.name for r in reports] == ["Seen"]
    assert state.counters()["planner_skips"] == skips + 1
    assert "camera" in state.last_plan("Hidden").reason


def test_an_unlit_object_gets_exactly_zero_without_a_solve(blender, cache_dir, memo_bakes):
    from translucency.ops import state

    obj = sphere()
    spot = add_light('SPOT', location=(0.0, 0.0, 5.0), energy=1000.0, name="Away")
    spot.rotation_euler = (math.pi, 0.0, 0.0)  # pointing up, away from the object
    bpy.context.scene.world = None
    assert bake(obj) == {'FINISHED'}
    start = state.counters()["solves"]
    _solve_scene()
    assert state.counters()["solves"] == start
    assert "unlit" in state.last_plan(obj.name).reason
    L = radiance(obj)
    assert L is not None and np.all(L == 0.0)
    # The panel's plan says which light misses, by how much, and what to change (issue 19).
    from translucency.ops import status

    text = status.plan_summary(obj.name)
    assert "'Away' (spot) is aimed 180 deg away from the object's centre" in text, text
    assert "Give a light power, aim a spot or area light at the object" in text, text


def test_solve_all_with_nothing_baked_says_what_to_do(blender, cache_dir, capfd):
    obj = sphere()
    obj.translucency.enabled = True
    assert bpy.ops.translucency.solve(all_objects=True) == {'CANCELLED'}
    out = capfd.readouterr()
    text = out.out + out.err
    assert ("No enabled, baked object or fluid to solve: 1 mesh objects in the scene, 1 with Translucency enabled; "
            "not baked: Blob (select one, press Bake)") in text, text


def test_a_pass_off_by_default_is_not_called_the_users_choice(blender, addon, cache_dir, memo_bakes):
    """Issue 32: a user who never touched Single Scattering (off by default) is not told it was "forced off by
    the user"; the plan names what turned it off -- the default, or the user's setting -- by the panel's name."""
    from translucency.ops import runtime, state

    obj = sphere()
    add_light()
    assert bake(obj) == {'FINISHED'}
    runtime.solve_object(obj, force=True)
    reasons = state.last_plan("Blob").single.reasons if state.last_plan("Blob").single is not None else []
    assert reasons and all("forced off by default: 'Single Scattering' is off unless turned on" in r
                           for r in reasons), reasons
    assert not any("by the user" in r for r in reasons)
    obj.translucency.use_multiple_scattering = False  # the user's own choice
    try:
        runtime.solve_object(obj, force=True)
    except Exception:  # noqa: BLE001 - nothing may run; the plan is what is checked
        pass
    reasons = state.last_plan("Blob").multiple.reasons
    assert all("forced off by the user's setting: 'Multiple Scattering' is off" in r for r in reasons), reasons
