# SPDX-License-Identifier: GPL-3.0-or-later
"""Live updates, frame changes, renders, file loads and (un)registration of the handlers.

Background Blender has no event loop, so ``bpy.app.timers`` never fire: the
tests trigger ``depsgraph_update_post`` with ``view_layer.update()`` and then
run the pending live check with ``live.flush()``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import bpy
import numpy as np
import pytest

from conftest import ROOT
from test_ops_bake import activate, add_light, bake, cache_dir, memo_bakes, radiance, sphere  # noqa: F401


@pytest.fixture
def solved_ball(blender, addon, cache_dir, memo_bakes):
    """A baked, solved ball and a point light; returns (obj, light, ops.live, ops.state)."""
    from translucency.ops import live, state

    obj = sphere()
    light = add_light(location=(3.0, 0.0, 1.0))
    assert bake(obj) == {'FINISHED'}
    bpy.context.view_layer.update()
    live.flush()
    return obj, light, live, state


def _update_and_flush(live):
    bpy.context.view_layer.update()
    return live.flush()


def test_moving_a_light_changes_the_attribute(solved_ball):
    from translucency.ops import status

    obj, light, live, state = solved_ball
    before = radiance(obj)
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    assert live.pending()  # scheduled, not solved inside the depsgraph handler
    reports = live.flush()
    assert [r.name for r in reports] == ["Blob"] and reports[0].solved
    after = radiance(obj)
    x = np.array([v.co.x for v in obj.data.vertices])
    assert after[x < -0.5].mean() > 5 * before[x < -0.5].mean()
    solved = status.solve_status(obj)
    assert solved.seconds > 0 and solved.backend


def test_own_attribute_writes_do_not_trigger_a_solve(solved_ball):
    obj, light, live, state = solved_ball
    light.location = (0.0, 3.0, 1.0)
    assert _update_and_flush(live)
    solves = state.counters()["solves"]
    for _ in range(3):  # the write above and the panel statistics cause depsgraph updates
        _update_and_flush(live)
    assert state.counters()["solves"] == solves
    assert not live.pending()


def test_bursts_coalesce_into_one_solve(solved_ball):
    obj, light, live, state = solved_ball
    solves = state.counters()["solves"]
    for x in np.linspace(3.0, -3.0, 6):  # a drag: many updates before the timer fires
        light.location.x = float(x)
        bpy.context.view_layer.update()
    assert live.pending()
    live.flush()
    assert state.counters()["solves"] == solves + 1


@pytest.mark.parametrize("change", ["energy", "color", "object_moved", "world", "texture", "preset", "tolerance"])
def test_changes_that_resolve(solved_ball, change):
    obj, light, live, state = solved_ball
    before = radiance(obj)
    solves = state.counters()["solves"]
    if change == "energy":
        light.data.energy *= 3.0
    elif change == "color":
        light.data.color = (1.0, 0.2, 0.2)
    elif change == "object_moved":
        obj.location = (0.0, 0.0, 2.0)
    elif change == "world":
        world = bpy.data.worlds.new("sky")
        from translucency.ops.compat import ensure_node_tree

        ensure_node_tree(world)
        next(n for n in world.node_tree.nodes if n.type == 'BACKGROUND').inputs["Strength"].default_value = 5.0
        bpy.context.scene.world = world
    elif change == "texture":
        tex = bpy.data.textures.new("veins", 'CLOUDS')
        s = obj.translucency
        s.use_heterogeneity, s.field_texture = True, tex
        _update_and_flush(live)
        before = radiance(obj)
        solves = state.counters()["solves"]
        tex.noise_scale = 0.1  # a texture edit: an update with an empty list
    elif change == "preset":
        obj.translucency.material_preset = 'SKIN1'  # a Python property: its update callback schedules
    elif change == "tolerance":
        bpy.context.scene.translucency.tolerance = 1e-6
    _update_and_flush(live)
    assert state.counters()["solves"] == solves + 1
    if change != "tolerance":
        assert np.abs(radiance(obj) - before).max() > 1e-4 * before.max()


def test_live_update_off_and_disabled_objects(solved_ball):
    obj, light, live, state = solved_ball
    solves = state.counters()["solves"]
    bpy.context.scene.translucency.live_update = False
    live.flush()
    light.location.x = -3.0
    bpy.context.view_layer.update()
    assert not live.pending()
    bpy.context.scene.translucency.live_update = True
    obj.translucency.enabled = False
    _update_and_flush(live)
    assert state.counters()["solves"] == solves


def _animated_light_scene(tmp_path):
    scene = bpy.context.scene
    obj = sphere()
    light = add_light(location=(3.0, 0.0, 1.0), energy=100.0)
    light.keyframe_insert("location", frame=1)
    light.data.keyframe_insert("energy", frame=1)
    light.location = (-3.0, 1.0, 1.0)
    light.data.energy = 1000.0
    light.keyframe_insert("location", frame=10)
    light.data.keyframe_insert("energy", frame=10)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.location = (0.0, -8.0, 0.0)
    cam.rotation_euler = (np.pi / 2, 0.0, 0.0)
    scene.camera = cam
    scene.render.engine = 'BLENDER_WORKBENCH'
    scene.render.resolution_x = scene.render.resolution_y = 8
    scene.render.filepath = str(tmp_path / "frame_")
    scene.frame_set(1)
    assert bake(obj) == {'FINISHED'}
    return scene, obj, light


class _Written:
    """Records the attribute when a render writes its image (``render_write``): after the
    render Blender restores the frame, and the viewport re-evaluates the attribute along
    the normals, so the render's own values can only be seen while it runs."""

    def __init__(self, obj):
        self.obj = obj
        self.frames = []

    def __call__(self, scene, *_args):
        self.frames.append((scene.frame_current, radiance(self.obj).copy()))

    def __enter__(self):
        bpy.app.handlers.render_write.append(self)
        return self

    def __exit__(self, *_exc):
        bpy.app.handlers.render_write.remove(self)


def test_render_frames_of_an_animated_light(blender, addon, cache_dir, memo_bakes, tmp_path, capfd):
    """frame_set + render per frame (what `blender -b -f` does): each frame is solved
    for its own light, towards the render camera."""
    from translucency.ops import live, runtime

    scene, obj, light = _animated_light_scene(tmp_path)
    with _Written(obj) as written:
        for frame in (1, 10):
            scene.frame_set(frame)
            bpy.ops.render.render(write_still=True)
    results = dict(written.frames)
    assert sorted(results) == [1, 10]
    out = capfd.readouterr().out
    assert "frame 1: 'Blob' solved on the" in out and "frame 10: 'Blob' solved on the" in out
    assert "view towards the camera" in out
    x = np.array([v.co.x for v in obj.data.vertices])
    assert np.abs(results[10] - results[1]).max() > 0.1 * results[1].max()
    assert results[10][x < -0.5].mean() > 5 * results[1][x < -0.5].mean()  # the light moved to -x
    # What the render wrote is the frame-10 solve towards the camera.
    scene.frame_set(10)
    report = runtime.solve_object(obj, scene, use_camera=True, force=True)
    assert report.view == "CAMERA"
    np.testing.assert_allclose(radiance(obj), results[10], rtol=1e-3, atol=1e-6)
    live.flush()


@pytest.mark.gpu
def test_a_gpu_failure_in_a_render_moves_renders_to_the_cpu(gpu_context, blender, addon, cache_dir, memo_bakes,
                                                             tmp_path, monkeypatch, capfd):
    """``backend.after_gpu_failure`` in a render: that frame is solved by the CPU twin, later renders
    stay there (``placement(failed_in_render=...)``), the object's own solver stays on the GPU, and
    the log says why."""
    from translucency.gpu_shaders.solver import GPUDiffusionSolver
    from translucency.ops import runtime, state

    scene, obj, light = _animated_light_scene(tmp_path)
    scene.translucency.solver_backend = 'GPU'
    scene.translucency.live_update = False  # frame_set must not solve in the viewport first
    runtime.solve_object(obj, scene, force=True)
    assert state.get_state(obj).backend == "GPU"

    def fail(self, *_args, **_kw):
        raise SystemError("simulated: no GPU context in the render")

    monkeypatch.setattr(GPUDiffusionSolver, "solve", fail)
    with _Written(obj) as written:
        for frame in (1, 10, 1):  # frame 1 reuses the viewport's GPU solution; frame 10 fails on the GPU
            scene.frame_set(frame)
            bpy.ops.render.render(write_still=True)
    (f1, gpu1), (f10, cpu10), (f1_again, cpu1) = written.frames
    assert (f1, f10, f1_again) == (1, 10, 1)
    assert np.all(np.isfinite(cpu10)) and cpu10[:, 0].sum() != pytest.approx(gpu1[:, 0].sum(), rel=0.05)
    # the CPU twin's frame 1 is the GPU's, to the solver's tolerance (1e-4) of the peak: the CPU folds the
    # bounce into one block solve, the GPU runs the two passes (interreflection.py)
    np.testing.assert_allclose(cpu1, gpu1, rtol=1e-3, atol=1e-4 * float(np.abs(gpu1).max()))
    st = state.get_state(obj)
    assert st.backend == "GPU" and type(st.solver) is not type(st.render_solver)  # the viewport keeps the GPU
    assert st.gpu_failed_in_render.startswith("the GPU solve failed (SystemError: simulated")
    out = capfd.readouterr().out
    assert "the GPU solve failed (SystemError: simulated: no GPU context in the render); using the CPU solver " \
           "for renders" in out
    assert "renders of this object stay on the CPU solver" in out  # the third render, placed by the policy


def test_animation_render_solves_every_frame(blender, addon, cache_dir, memo_bakes, tmp_path):
    from translucency.ops import state

    scene, obj, light = _animated_light_scene(tmp_path)
    scene.frame_start, scene.frame_end, scene.frame_step = 1, 10, 9
    with _Written(obj) as written:
        bpy.ops.render.render(animation=True)
    seen = written.frames
    frames = [f for f, _ in seen]
    assert frames == [1, 10], frames
    assert np.abs(seen[1][1] - seen[0][1]).max() > 0.1 * seen[0][1].max()
    assert state.counters()["solves"] >= 2


_HEADLESS_SCRIPT = textwrap.dedent(r"""
    import importlib.util, json, sys
    import bpy
    root, blend = sys.argv[1], sys.argv[2]
    spec = importlib.util.spec_from_file_location("translucency", root + "/__init__.py",
                                                  submodule_search_locations=[root])
    module = importlib.util.module_from_spec(spec)
    sys.modules["translucency"] = module
    spec.loader.exec_module(module)
    module.register()
    bpy.ops.wm.open_mainfile(filepath=blend)          # like `blender -b scene.blend`
    scene = bpy.context.scene
    obj = bpy.data.objects["Blob"]
    out = {}
    for frame in (1, 10):                               # like `-f 1` and `-f 10`
        scene.frame_set(frame)
        bpy.ops.render.render(write_still=True)
        attr = obj.data.attributes["translucency_radiance"]
        values = [0.0] * (4 * len(attr.data))
        attr.data.foreach_get("color", values)
        out[frame] = sum(values[0::4])
    print("RESULT " + json.dumps(out))
    module.unregister()
""")


def test_headless_render_of_a_saved_file(blender, addon, memo_bakes, tmp_path):
    """A fresh Blender process opens the .blend, finds the cache and renders two frames;
    the log says which solver ran."""
    blend = tmp_path / "anim.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    _animated_light_scene(tmp_path)
    obj = bpy.data.objects["Blob"]
    obj.data.attributes.remove(obj.data.attributes["translucency_radiance"])  # the render must write it
    bpy.ops.wm.save_mainfile()
    script = tmp_path / "headless.py"
    script.write_text(_HEADLESS_SCRIPT)
    proc = subprocess.run([sys.executable, str(script), str(ROOT), str(blend)], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(lines[-1][len("RESULT "):])
    assert result["1"] > 0 and result["10"] > 0 and result["1"] != pytest.approx(result["10"], rel=0.05)
    assert "loaded the bake of 'Blob'" in proc.stdout
    assert "'Blob' solves on the CPU" in proc.stdout or "'Blob' solves on the GPU" in proc.stdout
    assert "frame 10: 'Blob' solved on the" in proc.stdout, proc.stdout


def test_load_post_clears_runtime_state(solved_ball, tmp_path):
    obj, light, live, state = solved_ball
    assert state.get_state(obj) is not None
    blend = tmp_path / "reload.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    assert state.object_states() == []
    obj = bpy.data.objects["Blob"]
    assert state.cache_problem("Blob") is None  # the absolute cache path is still valid


def test_unregister_removes_every_handler(blender, addon):
    from translucency.ops import handlers, live

    names = {name for name, _fn in handlers.HANDLERS}
    assert {name for name, _fn in handlers.registered_handlers()} == names
    assert len(handlers.registered_handlers()) == len(handlers.HANDLERS)
    live.request_update()
    assert live.pending()
    addon.unregister()
    assert handlers.registered_handlers() == []
    assert not live.pending()
    for name in names:  # nothing of ours, by marker or by module
        for fn in getattr(bpy.app.handlers, name):
            assert not getattr(fn, "__module__", "").startswith("translucency.ops.handlers")
    addon.register()
    assert len(handlers.registered_handlers()) == len(handlers.HANDLERS)  # no duplicates
    handlers.register_handlers()  # even when called again (e.g. a module reload)
    assert len(handlers.registered_handlers()) == len(handlers.HANDLERS)
