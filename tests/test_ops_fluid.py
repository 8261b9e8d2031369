# SPDX-License-Identifier: GPL-3.0-or-later
"""The Fluid source in Blender (issue 14, item 5): particles of an emitter, a point cloud, Geometry Nodes or a
Mantaflow domain -> Voronoi-fluid cells every frame -> the ``translucency_radiance`` attribute and AOV.

Background Blender has no event loop: frame changes run the handlers at once
(``scene.frame_set``), and a pending live check runs with ``live.flush()``.
A few hundred particles per fluid keep every solve well under a second.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import textwrap

import bpy
import numpy as np
import pytest

from conftest import ROOT
from test_ops_bake import activate, add_light, radiance

SPACING = 0.1


def blob(radius=0.3, spacing=SPACING, center=(0.0, 0.0, 0.0), seed=0):
    """A ball of jittered lattice particles (about 120 for the defaults)."""
    k = int(math.ceil(radius / spacing))
    g = np.mgrid[-k:k + 1, -k:k + 1, -k:k + 1].reshape(3, -1).T * spacing
    P = g[np.linalg.norm(g, axis=1) <= radius]
    return P + np.random.default_rng(seed).uniform(-0.1 * spacing, 0.1 * spacing, P.shape) + np.asarray(center)


def point_cloud(name, points, ids=True, location=(0.0, 0.0, 0.0)):
    pc = bpy.data.pointclouds.new(name)
    set_points(pc, points, ids)
    obj = bpy.data.objects.new(name, pc)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def set_points(pc, points, ids=True):
    P = np.asarray(points, dtype=np.float32)
    if len(pc.points) != len(P):
        pc.resize(len(P))
    pc.attributes["position"].data.foreach_set("vector", P.ravel())
    radius = pc.attributes.get("radius") or pc.attributes.new("radius", 'FLOAT', 'POINT')
    radius.data.foreach_set("value", np.full(len(P), SPACING, np.float32))  # rendered as the union of the balls
    if ids:
        attr = pc.attributes.get("id") or pc.attributes.new("id", 'INT', 'POINT')
        attr.data.foreach_set("value", np.arange(len(P), dtype=np.int32))
    pc.update_tag()


def as_fluid(obj, kind='POINT_CLOUD', source=None, preset='SKIMMILK'):
    s = obj.translucency
    s.enabled = True
    s.source = 'FLUID'
    s.fluid_kind = kind
    s.fluid_object = source
    s.material_preset = preset
    return obj


def sun(energy=3.0, rotation=(0.0, math.radians(60.0), 0.0)):
    """A sun shining down and towards -x (its light comes from +x)."""
    return add_light('SUN', location=(0.0, 0.0, 5.0), energy=energy, rotation=rotation)


EMITTED = 286  # particles on the emitter's 8^3 grid inside its ball


def emitter(location=(0.0, 0.0, 0.0), frame_start=1, frame_end=1, speed=0.0, lifetime=100):
    """An icosphere emitting particles on a jittered grid inside its volume; they fly apart at ``speed``."""
    bpy.ops.mesh.primitive_ico_sphere_add(radius=0.3, subdivisions=2, location=location)
    em = bpy.context.object
    em.name = "Emitter"
    em.modifiers.new("Particles", 'PARTICLE_SYSTEM')
    psys = em.particle_systems[0]
    s = psys.settings
    s.frame_start, s.frame_end, s.lifetime = frame_start, frame_end, lifetime
    s.emit_from, s.distribution, s.grid_resolution, s.grid_random = 'VOLUME', 'GRID', 8, 0.1
    s.normal_factor = 0.0
    s.factor_random = speed
    s.effector_weights.gravity = 0.0
    return em


def target_sphere(name="Milk", radius=0.34, location=(0.0, 0.0, 0.0)):
    bpy.ops.mesh.primitive_ico_sphere_add(radius=radius, subdivisions=3, location=location)
    obj = bpy.context.object
    obj.name = name
    return obj


def snapshot():
    """What a failed solve must leave alone: the ID counts and every radiance attribute's values."""
    values = {}
    for obj in bpy.data.objects:
        data = obj.data
        attr = getattr(data, "attributes", None) and data.attributes.get("translucency_radiance")
        if attr is not None:
            rgba = np.empty(4 * len(attr.data), np.float32)
            attr.data.foreach_get("color", rgba)
            values[obj.name] = rgba.tobytes()
    return (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.node_groups), len(bpy.data.pointclouds),
            tuple((o.name, len(o.modifiers)) for o in bpy.data.objects), values)


def engine_solve(points, radius, mm, ids=None, surface=None, light_dir=None, irradiance=3.0):
    """The same frame through the engine directly (the independent check of what the add-on passes it)."""
    from translucency.translucency_addon.fluid import FluidSolver
    from translucency.translucency_addon.scene.lights import Light
    from translucency.translucency_addon.scene.materials import Material, preset

    lights = [Light("sun", color=(1.0, 1.0, 1.0), irradiance=irradiance, direction=light_dir)]
    return FluidSolver(Material(preset("skimmilk"), eta=1.3), radius, mm).solve(points, ids=ids, lights=lights,
                                                                               surface=surface)


def sun_direction(light):
    d = light.matrix_world.to_3x3() @ __import__("mathutils").Vector((0.0, 0.0, -1.0))
    return tuple(d.normalized())


# --------------------------------------------------------------------------- sources and outputs


def test_point_cloud_fluid_matches_the_engine(blender, addon):
    """A point cloud that is its own source: the point attribute is the engine's frame for the same
    particles, radius (Auto: the spacing), scale (the scene's unit scale: 1 unit = 10 mm) and sun, so units
    and lights arrive intact."""
    from translucency.ops import state, status
    from translucency.translucency_addon.fluid import suggest_radius

    P = blob()
    obj = as_fluid(point_cloud("Milk", P))
    bpy.context.scene.unit_settings.scale_length = 0.01  # 1 unit = 10 mm: a 6 mm drop, a few mean free paths
    light = sun()
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    attr = obj.data.attributes["translucency_radiance"]
    assert (attr.domain, attr.data_type, len(attr.data)) == ('POINT', 'FLOAT_COLOR', len(P))
    got = radiance(obj)
    want = engine_solve(P, suggest_radius(P), 10.0, ids=np.arange(len(P)),
                        light_dir=sun_direction(light)).point_radiance
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
    assert got.max() > 0 and got[P[:, 0] > 0.15].mean() > 2 * got[P[:, 0] < -0.15].mean()  # lit from +x
    st = state.fluid_state_of("Milk")
    assert st.particles == len(P) and st.cells == len(P) and st.surface_cells > 0 and st.solves == 1
    lines = status.fluid_lines(obj)
    assert lines[0].startswith(f"Frame 1: {len(P):,} particles (points of 'Milk') -> {len(P)} points")
    assert any(line.startswith("A frame costs") for line in lines)
    assert f"fluid: {len(P):,} particles, diffusion valid" in status.plan_summary("Milk")


@pytest.mark.gpu
def test_a_fluid_solves_on_the_gpu_like_the_engine(blender, addon):
    """Solver = GPU (llvmpipe here): the fluid's diffusion runs on the GPU solver (its cells' links in link
    pages; issue 34, item 4), the attribute is the engine's CPU frame, and the last frame's textures are
    freed when the next frame solves; a GPU solve that fails sends the fluid to the CPU with the reason."""
    from translucency.ops import state
    from translucency.translucency_addon.fluid import suggest_radius

    P = blob()
    obj = as_fluid(point_cloud("Milk", P))
    bpy.context.scene.unit_settings.scale_length = 0.01
    light = sun()
    bpy.context.scene.translucency.solver_backend = 'GPU'
    try:
        activate(obj)
        assert bpy.ops.translucency.solve() == {'FINISHED'}
        st = state.fluid_state_of("Milk")
        assert st.backend == "GPU" and st.backend_message == ""
        want = engine_solve(P, suggest_radius(P), 10.0, ids=np.arange(len(P)),
                            light_dir=sun_direction(light)).point_radiance
        np.testing.assert_allclose(radiance(obj), want, rtol=1e-4, atol=1e-4 * want.max())
        light.rotation_euler[0] += 0.1  # the next frame: new inputs, a new solve (and a failing GPU)
        from translucency.gpu_shaders import solver as gpu_solver

        def broken(*_a, **_k):
            raise SystemError("no GPU context (test)")

        old = gpu_solver.GPUDiffusionSolver.solve_systems
        gpu_solver.GPUDiffusionSolver.solve_systems = broken
        try:
            assert bpy.ops.translucency.solve() == {'FINISHED'}
        finally:
            gpu_solver.GPUDiffusionSolver.solve_systems = old
        assert st.backend == "CPU" and "the GPU solve failed (SystemError: no GPU context (test))" in st.backend_message
        from translucency.ops import status

        assert f"Diffusion on the CPU: {st.backend_message}" in status.fluid_lines(obj)
        want = engine_solve(P, suggest_radius(P), 10.0, ids=np.arange(len(P)),
                            light_dir=sun_direction(light)).point_radiance
        np.testing.assert_allclose(radiance(obj), want, rtol=1e-4, atol=1e-4 * want.max())
    finally:
        bpy.context.scene.translucency.solver_backend = 'AUTO'


def test_emitter_particles_onto_a_mesh_every_frame_warm_started_by_id(blender, addon):
    """A particle system's particles (evaluated object, world space) into the target's object space; each
    frame re-solves, warm-started from the last by particle index."""
    from translucency.ops import live, state, status
    from translucency.ops.scene_inputs import mesh_arrays
    from translucency.translucency_addon.fluid import suggest_radius

    em = emitter(speed=0.5, location=(0.5, 0.0, 0.0))
    target = as_fluid(target_sphere(radius=0.17, location=(0.5, 0.0, 0.0)), kind='PARTICLES', source=em)
    target.scale = (2.0, 2.0, 2.0)  # the target's space is not the world's: 1 unit = 2 m
    sun()
    scene = bpy.context.scene
    seen = []
    for frame in (1, 2, 3):
        scene.frame_set(frame)
        live.flush()
        assert state.solve_errors() == {}, state.solve_errors()
        st = state.fluid_state_of("Milk")
        seen.append((radiance(target).copy(), st.warm_started, st.particles))
    assert [s[1:] for s in seen] == [(False, EMITTED), (True, EMITTED), (True, EMITTED)]
    assert np.abs(seen[2][0] - seen[0][0]).max() > 0.05 * seen[0][0].max()  # the particles moved
    st = state.fluid_state_of("Milk")
    assert st.source == "particle system 'Particles' of 'Emitter'" and st.output == "162 vertices"
    # The particles went into the target's space: a direct solve of them, moved there, agrees.
    ev = em.evaluated_get(bpy.context.evaluated_depsgraph_get()).particle_systems[0].particles
    loc = np.empty(3 * len(ev), np.float32)
    ev.foreach_get("location", loc)
    P = (loc.reshape(-1, 3) - (0.5, 0.0, 0.0)) / 2.0
    assert st.radius == pytest.approx(2.0 * suggest_radius(P), rel=1e-6)  # scene units
    V, F = mesh_arrays(target.data)
    want = engine_solve(P, suggest_radius(P), 2000.0, ids=np.arange(len(P)), surface=(V, F),
                        light_dir=sun_direction(bpy.data.objects["sun"])).vertex_radiance
    np.testing.assert_allclose(radiance(target), want, rtol=2e-3, atol=1e-4 * want.max())
    assert f"Frame 3: {EMITTED} particles" in status.fluid_lines(target)[0]


def test_generated_geometry_gets_the_radiance_through_the_carrier(blender, addon):
    """A target whose modifiers generate what renders (as Mantaflow's liquid mesh does): the radiance
    reaches the evaluated vertices through the 'Translucency Radiance' modifier; without such modifiers it
    goes onto obj.data again and the carrier is removed."""
    from translucency.ops import attributes, live, state

    P = blob()
    cloud = point_cloud("Particles", P)
    cloud.hide_render = True
    target = as_fluid(target_sphere(), source=cloud)
    target.modifiers.new("Subdivision", 'SUBSURF').levels = 1
    sun()
    activate(target)
    assert bpy.ops.translucency.solve() == {'FINISHED'}, state.solve_errors()
    assert [m.name for m in target.modifiers] == ["Subdivision", "Translucency Radiance"]
    ev = target.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
    attr = ev.attributes["translucency_radiance"]
    assert len(attr.data) == len(ev.vertices) == 962  # 162 vertices, subdivided once
    rgba = np.empty(4 * len(attr.data), np.float32)
    attr.data.foreach_get("color", rgba)
    from translucency.ops.scene_inputs import mesh_arrays

    V, F = mesh_arrays(ev)
    from translucency.translucency_addon.fluid import suggest_radius

    want = engine_solve(P, suggest_radius(P), 1000.0, ids=np.arange(len(P)), surface=(V, F),
                        light_dir=sun_direction(bpy.data.objects["sun"])).vertex_radiance
    np.testing.assert_allclose(rgba.reshape(-1, 4)[:, :3], want, rtol=1e-3, atol=1e-5)
    assert target.data.attributes.get("translucency_radiance") is None
    carrier = bpy.data.objects[f"Milk {attributes.CARRIER_MODIFIER}"]
    assert carrier.users_collection == ()  # in no scene: never rendered itself
    # A modifier added after ours: ours moves back to the end.
    target.modifiers.new("Smooth", 'SMOOTH')
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert [m.name for m in target.modifiers][-1] == "Translucency Radiance"
    # No generating modifier left: the attribute goes onto obj.data and the carrier goes away.
    for name in ("Subdivision", "Smooth"):
        target.modifiers.remove(target.modifiers[name])
    bpy.context.view_layer.update()
    live.flush()
    assert [m.name for m in target.modifiers] == []
    assert f"Milk {attributes.CARRIER_MODIFIER}" not in bpy.data.objects
    assert radiance(target).shape == (162, 3) and radiance(target).max() > 0


def test_geometry_nodes_points_are_a_source(blender, addon):
    """The points a Geometry Nodes object outputs (its evaluated point cloud, here Mesh to Points of loose
    vertices), with their 'id' attribute: the same frame as the engine's for those points."""
    from translucency.ops import state
    from translucency.ops.scene_inputs import mesh_arrays
    from translucency.translucency_addon.fluid import suggest_radius

    P = blob()
    mesh = bpy.data.meshes.new("Points GN")
    mesh.from_pydata(P.tolist(), [], [])
    mesh.attributes.new("id", 'INT', 'POINT').data.foreach_set("value", np.arange(len(P), dtype=np.int32) * 7)
    gn = bpy.data.objects.new("Points GN", mesh)
    bpy.context.scene.collection.objects.link(gn)
    group = bpy.data.node_groups.new("Mesh To Points", 'GeometryNodeTree')
    group.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    group.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    inp, out = group.nodes.new('NodeGroupInput'), group.nodes.new('NodeGroupOutput')
    to_points = group.nodes.new('GeometryNodeMeshToPoints')
    group.links.new(inp.outputs[0], to_points.inputs[0])
    group.links.new(to_points.outputs[0], out.inputs[0])
    gn.modifiers.new("Points", 'NODES').node_group = group
    target = as_fluid(target_sphere(), kind='GEOMETRY_NODES', source=gn)
    target.scale = (0.5, 0.5, 0.5)  # the target's space: the points arrive scaled, and 1 unit = 2.5 mm
    bpy.context.scene.unit_settings.scale_length = 0.005
    light = sun()
    activate(target)
    assert bpy.ops.translucency.solve() == {'FINISHED'}, state.solve_errors()
    st = state.fluid_state_of("Milk")
    assert st.source == "points of 'Points GN'" and st.particles == len(P)
    V, F = mesh_arrays(target.data)
    P = 2.0 * P
    want = engine_solve(P, suggest_radius(P), 2.5, ids=np.arange(len(P)) * 7, surface=(V, F),
                        light_dir=sun_direction(light)).vertex_radiance
    np.testing.assert_allclose(radiance(target), want, rtol=1e-4, atol=1e-6)
    # A Geometry Nodes object that outputs no points is refused with what to do.
    to_points.mute = True
    with pytest.raises(RuntimeError, match="'Points GN' outputs no points: its Geometry Nodes must output a point"):
        bpy.ops.translucency.solve()


def test_two_media_from_a_point_attribute(blender, addon):
    """A point attribute of the source mixes two media per particle, as a mesh attribute does for meshes; a
    particle system has no point attributes and says so."""
    from translucency.ops import state
    from translucency.translucency_addon.fluid import FluidSolver, suggest_radius
    from translucency.translucency_addon.scene.lights import Light
    from translucency.translucency_addon.scene.materials import Material, preset

    P = blob()
    obj = as_fluid(point_cloud("Milk", P))
    weight = (P[:, 0] > 0).astype(np.float32)  # ketchup on the +x half
    obj.data.attributes.new("ketchup", 'FLOAT', 'POINT').data.foreach_set("value", weight)
    s = obj.translucency
    s.use_heterogeneity, s.second_preset, s.field_source, s.field_attribute = True, 'KETCHUP', 'ATTRIBUTE', "ketchup"
    light = sun()
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}, state.solve_errors()
    mixed = Material(preset("skimmilk"), preset("ketchup"), eta=1.3)
    lights = [Light("sun", color=(1.0, 1.0, 1.0), irradiance=3.0, direction=sun_direction(light))]
    want = FluidSolver(mixed, suggest_radius(P), 1000.0).solve(P, ids=np.arange(len(P)), field_values=weight,
                                                               lights=lights).point_radiance
    got = radiance(obj)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
    assert got[weight > 0, 1].mean() < 0.3 * got[weight > 0, 0].mean()  # ketchup keeps red, absorbs green
    s.fluid_kind, s.fluid_object = 'PARTICLES', emitter()
    activate(obj)
    with pytest.raises(RuntimeError, match="particle systems carry no point attributes for the heterogeneity field"):
        bpy.ops.translucency.solve()


# --------------------------------------------------------------------------- frames, renders, playback


def _render_scene(tmp_path):
    from translucency.ops import render_pass

    scene = bpy.context.scene
    em = emitter(speed=1.0)
    target = as_fluid(target_sphere(), kind='PARTICLES', source=em)
    em.show_instancer_for_render = False  # the emitter itself is not rendered; its particles are evaluated
    cloud = as_fluid(point_cloud("Drops", blob(), location=(1.0, 0.0, 0.0)))
    cloud.data.materials.append(bpy.data.materials.new("Drops"))
    sun(energy=5.0)
    for obj in (target, cloud):
        activate(obj)
        assert bpy.ops.translucency.add_to_material() == {'FINISHED'}
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.type = 'ORTHO'
    camera.data.ortho_scale = 2.4
    camera.location = (0.5, 0.0, 5.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = 'CYCLES'
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = 'CPU', 1, False
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 24, 12, 100
    render_pass.configure_output(scene.render.image_settings, 'OPEN_EXR_MULTILAYER')
    scene.render.filepath = str(tmp_path / "frame_")
    scene.frame_start, scene.frame_end = 1, 3
    return scene, target, cloud


def test_animation_render_of_a_saved_file_solves_every_frame(blender, addon, tmp_path, capfd):
    """`blender -b file.blend -a`: open the saved file, render the animation; every frame is a fresh solve
    of that frame's particles towards the camera, and the Translucency AOV follows the particles."""
    from tools.exr import exr_pass
    from translucency.ops import fluid_runtime, state

    _render_scene(tmp_path)
    blend = tmp_path / "fluid.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))  # like `blender -b fluid.blend`
    assert state.all_states() == []
    scene, target = bpy.context.scene, bpy.data.objects["Milk"]
    assert target.translucency.source == 'FLUID' and target.translucency.fluid_object.name == "Emitter"
    written = []

    def grab(scene_, *_):
        written.append((scene_.frame_current, radiance(target).copy()))

    bpy.app.handlers.render_write.append(grab)
    try:
        bpy.ops.render.render(animation=True)  # like `-a`
    finally:
        bpy.app.handlers.render_write.remove(grab)
    assert [f for f, _ in written] == [1, 2, 3]
    out = capfd.readouterr().out
    for frame in (1, 2, 3):
        assert f"frame {frame}: 'Milk' fluid frame {frame}: {EMITTED} particles" in out, out[-3000:]
    assert "view towards the camera" in out
    aov = [exr_pass(tmp_path / f"frame_{f:04d}.exr", "Translucency")[..., :3] for f in (1, 2, 3)]
    left = [a[:, :12] for a in aov]  # the emitter's fluid; the point cloud is on the right
    assert all(np.isfinite(a).all() and (a.max(axis=2) > 0).mean() > 0.2 for a in left)
    assert np.abs(left[2] - left[0]).max() > 0.05 * left[0].max()  # the AOV follows the particles
    assert (aov[0][:, 12:].max(axis=2) > 0).sum() >= 4  # the point cloud's spheres carry it too
    # What frame 3 rendered is that frame's solve towards the camera.
    scene.frame_set(3)
    report = fluid_runtime.solve_fluid(target, scene, use_camera=True, force=True)
    assert report.view == "CAMERA"
    np.testing.assert_allclose(radiance(target), written[2][1], rtol=1e-3, atol=1e-3 * written[2][1].max())


def test_a_new_view_re_evaluates_the_radiance_without_new_cells(blender, addon):
    """A render of the frame the viewport solved: the radiance towards the camera comes from the last solve
    (no cells rebuilt, no sweeps), and equals a full solve towards the camera."""
    from translucency.ops import fluid_runtime, runtime, state

    cloud = point_cloud("Particles", blob())
    target = as_fluid(target_sphere(), source=cloud)
    sun()
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location = (0.3, -2.0, 1.0)
    camera.rotation_euler = (-camera.location).to_track_quat('-Z', 'Y').to_euler()  # looking at the fluid
    bpy.context.scene.collection.objects.link(camera)
    bpy.context.scene.camera = camera
    scene = bpy.context.scene
    scene.frame_set(1)
    st = state.fluid_state_of("Milk")
    assert st.solves == 1
    along_normals = radiance(target).copy()
    (report,) = runtime.solve_scene(scene, use_camera=True)
    assert not report.solved and report.view == "CAMERA" and st.solves == 1
    assert "radiance re-evaluated towards the camera" in report.describe()
    towards = radiance(target).copy()
    assert np.abs(towards - along_normals).max() > 1e-3 * along_normals.max()
    full = fluid_runtime.solve_fluid(target, scene, use_camera=True, force=True)
    assert full.solved and st.solves == 2
    np.testing.assert_allclose(radiance(target), towards, rtol=1e-6, atol=1e-9)


def test_slow_fluid_frames_are_left_to_the_live_check_during_playback(blender, addon, monkeypatch):
    """While the viewport plays, a fluid whose frames take longer than FLUID_LIVE_BUDGET is not solved in the
    frame-change handler (playback keeps its pace): the live check solves the frame shown, and the panel
    says what a frame costs."""
    from translucency.ops import live, state, status

    obj = as_fluid(point_cloud("Milk", blob()))
    sun()
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    st = state.fluid_state_of("Milk")
    st.seconds = 2.5  # as a 10k-particle frame on 2 cores
    monkeypatch.setattr(status, "playing", lambda: True)
    said = []
    monkeypatch.setattr(status, "status_bar", said.append)
    solves = st.solves
    set_points(obj.data, blob() + (0.05, 0.0, 0.0))
    bpy.context.scene.frame_set(2)
    assert st.solves == solves and st.deferred == 1 and live.pending()
    assert any("left to the live check" in line for line in status.fluid_lines(obj))
    assert said and said[-1].startswith("Translucency: a frame of the fluid 'Milk' takes 2.5 s")
    monkeypatch.setattr(status, "playing", lambda: False)
    monkeypatch.setattr(status, "FLUID_LIVE_BUDGET", 60.0)  # whatever the machine's load: this frame is fast
    live.flush()
    assert st.solves == solves + 1 and st.frame == 2
    assert said[-1] is None  # playback stopped and the frame was fast: the status bar is Blender's again
    monkeypatch.setattr(status, "FLUID_LIVE_BUDGET", 0.1)
    # Not playing (a frame step, a script, a render): solved at once, however slow.
    st.seconds = 2.5
    set_points(obj.data, blob())
    bpy.context.scene.frame_set(3)
    assert st.solves == solves + 2 and st.frame == 3


# --------------------------------------------------------------------------- bad input


def _solve_refused(obj, expect):
    """The Solve operator reports the error (bpy raises it as a RuntimeError in background mode)."""
    activate(obj)
    with pytest.raises(RuntimeError, match=re.escape(expect)):
        bpy.ops.translucency.solve()


def _panel_text(ui, obj):
    from translucency.ops import panels

    layout = ui.FakeLayout()
    panels.draw_translucency(layout, ui.draw_context(obj))
    return "".join(layout.labels())  # long messages are split over labels of 70 characters


@pytest.mark.parametrize("case", ["planar", "all_nan", "radius_zero", "radius_huge", "too_many", "deleted_source",
                                  "wrong_kind"])
def test_bad_input_is_refused_and_the_scene_is_unchanged(blender, addon, ui, monkeypatch, case):
    """Each refusal names the problem in the panel and the Info log, through the handlers and the Solve
    operator, and changes nothing in the scene (the last good radiance stays)."""
    from translucency.ops import fluid_runtime, live, state

    P = blob()
    cloud = point_cloud("Particles", P)
    target = as_fluid(target_sphere(), source=cloud)
    sun()
    activate(target)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    state.take_info()
    expect = {
        "planar": "lie in one plane",
        "all_nan": "have NaN or Inf positions: the particle data is broken",
        "radius_zero": "the particle Radius is 0: set it to about the spacing between particles (Auto Radius would",
        "radius_huge": "is larger than the whole fluid",
        "too_many": "GiB for their cells (budget",
        "deleted_source": "(the Source Object is empty, so 'Milk' itself was used; if it was set, its object was deleted)",
        "wrong_kind": "'Particles' has no particle system: choose the emitter",
    }[case]
    if case == "planar":
        set_points(cloud.data, P * (1.0, 1.0, 0.0))
    elif case == "all_nan":
        set_points(cloud.data, np.full_like(P, np.nan))
    elif case == "radius_zero":
        target.translucency.fluid_radius_auto = False
        target.translucency.fluid_radius = 0.0
    elif case == "radius_huge":
        target.translucency.fluid_radius_auto = False
        target.translucency.fluid_radius = 5.0
    elif case == "too_many":
        monkeypatch.setattr(fluid_runtime, "MEMORY_BUDGET", 100_000)
        set_points(cloud.data, P + 0.01)
    elif case == "deleted_source":
        bpy.data.objects.remove(cloud)  # the pointer empties itself; the target is then its own (wrong) source
    elif case == "wrong_kind":
        target.translucency.fluid_kind = 'PARTICLES'
    before = snapshot()
    bpy.context.scene.frame_set(2)  # the handler path
    live.flush()
    assert expect in state.solve_error("Milk"), state.solve_errors()
    if case == "radius_huge":  # one suggestion, in scene units, naming the panel's settings
        message = state.solve_error("Milk")
        assert "Auto Radius" in message and "suggest_radius" not in message and "object units" not in message
    assert snapshot() == before
    assert expect in _panel_text(ui, target)
    assert any(level == 'ERROR' and expect in message for level, message in state.queued_info())
    live._report_timer()  # what the timer does in the UI: the operator puts it in the Info log
    assert not state.has_info()
    _solve_refused(target, expect)  # the operator path
    assert snapshot() == before


@pytest.mark.parametrize("case", ["some_nan", "one_particle", "sparse"])
def test_degenerate_particles_give_zero_where_zero_is_right(blender, addon, ui, case):
    """NaN particles are left out, a single particle and isolated droplets get no radiance: said, never a crash."""
    from translucency.ops import state, status

    P = blob()
    if case == "some_nan":
        P[:3] = np.nan
        expect = f"3 of {len(P)} particles have NaN or Inf positions and were left out"
    elif case == "one_particle":
        P = P[:1]
        expect = "one particle: Auto Radius needs two or more"
    else:
        P = np.random.default_rng(1).uniform(-3.0, 3.0, (40, 3))
        expect = "40 of 40 particles have no neighbour within twice the radius"
    obj = as_fluid(point_cloud("Milk", P))
    if case == "sparse":
        obj.translucency.fluid_radius_auto = False
        obj.translucency.fluid_radius = 0.05
    sun()
    activate(obj)
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert state.solve_errors() == {}
    rgb = radiance(obj)
    assert rgb.shape == (len(P), 3) and np.isfinite(rgb).all()
    text = "\n".join(status.fluid_lines(obj) + list(state.fluid_state_of("Milk").warnings))
    assert expect in text
    assert expect in _panel_text(ui, obj)
    if case == "some_nan":
        assert not rgb[:3].any() and rgb[3:].max() > 0
    else:
        assert not rgb.any()


def test_no_particles_outside_the_cache_range_or_before_emission(blender, addon, ui):
    """Outside the particle cache's frames, and before the first particle is born, the fluid is not there:
    radiance 0, and the panel and the Info log say why, with the frame range."""
    from translucency.ops import live, state, status

    # Blender's cache of an emitter runs from the first emission frame to past the last one's lifetime.
    em = emitter(frame_start=2.5, frame_end=3, lifetime=2)
    target = as_fluid(target_sphere(), kind='PARTICLES', source=em)
    sun()
    scene = bpy.context.scene
    scene.frame_set(1)
    cache = em.particle_systems[0].point_cache
    first, last = cache.frame_start, cache.frame_end
    assert (first, last) == (2, 6)
    assert not radiance(target).any()
    assert ("no particles at frame 1: the cache of the particle system 'Particles' of 'Emitter' covers frames 2-6, and "
            "particles exist only there") in status.fluid_lines(target)[1]
    scene.frame_set(2)
    assert not radiance(target).any()
    assert ("no particle of the particle system 'Particles' of 'Emitter' is alive at frame 2 (it emits from frame 2.5 "
            "to 3, each particle living 2 frames)") in status.fluid_lines(target)[1]
    scene.frame_set(3)
    assert radiance(target).max() > 0 and state.fluid_state_of("Milk").empty == ""
    state.take_info()
    for frame in (4, 5, 6, 7):
        scene.frame_set(frame)
    live.flush()
    assert not radiance(target).any() and state.solve_errors() == {}
    message = ("no particles at frame 7: the cache of the particle system 'Particles' of 'Emitter' covers frames 2-6, "
               "and particles exist only there")
    assert message in status.fluid_lines(target)[1] and message in _panel_text(ui, target)
    assert any(level == 'WARNING' and "no particle" in text for level, text in state.queued_info())  # said once, not per frame


_MANTAFLOW_SCRIPT = textwrap.dedent(r"""
    import json, os, sys
    sys.path[:0] = [sys.argv[1] + "/tests", sys.argv[1]]
    import conftest
    addon = conftest.load_addon()
    import bpy
    conftest.factory_reset()
    addon.register()
    import test_ops_fluid as t
    from translucency.ops import state, status

    def domain(name, liquid):
        bpy.ops.mesh.primitive_cube_add(size=2.0)
        obj = bpy.context.object
        obj.name = name
        mod = obj.modifiers.new("Fluid", 'FLUID')
        mod.fluid_type = 'DOMAIN'
        if liquid:
            mod.domain_settings.domain_type = 'LIQUID'  # Blender adds the 'Liquid' FLIP particle system
        return obj

    out = {}
    liquid = domain("Domain", True)
    out["systems"] = [p.settings.type for p in liquid.particle_systems]
    target = t.as_fluid(t.target_sphere(), kind='MANTAFLOW', source=liquid)
    bpy.context.scene.frame_set(300)
    out["errors_300"] = state.solve_errors()
    out["lines_300"] = status.fluid_lines(target)
    out["radiance_300"] = float(abs(t.radiance(target)).max())
    target.translucency.fluid_object = domain("Smoke", False)
    bpy.context.scene.frame_set(301)
    out["errors_gas"] = state.solve_errors()
    print("RESULT " + json.dumps(out), flush=True)
    os._exit(0)  # Blender's Mantaflow aborts when a domain is freed in the bpy module ("some grids are still in use")
""")


def test_a_mantaflow_domain_that_cannot_give_particles_says_why(addon, tmp_path):
    """A liquid domain outside its cache's frames, and a gas domain.  Mantaflow does not simulate in the bpy
    module (its Python bindings fail headless, and freeing an evaluated domain aborts the process), so this
    runs in a process of its own, and the FLIP particles themselves are read by the particle-system path
    tested above."""
    script = tmp_path / "mantaflow.py"
    script.write_text(_MANTAFLOW_SCRIPT)
    proc = subprocess.run([sys.executable, str(script), str(ROOT)], capture_output=True, text=True, timeout=300,
                          cwd=tmp_path)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = json.loads(lines[-1][len("RESULT "):])
    assert out["systems"] == ["FLIP"] and out["errors_300"] == {} and out["radiance_300"] == 0.0
    assert ("no particles at frame 300: the cache of the FLIP particles of the liquid domain 'Domain' covers frames "
            "1-250") in out["lines_300"][1]
    assert "'Smoke' is a gas domain; a Fluid source needs a liquid domain" in out["errors_gas"]["Milk"]


def test_fluid_settings_are_saved_in_the_blend(blender, addon, tmp_path, ui):
    """Source, kind, object, particle system and radius survive a save and a reload; the panel draws them."""
    em = emitter()
    target = as_fluid(target_sphere(), kind='PARTICLES', source=em)
    s = target.translucency
    s.fluid_particle_system = "Particles"
    s.fluid_radius_auto = False
    s.fluid_radius = 0.07
    s.material_preset = 'WHOLEMILK'
    path = tmp_path / "settings.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    s = bpy.data.objects["Milk"].translucency
    assert (s.source, s.fluid_kind, s.fluid_object.name, s.fluid_particle_system) == \
        ('FLUID', 'PARTICLES', "Emitter", "Particles")
    assert (s.fluid_radius_auto, round(s.fluid_radius, 6), s.material_preset) == (False, 0.07, 'WHOLEMILK')
    from translucency.ops import panels

    layout = ui.FakeLayout()
    panels.draw_translucency(layout, ui.draw_context(bpy.data.objects["Milk"]))
    props = layout.props()
    for name in ("source", "fluid_kind", "fluid_object", "fluid_particle_system", "fluid_radius_auto", "fluid_radius",
                 "material_preset"):
        assert name in props
    assert "quality" not in props and "translucency.bake" not in layout.operators()  # no bake for a fluid
