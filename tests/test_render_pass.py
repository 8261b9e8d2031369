# SPDX-License-Identifier: GPL-3.0-or-later
"""Render pass (ops/render_pass.py): the "Add to material" operators, the
Translucency AOV in Cycles and EEVEE renders saved as multilayer OpenEXR, and
the EXR reader that reads it back."""

from __future__ import annotations

import math

import bpy
import numpy as np
import pytest

from tools.exr import exr_pass, read_exr

ATTRIBUTE = "translucency_radiance"
SIZE = 32
ROLE = "translucency_role"


@pytest.fixture
def render_pass(blender, addon):
    """ops.render_pass, registered (by the add-on when ops/__init__.py lists it, else here)."""
    from translucency.ops import render_pass as module

    own = module not in addon.ops.MODULES
    if own:
        for cls in module.CLASSES:
            bpy.utils.register_class(cls)
    try:
        yield module
    finally:
        if own:
            for cls in reversed(module.CLASSES):
                if cls.is_registered:
                    bpy.utils.unregister_class(cls)


# --- scene helpers -------------------------------------------------------------------------

def write_radiance(obj, func, name=ATTRIBUTE):
    mesh = obj.data
    n = len(mesh.vertices)
    co = np.empty(n * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    rgba = np.ones((n, 4), np.float32)
    rgba[:, :3] = func(co.reshape(n, 3))
    attr = mesh.color_attributes.get(name) or mesh.color_attributes.new(name, 'FLOAT_COLOR', 'POINT')
    attr.data.foreach_set("color", rgba.ravel())
    mesh.update()


def lit_from_plus_x(co):
    """Radiance brighter on the +x side (what a light at +x gives)."""
    t = 0.5 * (1.0 + co[:, 0])
    return np.stack([0.8 * t, 0.6 * t, 0.4 * t], 1)


def sphere_scene(material=True):
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, segments=32, ring_count=16)
    obj = bpy.context.object
    bpy.ops.object.shade_smooth()
    if material:
        mat = bpy.data.materials.new("Sphere Material")
        from translucency.ops.compat import ensure_node_tree

        ensure_node_tree(mat)
        obj.data.materials.append(mat)
    write_radiance(obj, lit_from_plus_x)
    scene = bpy.context.scene
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.lens_unit = 'FOV'
    camera.data.angle = math.radians(40.0)
    camera.location = (0.0, 0.0, 5.0)  # looks down -z at the sphere
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.resolution_x = scene.render.resolution_y = SIZE
    scene.render.resolution_percentage = 100
    return obj


def masks(margin_px=2.0):
    """(inside, outside) pixel masks of the unit sphere seen by the camera above, top row first."""
    r_px = math.tan(math.asin(1.0 / 5.0)) / math.tan(math.radians(20.0)) * SIZE / 2.0
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d = np.hypot(xx - SIZE / 2.0, yy - SIZE / 2.0)
    return d < r_px - margin_px, d > r_px + margin_px


def render_exr(render_pass, path, engine, samples=4):
    scene = bpy.context.scene
    scene.render.engine = engine
    if engine == 'CYCLES':
        scene.cycles.device = 'CPU'
        scene.cycles.samples = samples
        scene.cycles.use_denoising = False
    else:
        scene.eevee.taa_render_samples = samples
    render_pass.configure_output(scene.render.image_settings, 'OPEN_EXR_MULTILAYER')
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    assert path.exists(), f"{engine} wrote no {path}"
    return path


def check_pass(translucency):
    """Non-zero on the object, zero off it, brighter on the lit (+x, right) side."""
    inside, outside = masks()
    rgb = translucency[..., :3]
    assert np.isfinite(rgb).all()
    assert np.all(rgb[inside].max(axis=1) > 0.0), "the pass is black somewhere on the object"
    assert np.all(rgb[outside] == 0.0), "the pass is not zero off the object"
    right = inside.copy()
    right[:, :SIZE // 2] = False
    left = inside.copy()
    left[:, SIZE // 2:] = False
    assert rgb[right].mean() > 1.5 * rgb[left].mean(), "the lit side is not brighter"
    # The pass holds the attribute itself: the centre of the image is x ~ 0, L ~ (0.4, 0.3, 0.2).
    centre = rgb[SIZE // 2 - 1:SIZE // 2 + 1, SIZE // 2 - 1:SIZE // 2 + 1].mean(axis=(0, 1))
    np.testing.assert_allclose(centre, [0.4, 0.3, 0.2], atol=0.06)


def nodes_by_role(material):
    roles = {}
    for node in material.node_tree.nodes:
        role = node.get(ROLE)
        if role:
            roles.setdefault(role, []).append(node)
    return roles


def surface_source(material):
    output = material.node_tree.get_output_node('ALL')
    links = output.inputs["Surface"].links
    return links[0].from_node if links else None


# --- operators ------------------------------------------------------------------------------

def test_operators_are_undoable(render_pass):
    for cls in render_pass.CLASSES:
        assert 'UNDO' in cls.bl_options and 'REGISTER' in cls.bl_options, cls
    assert bpy.ops.translucency.add_to_material.get_rna_type().identifier == "TRANSLUCENCY_OT_add_to_material"
    assert bpy.ops.translucency.remove_from_material.get_rna_type()


def test_add_to_material_wires_attribute_to_aov_and_is_idempotent(render_pass):
    obj = sphere_scene()
    material = obj.active_material
    before = {node.name for node in material.node_tree.nodes}
    assert bpy.ops.translucency.add_to_material() == {'FINISHED'}
    assert bpy.ops.translucency.add_to_material() == {'FINISHED'}
    roles = nodes_by_role(material)
    assert sorted(roles) == ["aov", "attribute"]
    assert len(roles["aov"]) == len(roles["attribute"]) == 1
    attr, aov = roles["attribute"][0], roles["aov"][0]
    assert attr.attribute_name == ATTRIBUTE and attr.attribute_type == 'GEOMETRY'
    assert aov.aov_name == "Translucency"
    assert aov.inputs["Color"].links[0].from_node == attr
    assert len(material.node_tree.links) == 1 + 1  # Principled -> Output, Attribute -> AOV
    assert {node.name for node in material.node_tree.nodes} - before == {attr.name, aov.name}
    aovs = [a for a in bpy.context.view_layer.aovs if a.name == "Translucency"]
    assert len(aovs) == 1 and aovs[0].type == 'COLOR'
    assert surface_source(material).type == 'BSDF_PRINCIPLED'  # beauty untouched by default


def test_add_to_material_creates_a_material_when_there_is_none(render_pass):
    obj = sphere_scene(material=False)
    assert len(obj.material_slots) == 0
    bpy.ops.translucency.add_to_material()
    assert len(obj.material_slots) == 1
    assert sorted(nodes_by_role(obj.active_material)) == ["aov", "attribute"]
    bpy.ops.translucency.add_to_material()
    assert len(obj.material_slots) == 1 and len(bpy.data.materials) == 1


def test_every_material_of_the_object_gets_the_pass(render_pass):
    obj = sphere_scene()
    second = bpy.data.materials.new("Second")
    obj.data.materials.append(second)
    obj.data.materials.append(second)  # shared slot: handled once
    bpy.ops.translucency.add_to_material()
    for material in (obj.data.materials[0], second):
        roles = nodes_by_role(material)
        assert len(roles["aov"]) == 1 and len(roles["attribute"]) == 1


def test_emission_option_adds_to_the_surface_and_is_reversible(render_pass):
    obj = sphere_scene()
    material = obj.active_material
    bpy.ops.translucency.add_to_material(use_emission=True, emission_strength=2.0)
    bpy.ops.translucency.add_to_material(use_emission=True, emission_strength=2.0)
    roles = nodes_by_role(material)
    assert len(roles["emission"]) == 1 and len(roles["add_shader"]) == 1
    add = roles["add_shader"][0]
    assert surface_source(material) == add
    assert add.inputs[0].links[0].from_node.type == 'BSDF_PRINCIPLED'
    assert add.inputs[1].links[0].from_node == roles["emission"][0]
    assert roles["emission"][0].inputs["Color"].links[0].from_node == roles["attribute"][0]
    assert roles["emission"][0].inputs["Strength"].default_value == 2.0
    # Emission off again: the original surface link comes back.
    bpy.ops.translucency.add_to_material(use_emission=False)
    assert sorted(nodes_by_role(material)) == ["aov", "attribute"]
    assert surface_source(material).type == 'BSDF_PRINCIPLED'


def test_remove_from_material_restores_the_material_and_the_view_layer(render_pass):
    obj = sphere_scene()
    material = obj.active_material
    names = sorted(node.name for node in material.node_tree.nodes)
    bpy.ops.translucency.add_to_material(use_emission=True)
    assert bpy.ops.translucency.remove_from_material() == {'FINISHED'}
    assert sorted(node.name for node in material.node_tree.nodes) == names
    assert surface_source(material).type == 'BSDF_PRINCIPLED'
    assert not any(a.name == "Translucency" for a in bpy.context.view_layer.aovs)


def test_aov_stays_while_another_material_uses_it(render_pass):
    a = sphere_scene()
    bpy.ops.mesh.primitive_cube_add(location=(3, 0, 0))
    b = bpy.context.object
    b.data.materials.append(bpy.data.materials.new("Cube Material"))
    bpy.ops.translucency.add_to_material()
    bpy.context.view_layer.objects.active = a
    bpy.ops.translucency.add_to_material()
    bpy.ops.translucency.remove_from_material()
    assert any(x.name == "Translucency" for x in bpy.context.view_layer.aovs)
    bpy.context.view_layer.objects.active = b
    bpy.ops.translucency.remove_from_material()
    assert not any(x.name == "Translucency" for x in bpy.context.view_layer.aovs)


def test_single_scattering_aov_when_the_attribute_exists(render_pass):
    obj = sphere_scene()
    bpy.ops.translucency.add_to_material()
    assert "ss_aov" not in nodes_by_role(obj.active_material)
    write_radiance(obj, lambda co: np.full_like(co, 0.1), name="translucency_radiance_ss")
    bpy.ops.translucency.add_to_material()
    roles = nodes_by_role(obj.active_material)
    assert roles["ss_aov"][0].aov_name == "Translucency_SS"
    assert roles["ss_attribute"][0].attribute_name == "translucency_radiance_ss"
    assert {a.name for a in bpy.context.view_layer.aovs} >= {"Translucency", "Translucency_SS"}
    bpy.ops.translucency.add_to_material(use_single_scattering=False)
    assert "ss_aov" not in nodes_by_role(obj.active_material)
    assert not any(a.name == "Translucency_SS" for a in bpy.context.view_layer.aovs)


def test_aovs_on_every_view_layer(render_pass):
    sphere_scene()
    scene = bpy.context.scene
    scene.view_layers.new("Second")
    bpy.ops.translucency.add_to_material()
    for view_layer in scene.view_layers:
        assert [a.name for a in view_layer.aovs].count("Translucency") == 1, view_layer.name


def test_draw_settings(render_pass, ui):
    obj = sphere_scene()
    layout = ui.FakeLayout()
    render_pass.draw_settings(layout, ui.draw_context(obj))
    assert layout.operators() == ["translucency.add_to_material", "translucency.remove_from_material"]
    bpy.ops.translucency.add_to_material()
    layout = ui.FakeLayout()
    render_pass.draw_settings(layout, ui.draw_context(obj))
    assert any("1 of 1" in text for text in layout.labels())
    layout = ui.FakeLayout()
    render_pass.draw_settings(layout, ui.draw_context(None))
    assert layout.operators() == []


def test_eevee_engine_id(render_pass):
    engine = render_pass.eevee_engine_id()
    assert engine == ('BLENDER_EEVEE' if bpy.app.version >= (5, 0, 0) else 'BLENDER_EEVEE_NEXT')
    bpy.context.scene.render.engine = engine  # refused if the id is wrong
    assert bpy.context.scene.render.engine == engine


# --- renders ------------------------------------------------------------------------------------

def test_cycles_renders_the_translucency_pass(render_pass, tmp_path):
    obj = sphere_scene()
    # A second object with the same material but no radiance attribute, in a corner of
    # the frame (outside the sphere's mask): it must write zero into the pass.
    bpy.ops.mesh.primitive_cube_add(size=0.4, location=(1.3, 1.3, 0.0))
    bpy.context.object.data.materials.append(obj.active_material)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.translucency.add_to_material()
    path = render_exr(render_pass, tmp_path / "cycles.exr", 'CYCLES')
    check_pass(exr_pass(path, "Translucency"))
    alpha = exr_pass(path, "Combined")[..., 3]
    assert alpha[:SIZE // 4, -SIZE // 4:].max() > 0.9, "the cube is in the frame (top right)"


def test_cycles_emission_option_brightens_the_beauty_pass(render_pass, tmp_path):
    sphere_scene()
    bpy.ops.translucency.add_to_material()
    plain = exr_pass(render_exr(render_pass, tmp_path / "plain.exr", 'CYCLES'), "Combined")
    bpy.ops.translucency.add_to_material(use_emission=True)
    lit = exr_pass(render_exr(render_pass, tmp_path / "emission.exr", 'CYCLES'), "Combined")
    inside, _ = masks()
    # No lights and no world: without emission the sphere is black, with it the radiance shows.
    assert plain[inside][:, :3].max() < 1e-3
    assert lit[inside][:, :3].mean() > 0.1


@pytest.mark.gpu
def test_eevee_renders_the_translucency_pass(render_pass, tmp_path):
    sphere_scene()
    bpy.ops.translucency.add_to_material()
    path = render_exr(render_pass, tmp_path / "eevee.exr", render_pass.eevee_engine_id(), samples=1)
    check_pass(exr_pass(path, "Translucency"))


# --- the EXR reader -----------------------------------------------------------------------------

@pytest.fixture
def cycles_codecs(render_pass, tmp_path):
    sphere_scene()
    bpy.ops.translucency.add_to_material()
    scene = bpy.context.scene
    out = {}
    for codec in ('ZIP', 'ZIPS', 'RLE', 'NONE'):
        scene.render.engine = 'CYCLES'
        scene.cycles.samples = 2
        scene.cycles.seed = 0
        render_pass.configure_output(scene.render.image_settings, 'OPEN_EXR_MULTILAYER', codec=codec)
        scene.render.filepath = str(tmp_path / f"{codec}.exr")
        bpy.ops.render.render(write_still=True)
        out[codec] = tmp_path / f"{codec}.exr"
    return out


def test_exr_reader_agrees_across_codecs(render_pass, cycles_codecs):
    reference = read_exr(cycles_codecs['NONE'])
    assert {"ViewLayer.Translucency.R", "ViewLayer.Combined.A"} <= set(reference)
    for codec, path in cycles_codecs.items():
        channels = read_exr(path)
        assert set(channels) == set(reference), codec
        for name in reference:
            np.testing.assert_array_equal(channels[name], reference[name], err_msg=f"{codec} {name}")


def test_exr_reader_agrees_with_mitsuba(render_pass, cycles_codecs):
    """Mitsuba's Bitmap reads the first part of the file (the Combined pass)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant('scalar_rgb')
    bitmap = mi.Bitmap(str(cycles_codecs['ZIP']))
    theirs = np.array(bitmap, np.float32)
    ours = exr_pass(cycles_codecs['ZIP'], "Combined")
    assert theirs.shape == ours.shape
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-6)


def test_exr_reader_rejects_what_it_cannot_read(render_pass, tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(ValueError):
        read_exr(bad)


# --- integration with the real bake, solve and frame handlers ---------------------------------

def baked_sphere_scene():
    """The render scene above, with the sphere baked and solved through the add-on's operators.

    One unit is 50 mm (unit scale 0.05), so the sphere is 100 mm of marble; a point
    light keyed at +x on frame 1 and at -x on frame 10.
    """
    obj = sphere_scene()
    scene = bpy.context.scene
    scene.unit_settings.scale_length = 0.05
    obj.data.attributes.remove(obj.data.attributes[ATTRIBUTE])  # the solve writes it
    obj.translucency.enabled = True
    obj.translucency.quality = 'DRAFT'
    light = bpy.data.objects.new("Light", bpy.data.lights.new("Light", 'POINT'))
    light.data.energy = 1000.0
    scene.collection.objects.link(light)
    for frame, x in ((1, 3.0), (10, -3.0)):
        light.location = (x, 0.0, 1.0)
        light.keyframe_insert("location", frame=frame)
    scene.frame_set(1)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.translucency.bake() == {'FINISHED'}, obj.translucency.status.bake_status
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    return obj


def radiance_of(obj):
    attr = obj.data.attributes[ATTRIBUTE]
    buf = np.empty(len(attr.data) * 4, np.float32)
    attr.data.foreach_get("color", buf)
    return buf.reshape(-1, 4)[:, :3]


def lit_sides(translucency):
    inside, outside = masks()
    rgb = translucency[..., :3]
    assert np.isfinite(rgb).all()
    assert np.all(rgb[inside].max(axis=1) > 0.0), "the pass is black somewhere on the object"
    assert np.all(rgb[outside] == 0.0), "the pass is not zero off the object"
    right = inside.copy()
    right[:, :SIZE // 2] = False
    left = inside.copy()
    left[:, SIZE // 2:] = False
    return rgb[right].mean(), rgb[left].mean()


def test_solve_then_cycles_pass_follows_the_animated_light(render_pass, tmp_path):
    obj = baked_sphere_scene()
    L = radiance_of(obj)
    assert L.shape == (len(obj.data.vertices), 3) and np.isfinite(L).all() and L.max() > 0
    bpy.ops.translucency.add_to_material()
    scene = bpy.context.scene
    passes = {}
    for frame in (1, 10):
        scene.frame_set(frame)  # the add-on's frame handlers re-solve for the moved light
        path = render_exr(render_pass, tmp_path / f"frame_{frame}.exr", 'CYCLES')
        passes[frame] = exr_pass(path, "Translucency")
    right, left = lit_sides(passes[1])
    assert right > 2.0 * left, f"frame 1: light at +x, right {right} left {left}"
    right, left = lit_sides(passes[10])
    assert left > 2.0 * right, f"frame 10: light at -x, right {right} left {left}"
    assert not np.allclose(passes[1], passes[10])


@pytest.mark.gpu
def test_solve_then_eevee_pass_is_brighter_on_the_lit_side(render_pass, tmp_path):
    baked_sphere_scene()
    bpy.ops.translucency.add_to_material()
    path = render_exr(render_pass, tmp_path / "eevee.exr", render_pass.eevee_engine_id(), samples=1)
    right, left = lit_sides(exr_pass(path, "Translucency"))
    assert right > 2.0 * left
