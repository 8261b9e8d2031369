# SPDX-License-Identifier: GPL-3.0-or-later
"""The World as Cycles sees it, in Blender (ops/world.py): an HDRI world and a Sky Texture world solve in the
viewport path and in F12 through Cycles with the Translucency pass, without a fallback warning; the HDRI's sun
becomes a directional light and the panel says so; a Mapping rotation turns it; the Sky Texture's bake puts
the sun where the node's angles say; bad input (an image that did not load, no World Output) falls back with
a message and leaves the file as it was."""

from __future__ import annotations

import math
from pathlib import Path

import bpy
import numpy as np
import pytest

from test_render_pass import (  # noqa: F401  (render_pass is a fixture)
    ATTRIBUTE, lit_sides, radiance_of, render_exr, render_pass, sphere_scene)
from tools.exr import exr_pass

HDRI = Path(__file__).resolve().parent / "data" / "sun_sky_cc0.exr"


def hdri_world(rotation_deg=(0.0, 0.0, 0.0), path=HDRI, backdrop=True):
    """Texture Coordinate -> Mapping (Euler rotation) -> Environment Texture -> Background, mixed by Light Path's
    Is Camera Ray with a grey backdrop the camera sees (the object is lit by the HDRI)."""
    from translucency.ops.compat import ensure_node_tree

    world = bpy.data.worlds.new("HDRI")
    tree = ensure_node_tree(world)
    tree.nodes.clear()
    n = tree.nodes
    coord, mapping = n.new("ShaderNodeTexCoord"), n.new("ShaderNodeMapping")
    env = n.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(str(path), check_existing=True)
    bg, out = n.new("ShaderNodeBackground"), n.new("ShaderNodeOutputWorld")
    mapping.inputs["Rotation"].default_value = tuple(math.radians(a) for a in rotation_deg)
    tree.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
    tree.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    if backdrop:
        path_node, grey, mix = n.new("ShaderNodeLightPath"), n.new("ShaderNodeBackground"), n.new("ShaderNodeMixShader")
        grey.inputs["Color"].default_value = (0.05, 0.05, 0.05, 1.0)
        tree.links.new(path_node.outputs["Is Camera Ray"], mix.inputs["Fac"])
        tree.links.new(bg.outputs[0], mix.inputs[1])
        tree.links.new(grey.outputs[0], mix.inputs[2])
        tree.links.new(mix.outputs[0], out.inputs["Surface"])
    else:
        tree.links.new(bg.outputs[0], out.inputs["Surface"])
    return world


def sky_world(elevation=30.0, rotation=60.0):
    from translucency.ops.compat import ensure_node_tree

    world = bpy.data.worlds.new("Sky")
    tree = ensure_node_tree(world)
    sky = tree.nodes.new("ShaderNodeTexSky")
    sky.sun_elevation, sky.sun_rotation = math.radians(elevation), math.radians(rotation)
    bg = next(node for node in tree.nodes if node.type == 'BACKGROUND')
    bg.inputs["Strength"].default_value = 0.05
    tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
    return world


def world_sphere(world):
    """The render-pass test's sphere (100 mm of marble, camera above), lit by ``world`` only, baked and solved."""
    obj = sphere_scene()
    scene = bpy.context.scene
    scene.unit_settings.scale_length = 0.05
    obj.data.attributes.remove(obj.data.attributes[ATTRIBUTE])
    obj.translucency.enabled = True
    obj.translucency.quality = 'DRAFT'
    scene.world = world
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.translucency.bake() == {'FINISHED'}, obj.translucency.status.bake_status
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    return obj


def no_world_warning(obj):
    from translucency.ops import state

    st = state.get_state(obj)
    warnings = [w for w in st.warnings if "world" in w.lower()]
    assert warnings == [], warnings


def test_hdri_world_solves_in_the_viewport_and_f12_with_its_sun_as_a_light(render_pass, tmp_path):
    from tools.make_hdri import SUN_IRRADIANCE, sun_direction
    from translucency.ops import scene_inputs, world

    world.clear_cache()
    w = hdri_world()
    env, warning, suns = scene_inputs.world_environment(w)
    assert warning is None and env is not None and env.sh.shape == (9, 3)
    (sun,) = suns
    assert sun.kind == "sun"
    assert math.degrees(math.acos(-np.dot(sun.unit_direction, sun_direction()))) < 0.2
    E = float(np.dot(sun.rgb, [0.2126, 0.7152, 0.0722]))
    assert E == pytest.approx(SUN_IRRADIANCE, rel=0.05)  # the generated disk's irradiance, to pixelisation
    line = world.status_line()
    assert line.startswith("World: HDRI 'sun_sky_cc0.exr' projected to SH order 2; its sun (") and \
        "became a directional light" in line, line

    obj = world_sphere(w)  # the viewport path (Solve)
    no_world_warning(obj)
    from translucency.ops import status

    assert status.world_line(obj) == (line, False)  # what the panel shows under Solve
    L = radiance_of(obj)
    assert np.isfinite(L).all() and L.max() > 0
    bpy.ops.translucency.add_to_material()
    path = render_exr(render_pass, tmp_path / "hdri.exr", 'CYCLES')
    right, left = lit_sides(exr_pass(path, "Translucency"))  # the sun is at +x (azimuth 30, elevation 35)
    assert right > 1.5 * left, (right, left)
    no_world_warning(obj)


def test_mapping_rotation_turns_the_hdri_sun_and_the_sh(blender):
    from tools.make_hdri import sun_direction
    from translucency.ops import scene_inputs, world
    from translucency.translucency_addon.scene.environment_map import rotate_sh
    from translucency.translucency_addon.scene.world_nodes import euler_matrix

    world.clear_cache()
    rot = (40.0, 0.0, 90.0)  # a tilt too: the sky without its sun is symmetric about Z
    env0, _, (sun0,) = scene_inputs.world_environment(hdri_world(backdrop=False))
    env1, warning, (sun1,) = scene_inputs.world_environment(hdri_world(rot, backdrop=False))
    assert warning is None
    R = euler_matrix(tuple(math.radians(a) for a in rot))
    # POINT mapping looks the image up at R d: the world turns by R^T
    expected = R.T @ sun_direction()
    assert math.degrees(math.acos(-np.dot(sun1.unit_direction, expected))) < 0.3
    scale = np.abs(env0.sh).max()
    assert np.abs(env1.sh - rotate_sh(env0.sh, R)).max() < 0.02 * scale
    assert np.abs(env1.sh - env0.sh).max() > 0.2 * scale  # it did turn


def test_the_world_is_evaluated_once_per_change(blender):
    from translucency.ops import world

    world.clear_cache()
    w = hdri_world(backdrop=False)
    first = world.evaluate_world(w)
    assert world.evaluate_world(w) is first  # the next frame: no pixels read, nothing projected
    w.node_tree.nodes["Background"].inputs["Strength"].default_value = 2.0
    second = world.evaluate_world(w)
    assert second is not first
    np.testing.assert_allclose(second.sh, 2.0 * first.sh, rtol=1e-6)
    assert second.sun.irradiance == pytest.approx(tuple(2.0 * x for x in first.sun.irradiance), rel=1e-6)


def test_sky_texture_world_is_baked_by_cycles_and_solves_in_f12(render_pass, tmp_path):
    from translucency.ops import scene_inputs, world

    world.clear_cache()
    w = sky_world(elevation=30.0, rotation=60.0)
    before = {k: len(getattr(bpy.data, k)) for k in ("scenes", "worlds", "images", "objects", "cameras")}
    env, warning, (sun,) = scene_inputs.world_environment(w)
    assert warning is None
    assert {k: len(getattr(bpy.data, k)) for k in before} == before, "the sky bake left something behind"
    el, rot = math.radians(30.0), math.radians(60.0)
    node_sun = np.array([math.sin(rot) * math.cos(el), math.cos(rot) * math.cos(el), math.sin(el)])
    # Blender's own sun angles (Cycles' sky_spherical_coordinates) against the sun found in the bake: this
    # checks the equirectangular camera's orientation in ops.world.bake_sky
    assert math.degrees(math.acos(-np.dot(sun.unit_direction, node_sun))) < 0.2
    assert "Sky Texture 'Sky Texture' (Multiple Scattering, baked by Cycles)" in world.status_line()

    obj = world_sphere(w)
    no_world_warning(obj)
    bpy.ops.translucency.add_to_material()
    path = render_exr(render_pass, tmp_path / "sky.exr", 'CYCLES')
    right, left = lit_sides(exr_pass(path, "Translucency"))  # the sun at x = sin 60 > 0
    assert right > 1.2 * left, (right, left)
    no_world_warning(obj)

    # A sky met first inside a render (a render depsgraph or thread: frame.gather says can_render=False)
    # cannot be baked there: it falls back, says why, and creates nothing
    world.clear_cache()
    w.node_tree.nodes["Sky Texture"].sun_elevation = math.radians(31.0)
    before = {k: len(getattr(bpy.data, k)) for k in before}
    env, warning, suns = scene_inputs.world_environment(w, None, can_render=False)
    assert "viewport colour" in warning and "inside another render" in warning and suns == (), warning
    assert {k: len(getattr(bpy.data, k)) for k in before} == before


def test_bad_worlds_fall_back_with_a_message_and_write_nothing(blender, tmp_path):
    from translucency.ops import scene_inputs, world

    world.clear_cache()
    missing = tmp_path / "gone.exr"
    missing.write_bytes(HDRI.read_bytes())
    w = hdri_world(path=missing)
    missing.unlink()
    w.node_tree.nodes["Environment Texture"].image.reload()
    w.color = (0.1, 0.2, 0.3)
    counts = {k: len(getattr(bpy.data, k)) for k in ("images", "worlds", "scenes")}
    env, warning, suns = scene_inputs.world_environment(w)
    assert "did not load" in warning and "gone.exr" in warning and "Find Missing Files" in warning, warning
    assert suns == () and env.radiance == pytest.approx((0.1, 0.2, 0.3)) and env.sh is None
    assert {k: len(getattr(bpy.data, k)) for k in counts} == counts
    assert not missing.exists()

    w2 = hdri_world()
    for node in [n for n in w2.node_tree.nodes if n.type == 'OUTPUT_WORLD']:
        w2.node_tree.nodes.remove(node)
    w2.color = (0.4, 0.4, 0.4)
    env, warning, suns = scene_inputs.world_environment(w2)
    assert "no World Output node" in warning and env.radiance == pytest.approx((0.4, 0.4, 0.4)), warning
