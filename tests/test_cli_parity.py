# SPDX-License-Identifier: GPL-3.0-or-later
"""One frame, one answer (issue 29): the add-on and the command line render the same radiance.

A scene is solved through the add-on (bake operator, ``runtime.solve_object`` as F12 does, towards the
camera); the CLI's ``solve`` then renders the add-on's own cache with the same inputs: the material,
the scale, the tolerance, the lights and the World exactly as the add-on read them for that frame
(``ops.frame.gather``, object space, W and W/m^2), and the camera.  Per vertex the two agree to 1e-5 of
the mean.  Before the one recipe (``translucency_addon/frame.py``) the CLI had its own: no planner, no
first-scatter split, single scattering added on top of diffusion -- 35 % RMS apart on a held-out mesh.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys

import bpy
import numpy as np
import pytest

from conftest import ROOT
from test_ops_bake import activate, add_light, bake, cache_dir, memo_bakes, radiance, sphere  # noqa: F401


@pytest.fixture(autouse=True)
def _cpu_backend(blender):
    """The recipe is compared on the CPU, in fp64, whether or not this process has a GPU context (the GPU's fp32
    solve agrees with the CPU to its own tolerance: test_gpu_solver, the hard cases, and the GPU test below)."""
    bpy.context.scene.translucency.solver_backend = 'CPU'


def _camera(location=(0.0, -6.0, 1.5)):
    data = bpy.data.cameras.new("Cam")
    cam = bpy.data.objects.new("Cam", data)
    cam.location = location
    direction = -np.asarray(location, dtype=np.float64)
    from mathutils import Vector

    cam.rotation_euler = Vector(direction).to_track_quat('-Z', 'Y').to_euler()
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    return cam


def _world(rgb):
    world = bpy.data.worlds.new("Sky")
    if bpy.app.version < (5, 0, 0):  # always nodes from 5.0 (use_nodes deprecated)
        world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*rgb, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    bpy.context.scene.world = world


def _cli_options(frame) -> list[str]:
    """The add-on's frame inputs as the CLI's options (every light must be one the CLI can express)."""
    out = ["--mm-per-unit", repr(frame.mm), "--tol", repr(frame.tolerance)]
    for light in frame.lights:
        assert tuple(light.color) == (1.0, 1.0, 1.0), "a coloured light: the CLI takes white lights"
        if light.kind == "sun":
            d = ",".join(repr(float(x)) for x in light.direction)
            out.append(f"--sun={d}:{light.irradiance!r}")
        elif light.kind == "point":
            p = ",".join(repr(float(x)) for x in light.position)
            out.append(f"--point={p}:{4.0 * math.pi * light.intensity!r}:{light.radius!r}")
        elif light.kind == "spot":
            p, d = (",".join(repr(float(x)) for x in v) for v in (light.position, light.direction))
            out.append(f"--spot={p}:{d}:{4.0 * math.pi * light.intensity!r}:{math.degrees(light.spot_size)!r}:"
                       f"{light.spot_blend!r}:{light.radius!r}")
        elif light.kind == "area":
            p, ex, ey = (",".join(repr(float(x)) for x in v) for v in (light.position, light.edge_x, light.edge_y))
            out.append(f"--area={p}:{ex}:{ey}:{math.pi * light.intensity!r}" + (":disk" if light.shape == "ellipse"
                                                                                 else ""))
        else:
            raise AssertionError(f"a {light.kind} light has no CLI option yet")
    env = frame.environment
    if env is not None and not env.is_black:
        assert env.sh is None, "an SH or image World: the CLI takes a uniform one"
        out += ["--env", ",".join(repr(float(x)) for x in env.radiance)]
    if frame.view is not None:
        kind, value = frame.view
        assert kind == "PERSP"
        out += ["--camera", ",".join(repr(float(x)) for x in value)]
    return out


SCENES = {
    "marble, sky and sun": dict(preset='MARBLE', world=(0.3, 0.35, 0.4), lights=[('SUN', (0.0, 0.0, 5.0), 3.0)]),
    "skin1, point light": dict(preset='SKIN1', world=None, lights=[('POINT', (3.0, -2.0, 2.0), 800.0)]),
    "ketchup, sun (single scattering replaces diffusion)": dict(
        preset='KETCHUP', world=(0.2, 0.2, 0.2), lights=[('SUN', (0.0, 0.0, 5.0), 3.0)], single=True),
    "skin1, a spot and a rectangular area light (issue 31's lamps through the CLI)": dict(
        preset='SKIN1', world=None, lights=[('SPOT', (1.5, 0.0, 3.0), 600.0, (0.0, 0.45, 0.0)),
                                            ('AREA', (-1.0, -2.0, 2.5), 300.0, (0.7, -0.3, 0.2))]),
    "marble and skin1 mixed by a mesh attribute, sky and sun": dict(
        preset='MARBLE', world=(0.3, 0.35, 0.4), lights=[('SUN', (0.0, 0.0, 5.0), 3.0)], mix_with='SKIN1'),
}


def _positions(obj) -> np.ndarray:
    me = obj.data
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _attribute_field(obj, second: str) -> np.ndarray:
    """A heterogeneous material whose field is a float attribute (0 at the bottom, 1 at the top); the weights
    per vertex, as the CLI's --field-values takes them."""
    me = obj.data
    z = _positions(obj)[:, 2]
    weights = (z - z.min()) / (z.max() - z.min())
    me.attributes.new("mix", 'FLOAT', 'POINT').data.foreach_set("value", weights.astype(np.float32))
    s = obj.translucency
    s.use_heterogeneity, s.second_preset, s.field_source, s.field_attribute = True, second, 'ATTRIBUTE', "mix"
    return weights.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize("scene_name", list(SCENES))
def test_the_cli_renders_what_the_addon_renders(blender, addon, cache_dir, memo_bakes, tmp_path, scene_name):
    from translucency.ops import runtime, state
    from translucency.ops.frame import gather

    spec = SCENES[scene_name]
    obj = sphere(name="Ball")
    obj.translucency.material_preset = spec["preset"]
    if spec.get("single"):
        obj.translucency.use_single_scattering = True
        obj.translucency.ss_samples = 300
    weights = _attribute_field(obj, spec["mix_with"]) if spec.get("mix_with") else None
    if spec["world"] is not None:
        _world(spec["world"])
    else:
        bpy.context.scene.world = None
    for kind, location, energy, *rotation in spec["lights"]:
        rot = rotation[0] if rotation else ((0.3, 0.2, 0.0) if kind == 'SUN' else (0, 0, 0))
        lamp = add_light(kind, location=location, energy=energy, rotation=rot)
        if kind == 'SPOT':
            lamp.data.spot_size, lamp.data.spot_blend = math.radians(50.0), 0.3
        if kind == 'AREA':
            lamp.data.shape, lamp.data.size, lamp.data.size_y = 'RECTANGLE', 1.2, 0.5
    _camera()
    bpy.context.scene.translucency.tolerance = 1e-8  # both converged: the comparison sees the recipe, not the stop
    activate(obj)
    assert bake(obj) == {'FINISHED'}
    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    runtime.solve_object(obj, scene, depsgraph, use_camera=True, force=True)
    ours = radiance(obj)
    st = state.get_state(obj)
    frame = gather(obj, scene, depsgraph, st, True)
    if spec.get("single"):
        assert frame.use_ss, "the scene is meant to run single scattering"
    assert {x.kind for x in frame.lights} == {k.lower() for k, *_ in spec["lights"]}, "every lamp reaches the frame"
    cache = bpy.path.abspath(obj.translucency.cache_filepath)
    out = tmp_path / "cli.npy"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "translucency_addon", "solve", cache, "-o", str(out),
           "--material", spec["preset"].lower(), *_cli_options(frame)]
    if weights is not None:
        from translucency_addon.cache import load_bake

        baked = load_bake(cache).mesh_vertices
        co = _positions(obj)
        np.testing.assert_allclose(baked[: len(co)], co, atol=1e-6)  # the same vertices
        np.save(tmp_path / "weights.npy", weights)
        cmd += ["--mix-with", spec["mix_with"].lower(), "--field-values", str(tmp_path / "weights.npy")]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    cli = np.load(out)[: len(ours)]
    mean = float(np.abs(ours).mean())
    assert mean > 0
    diff = float(np.abs(cli - ours).max()) / mean
    assert diff <= 1e-5, f"{scene_name}: the CLI differs from the add-on by {diff:.2e} of the mean\n{' '.join(cmd)}"


def test_a_deformed_pose_renders_the_same_through_the_cli(blender, addon, cache_dir, memo_bakes, tmp_path):
    """An armature pose solved on the baked graph (no re-bake) by the add-on's frame handler, and the CLI's
    ``solve --deformed POSED.obj`` of the add-on's cache with the same evaluated mesh: the same radiance."""
    from test_ops_deformation import baked_bar, evaluated, key_bend

    from translucency.ops import state
    from translucency.ops.frame import gather
    from translucency.translucency_addon.geometry.meshio import save_obj

    obj, rig = baked_bar()
    key_bend(rig, 10, 60.0)
    scene = bpy.context.scene
    scene.frame_set(10)  # the frame handler solves the pose
    ours = radiance(obj)
    st = state.get_state(obj)
    assert st.pose is not None
    V, F = evaluated(obj)
    posed = tmp_path / "posed.obj"
    save_obj(posed, V, F)
    frame = gather(obj, scene, bpy.context.evaluated_depsgraph_get(), st, False)
    out = tmp_path / "cli.npy"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "translucency_addon", "solve", bpy.path.abspath(obj.translucency.cache_filepath),
           "-o", str(out), "--material", obj.translucency.material_preset.lower(), "--deformed", str(posed),
           *_cli_options(frame)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    cli = np.load(out)[: len(ours)]
    diff = float(np.abs(cli - ours).max()) / float(np.abs(ours).mean())
    assert diff <= 1e-5, f"the CLI differs from the add-on on the pose by {diff:.2e} of the mean\n{' '.join(cmd)}"


def _cli_material(obj) -> list[str]:
    s = obj.translucency
    if s.material_preset != 'CUSTOM':
        return ["--material", s.material_preset.lower()]
    return ["--sigma-a", ",".join(repr(float(x)) for x in s.sigma_a),
            "--sigma-s", ",".join(repr(float(x)) for x in s.sigma_s), "--eta", repr(float(s.eta))]


def _addon_then_cli(obj, tmp_path, use_camera=False):
    """The add-on's radiance of ``obj`` (solved as F12 does) and the CLI's on its cache with the same inputs."""
    from translucency.ops import runtime, state
    from translucency.ops.frame import gather

    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    runtime.solve_object(obj, scene, depsgraph, use_camera=use_camera, force=True)
    ours = radiance(obj)
    frame = gather(obj, scene, depsgraph, state.get_state(obj), use_camera)
    out = tmp_path / "cli.npy"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "translucency_addon", "solve", bpy.path.abspath(obj.translucency.cache_filepath),
           "-o", str(out), *_cli_material(obj), *_cli_options(frame)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return ours, np.load(out)[: len(ours)], frame, cmd


@pytest.mark.parametrize("scene_name", ["cube with a cavity", "bottle of wine"])
def test_inner_parts_render_the_same_through_the_cli(blender, addon, cache_dir, memo_bakes, tmp_path, scene_name):
    """Inner parts: the marble cube with a cavity (the cavity exchange) and the glass bottle of wine (the planner
    hands it to the Voxel Number Map), through the add-on and through the CLI on the add-on's cache."""
    from test_ops_inner_parts import bake_op, bottle_scene, cube_scene

    obj = cube_scene()[0] if scene_name == "cube with a cavity" else bottle_scene()[0]
    bpy.context.scene.translucency.tolerance = 1e-8
    assert bake_op(obj) == {'FINISHED'}
    ours, cli, frame, cmd = _addon_then_cli(obj, tmp_path)
    if scene_name == "cube with a cavity":
        assert frame.use_ms and st_exchange(obj)
    else:
        assert frame.use_vnm and not frame.use_ms
    diff = float(np.abs(cli - ours).max()) / float(np.abs(ours).mean())
    assert diff <= 1e-5, f"{scene_name}: the CLI differs from the add-on by {diff:.2e} of the mean\n{' '.join(cmd)}"


def st_exchange(obj) -> bool:
    from translucency.ops import state

    return state.get_state(obj).bake.composite.exchange is not None


def test_a_particle_fluid_renders_the_same_through_the_cli(blender, addon, tmp_path):
    """A point cloud that is its own Fluid source (Kang & Kim's Voronoi-fluid cells every frame, no bake), solved
    by the add-on, and the CLI's ``fluid`` on the same particles with the same radius, scale, lights and World."""
    from test_ops_fluid import as_fluid, blob, point_cloud, sun

    from translucency.ops import fluid_runtime, state

    P = blob()
    obj = as_fluid(point_cloud("Milk", P))
    bpy.context.scene.unit_settings.scale_length = 0.01  # 1 unit = 10 mm
    bpy.context.scene.translucency.tolerance = 1e-8
    sun()
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    ours = radiance(obj)
    frame = fluid_runtime.gather(obj, bpy.context.scene, bpy.context.evaluated_depsgraph_get(),
                                 state.fluid_state(obj), False)
    assert frame.use_points and frame.view is None
    points = tmp_path / "points.npy"
    np.save(points, np.asarray(frame.particles.points, dtype=np.float64))
    out = tmp_path / "phi.npz"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "translucency_addon", "fluid", str(points), "-o", str(out),
           "--radius", repr(float(frame.radius)), "--material", obj.translucency.material_preset.lower(),
           *_cli_options(frame)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    with np.load(out) as z:
        cli = np.asarray(z["point_radiance"], dtype=np.float64)
    diff = float(np.abs(cli - ours).max()) / float(np.abs(ours).mean())
    assert diff <= 1e-5, f"the CLI's fluid differs from the add-on's by {diff:.2e} of the mean\n{' '.join(cmd)}"


@pytest.mark.gpu
def test_the_gpu_backend_renders_only_the_planners_channels(blender, addon, cache_dir, memo_bakes):
    """Ketchup under a sun: the planner runs diffusion in red only (green and blue: reduced albedo 0.07 and 0.02,
    handed to single scattering).  The GPU solver solves every channel; its diffusion must not reach the channels
    the planner turned off.  It did: green and blue came out 4.5x and 13x the CPU's (the single scattering alone)."""
    from translucency.ops import runtime, state

    obj = sphere(name="Ball")
    obj.translucency.material_preset = 'KETCHUP'
    obj.translucency.use_single_scattering = True
    obj.translucency.ss_samples = 300
    _world((0.2, 0.2, 0.2))
    add_light('SUN', location=(0.0, 0.0, 5.0), energy=3.0, rotation=(0.3, 0.2, 0.0))
    bpy.context.scene.translucency.tolerance = 1e-6
    activate(obj)
    assert bake(obj) == {'FINISHED'}
    out = {}
    for backend in ('CPU', 'GPU'):
        bpy.context.scene.translucency.solver_backend = backend
        runtime.solve_object(obj, bpy.context.scene, bpy.context.evaluated_depsgraph_get(), force=True)
        out[backend] = radiance(obj).copy()
        assert state.get_state(obj).backend == backend
    plan = state.get_state(obj).plan
    assert plan.multiple.channels == (True, False, False) and plan.single.channels[1:] == (True, True)
    cpu, gpu = out['CPU'], out['GPU']
    err = np.abs(gpu - cpu).max(axis=0) / np.abs(cpu).mean(axis=0)
    assert np.all(err < 1e-3), f"GPU vs CPU per channel, of the channel's mean: {err}"
