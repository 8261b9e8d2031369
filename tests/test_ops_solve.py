# SPDX-License-Identifier: GPL-3.0-or-later
"""``translucency.solve``, the runtime state and the scene inputs it reads."""

from __future__ import annotations

import math

import bpy
import numpy as np
import pytest
from mathutils import Vector

from test_ops_bake import activate, add_light, bake, cache_dir, memo_bakes, radiance, sphere  # noqa: F401


def _baked(subsurf=0, **kw):
    obj = sphere(subsurf=subsurf, **kw)
    assert bake(obj) == {'FINISHED'}
    return obj


def test_solve_writes_a_finite_point_color_attribute(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import state, status

    add_light()
    for subsurf in (0, 1):
        obj = _baked(subsurf=subsurf, name=f"S{subsurf}", location=(4.0 * subsurf, 0.0, 0.0))
        activate(obj)
        assert bpy.ops.translucency.solve() == {'FINISHED'}
        attr = obj.data.attributes["translucency_radiance"]
        assert (attr.domain, attr.data_type) == ('POINT', 'FLOAT_COLOR')
        rgb = radiance(obj)
        assert rgb.shape == (len(obj.data.vertices), 3)
        assert np.all(np.isfinite(rgb)) and rgb.min() >= 0.0 and rgb.max() > 0.0
        # Modifiers carry it to the evaluated mesh (the one renders and the overlay read).
        evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        assert len(evaluated.attributes["translucency_radiance"].data) == len(evaluated.vertices)
        solved = status.solve_status(obj)  # the runtime state's, never saved
        assert solved.backend in {"CPU", "GPU"} and solved.seconds > 0 and 0 < solved.residual < 1e-3
        # iterations may be 0: after the bake's own solve, the same frame warm-starts from its converged
        # pair (Self-Occlusion's one block solve) and is done at once
        st = state.get_state(obj)
        assert st.backend == solved.backend and solved.iterations == st.iterations
        assert obj.translucency.status.bake_status == "Baked"  # a solve leaves the saved status alone
    last = status.last_solve()
    assert last["name"] == "S1" and last["backend"] in {"CPU", "GPU"} and last["seconds"] > 0


def test_lit_side_is_brighter(blender, addon, cache_dir, memo_bakes):
    obj = _baked()
    add_light(location=(4.0, 0.0, 0.0))
    activate(obj)
    bpy.ops.translucency.solve()
    rgb = radiance(obj)
    x = np.array([v.co.x for v in obj.data.vertices])
    assert rgb[x > 0.5].mean() > 5 * rgb[x < -0.5].mean()


def test_material_change_resolves_without_rebake(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import state

    obj = _baked()
    add_light()
    activate(obj)
    bpy.ops.translucency.solve()
    st = state.get_state(obj)
    solver = st.solver
    marble = radiance(obj)
    calls = memo_bakes.calls
    obj.translucency.material_preset = 'KETCHUP'
    bpy.ops.translucency.solve()
    ketchup = radiance(obj)
    assert np.abs(ketchup - marble).max() > 0.1 * marble.max()
    assert ketchup[:, 1].mean() < 0.2 * marble[:, 1].mean()  # ketchup absorbs green
    obj.translucency.material_preset = 'CUSTOM'
    obj.translucency.sigma_a = (0.5, 0.5, 0.5)
    bpy.ops.translucency.solve()
    assert radiance(obj).mean() < 0.5 * marble.mean()  # strongly absorbing
    assert memo_bakes.calls == calls  # no bake at all
    assert state.get_state(obj).solver is solver  # set_material on the same solver


def test_bad_custom_material_is_reported(blender, addon, cache_dir, memo_bakes):
    obj = _baked()
    s = obj.translucency
    s.material_preset = 'CUSTOM'
    s.sigma_a = (0.0, 0.0, 0.0)
    s.sigma_s = (0.0, 1.0, 1.0)
    activate(obj)
    with pytest.raises(RuntimeError, match="sigma_a \\+ sigma_s is zero"):
        bpy.ops.translucency.solve()


def test_texture_field_is_sampled_at_the_nodes_and_resampled_on_edit(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import state

    obj = _baked()
    add_light()
    activate(obj)
    bpy.ops.translucency.solve()
    homogeneous = radiance(obj)
    tex = bpy.data.textures.new("veins", 'CLOUDS')
    tex.noise_scale = 0.4
    s = obj.translucency
    s.use_heterogeneity = True
    s.second_preset = 'KETCHUP'
    s.field_source = 'TEXTURE'
    s.field_texture = tex
    samples = state.counters()["field_samples"]
    calls = memo_bakes.calls
    bpy.ops.translucency.solve()
    mixed = radiance(obj)
    assert state.counters()["field_samples"] == samples + 1
    st = state.get_state(obj)
    assert [len(f) for f in st.field_values] == [lv.n_nodes for lv in st.bake.levels]
    f = st.field_values[-1]
    assert 0.0 <= f.min() and f.max() <= 1.0 and f.std() > 0.02  # a real pattern
    # The field is the texture's intensity at the node positions (object space x scale).
    p = st.bake.levels[-1].position[:5]
    np.testing.assert_allclose(f[:5], [tex.evaluate(tuple(x))[3] for x in p], atol=1e-6)
    assert np.abs(mixed - homogeneous).max() > 0.05 * homogeneous.max()

    bpy.ops.translucency.solve()  # nothing changed: not sampled again
    assert state.counters()["field_samples"] == samples + 1
    tex.noise_scale = 0.15  # editing the texture re-samples, still without a re-bake
    bpy.ops.translucency.solve()
    assert state.counters()["field_samples"] == samples + 2
    assert np.abs(radiance(obj) - mixed).max() > 0
    s.field_scale = 3.0
    bpy.ops.translucency.solve()
    assert state.counters()["field_samples"] == samples + 3
    assert memo_bakes.calls == calls


@pytest.mark.parametrize("source", ["VERTEX_GROUP", "ATTRIBUTE"])
def test_vertex_group_and_attribute_fields(blender, addon, cache_dir, memo_bakes, source):
    from translucency.ops import state

    obj = _baked(subsurf=1)
    add_light()
    upper = [v.index for v in obj.data.vertices if v.co.z > 0.3]
    if source == 'VERTEX_GROUP':
        group = obj.vertex_groups.new(name="mix")
        group.add(upper, 1.0, 'REPLACE')
    else:
        attr = obj.data.attributes.new("mix", 'FLOAT', 'POINT')
        values = np.zeros(len(obj.data.vertices))
        values[upper] = 1.0
        attr.data.foreach_set("value", values)
    s = obj.translucency
    s.use_heterogeneity = True
    s.field_source = source
    s.field_vertex_group = s.field_attribute = "mix"
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    level = state.get_state(obj).bake.levels[-1]
    f = state.get_state(obj).field_values[-1]
    z = level.position[:, 2]
    assert f[z > 0.7].mean() > 0.9 and f[z < -0.2].mean() < 0.1

    s.field_vertex_group = s.field_attribute = "nope"
    with pytest.raises(RuntimeError, match="nope"):
        bpy.ops.translucency.solve()


def test_heterogeneous_without_a_texture_is_reported(blender, addon, cache_dir, memo_bakes):
    obj = _baked()
    obj.translucency.use_heterogeneity = True
    activate(obj)
    with pytest.raises(RuntimeError, match="no texture is chosen"):
        bpy.ops.translucency.solve()


def test_lights_are_converted_into_object_space(blender, addon):
    from translucency.ops import scene_inputs

    obj = sphere()
    obj.location = (1.0, 2.0, 3.0)
    obj.rotation_euler = (0.3, -0.2, 1.1)
    obj.scale = (2.0, 2.0, 2.0)
    spot = add_light('SPOT', location=(4.0, -1.0, 5.0), rotation=(0.4, 0.1, 0.0), energy=200.0)
    spot.data.spot_size = 0.8
    spot.data.spot_blend = 0.3
    spot.data.color = (1.0, 0.5, 0.25)
    sun = add_light('SUN', rotation=(0.5, 0.0, 0.7), energy=3.0)
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    lights = {light.kind: light for light in scene_inputs.collect_lights(depsgraph, obj.matrix_world, 1.0)}
    to_obj = obj.matrix_world.inverted()
    np.testing.assert_allclose(lights["spot"].position, to_obj @ spot.matrix_world.translation, atol=1e-6)
    d = (to_obj.to_3x3() @ (spot.matrix_world.to_3x3() @ Vector((0, 0, -1)))).normalized()
    np.testing.assert_allclose(lights["spot"].unit_direction, d, atol=1e-6)
    assert lights["spot"].intensity == pytest.approx(200.0 / (4 * math.pi))
    assert lights["spot"].color == pytest.approx((1.0, 0.5, 0.25))
    assert lights["spot"].spot_size == pytest.approx(0.8) and lights["spot"].spot_blend == pytest.approx(0.3)
    assert lights["sun"].irradiance == pytest.approx(3.0)
    sun_dir = (to_obj.to_3x3() @ (sun.matrix_world.to_3x3() @ Vector((0, 0, -1)))).normalized()
    np.testing.assert_allclose(lights["sun"].unit_direction, sun_dir, atol=1e-6)
    # Hidden lights do not count.
    sun.hide_set(True)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    assert [lt.kind for lt in scene_inputs.collect_lights(depsgraph, obj.matrix_world, 1.0)] == ["spot"]


def test_occluders_cast_shadows(blender, addon, cache_dir, memo_bakes):
    obj = _baked()
    add_light(location=(0.0, 0.0, 4.0))
    activate(obj)
    bpy.ops.translucency.solve()
    lit = radiance(obj)
    bpy.ops.mesh.primitive_plane_add(size=4.0, location=(0.0, 0.0, 2.0))  # between light and object
    activate(obj)
    bpy.ops.translucency.solve()
    shadowed = radiance(obj)
    assert shadowed.mean() < 0.2 * lit.mean()


def test_world_lights_the_object(blender, addon, cache_dir, memo_bakes):
    obj = _baked()
    world = bpy.data.worlds.new("sky")
    from translucency.ops.compat import ensure_node_tree

    ensure_node_tree(world)
    background = next(n for n in world.node_tree.nodes if n.type == 'BACKGROUND')
    background.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    background.inputs["Strength"].default_value = 1.0
    bpy.context.scene.world = world
    activate(obj)
    bpy.ops.translucency.solve()
    rgb = radiance(obj)
    # A marble ball under a white uniform sky: nearly uniform, below the incident radiance 1.
    assert 0.5 < rgb.mean() < 1.0 and rgb.std() / rgb.mean() < 0.1


def test_view_towards_the_camera(blender, addon, cache_dir, memo_bakes):
    from translucency.ops import runtime, state

    obj = _baked()
    add_light(location=(0.0, -4.0, 0.0))
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    bpy.context.scene.collection.objects.link(cam)
    cam.location = (0.0, -6.0, 0.0)
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)
    bpy.context.scene.camera = cam
    activate(obj)
    bpy.ops.translucency.solve()
    normal = radiance(obj)
    solves = state.counters()["solves"]
    assert bpy.ops.translucency.solve(use_camera=True) == {'FINISHED'}
    towards = radiance(obj)
    y = np.array([v.co.y for v in obj.data.vertices])
    front = y < -0.9  # facing the camera: the same; grazing or back-facing: darker
    np.testing.assert_allclose(towards[front], normal[front], rtol=0.05)
    assert towards[y > 0.3].sum() == 0.0
    assert state.counters()["solves"] == solves + 1  # forced; a view change alone needs no solve
    report = runtime.solve_object(obj, use_camera=False)
    assert report is not None and not report.solved  # only the radiance was re-evaluated


def test_state_follows_the_bake_key_as_after_undo(blender, addon, cache_dir, memo_bakes):
    """Undo restores properties, not Python state: a state is used only while its key matches."""
    from translucency.ops import state

    obj = _baked()
    add_light()
    activate(obj)
    bpy.ops.translucency.solve()
    key = obj.translucency.bake_key
    loads = state.counters()["loads"]
    obj.translucency.bake_key = "0" * 64  # as if undo went back to another bake
    assert state.get_state(obj) is None
    with pytest.raises(RuntimeError, match="stale"):
        bpy.ops.translucency.solve()
    obj.translucency.bake_key = key  # redo
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert state.counters()["loads"] == loads + 1  # re-loaded from the cache file
    assert state.get_state(obj).key == key


def test_unbaked_object_cannot_be_solved(blender, addon):
    obj = sphere()
    activate(obj)
    with pytest.raises(RuntimeError, match="not baked yet"):
        bpy.ops.translucency.solve()


def test_backend_falls_back_to_cpu(blender, addon, monkeypatch):
    import sys
    import types

    from translucency.ops import backend
    from translucency.translucency_addon.quadgraph.bake import bake_mesh, BakeSettings
    from translucency.translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
    from translucency.translucency_addon.scene.materials import material_from_preset
    from translucency.translucency_addon.geometry.primitives import icosphere

    V, F = icosphere(1.0, 2)
    bake_obj = bake_mesh(V, F, BakeSettings(quality="draft", levels=1, base_triangles=200, mm_per_unit=10))
    material = material_from_preset("marble")

    solver, name, message = backend.make_solver(bake_obj, material, None, SolveOptions(), prefer="CPU")
    assert isinstance(solver, DiffusionSolver) and name == "CPU" and message == ""

    broken = types.ModuleType("translucency.gpu_shaders")

    def fail(*_a, **_k):
        raise RuntimeError("shader compile error")

    broken.make_solver = fail
    broken.available = lambda: (True, "simulated GPU")  # the policy asks for a GPU context first
    monkeypatch.setitem(sys.modules, "translucency.gpu_shaders", broken)
    monkeypatch.setattr(sys.modules["translucency"], "gpu_shaders", broken, raising=False)
    solver, name, message = backend.make_solver(bake_obj, material, None, SolveOptions(), prefer="AUTO")
    assert name == "CPU" and "shader compile error" in message and isinstance(solver, DiffusionSolver)

    empty = types.ModuleType("translucency.gpu_shaders")
    monkeypatch.setitem(sys.modules, "translucency.gpu_shaders", empty)
    monkeypatch.setattr(sys.modules["translucency"], "gpu_shaders", empty, raising=False)
    solver, name, message = backend.make_solver(bake_obj, material, None, SolveOptions(), prefer="GPU")
    assert name == "CPU" and "not available" in message
    backend.free_solver(solver)  # no .free(): a no-op


def test_one_policy_places_every_pass_and_says_why(blender, addon, monkeypatch):
    """``ops.backend.placement`` is where GPU or CPU is decided, each refusal with its reason."""
    import threading

    from translucency import gpu_shaders
    from translucency.ops import backend

    monkeypatch.setattr(gpu_shaders, "available", lambda: (True, "llvmpipe (LLVM 15.0.6, 256 bits)"))
    assert backend.placement("CPU") == backend.Placement("CPU", "")
    assert backend.placement("AUTO", off_main=False).gpu
    off = backend.placement("AUTO", off_main=True)
    assert not off.gpu and f"thread '{threading.current_thread().name}'" in off.reason
    assert "no GPU version" in backend.placement("GPU", solver="direct", off_main=False).reason
    ss = backend.placement("AUTO", kind="single scattering", off_main=False)
    assert not ss.gpu and "llvmpipe" in ss.reason and "software rasteriser" in ss.reason
    assert backend.placement("GPU", kind="single scattering", off_main=False).gpu  # asked for: no preference
    failed = backend.after_gpu_failure(SystemError("no GPU context"), rendering=True)
    assert not failed.gpu and "SystemError: no GPU context" in failed.reason and "for renders" in failed.reason
    assert backend.after_gpu_failure(ValueError("a bug"), rendering=False, on_gpu=False) is None  # not a fallback
    again = backend.placement("AUTO", off_main=False, failed_in_render=failed.reason, built=True)
    assert not again.gpu and "renders of this object stay on the CPU" in again.reason
    assert backend.placement("AUTO", off_main=False, built=True).gpu
    monkeypatch.setattr(gpu_shaders, "available", lambda: (False, "simulated: no compute shaders"))
    assert "simulated: no compute shaders" in backend.placement("AUTO", off_main=False).reason
    assert backend.placement("AUTO", off_main=False, built=True).gpu  # a built solver is not re-checked per frame


@pytest.mark.gpu
def test_a_gpu_solve_that_raises_is_redone_on_the_cpu_and_says_why(gpu_context, blender, addon, cache_dir,
                                                                   memo_bakes, monkeypatch):
    """The retry rule (``backend.after_gpu_failure``): outside a render the object moves to the CPU
    solver for good, the same frame is solved there, and the panel and the log say why."""
    from translucency.gpu_shaders.solver import GPUDiffusionSolver
    from translucency.ops import state, status

    obj = _baked()
    add_light()
    activate(obj)
    scene = bpy.context.scene.translucency
    scene.solver_backend = 'CPU'
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    cpu = radiance(obj)
    scene.solver_backend = 'GPU'

    def fail(self, *_args, **_kw):
        raise SystemError("simulated: the GPU context went away")

    monkeypatch.setattr(GPUDiffusionSolver, "solve", fail)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    st = state.get_state(obj)
    assert st.backend == "CPU" and type(st.solver).__name__ == "DiffusionSolver"
    assert "the GPU solve failed (SystemError: simulated: the GPU context went away)" in st.backend_message
    assert "GPU solve failed" in status.solve_status(obj).message
    np.testing.assert_allclose(radiance(obj), cpu, rtol=1e-6)  # the same frame, solved on the CPU


def test_panel_shows_stats_actions_and_hooks(blender, addon, ui, cache_dir, memo_bakes, monkeypatch):
    import importlib

    obj = _baked()
    add_light()
    activate(obj)
    bpy.ops.translucency.solve()
    calls = []
    for name in ("overlay", "render_pass"):
        try:
            module = importlib.import_module(f"translucency.ops.{name}")
        except ImportError:
            continue
        monkeypatch.setattr(module, "draw_settings", lambda layout, context, n=name: calls.append(n), raising=False)
    layout = ui.FakeLayout()
    addon.ops.panels.draw_translucency(layout, ui.draw_context(obj))
    text = "\n".join(layout.labels())
    ops = layout.operators()
    assert {"translucency.bake", "translucency.free_bake", "translucency.solve"} <= set(ops)
    s = obj.translucency
    for lv in s.status.bake_levels:
        assert f"{lv.n_surface:,}" in text and f"{lv.n_inner:,}" in text
    assert "MiB" in text and "bake time" in text
    solved = addon.ops.status.solve_status(obj)
    assert "Last solve" in text and f"on the {solved.backend}" in text and "residual" in text
    assert {"live_update", "field_source", "solver_backend", "tolerance"} <= set(layout.props())
    for name in ("overlay", "render_pass"):
        if importlib.util.find_spec(f"translucency.ops.{name}") is not None:
            assert name in calls


def test_solve_all_objects(blender, addon, cache_dir, memo_bakes):
    a = _baked(name="A")
    b = _baked(name="B", location=(3.0, 0.0, 0.0))
    add_light()
    b.translucency.enabled = False
    activate(a)
    assert bpy.ops.translucency.solve(all_objects=True) == {'FINISHED'}
    assert radiance(a) is not None
    b.data.attributes.remove(b.data.attributes["translucency_radiance"])
    bpy.ops.translucency.solve(all_objects=True)
    assert radiance(b) is None  # disabled objects are skipped
