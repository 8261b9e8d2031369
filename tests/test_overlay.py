# SPDX-License-Identifier: GPL-3.0-or-later
"""Viewport overlay (ops/overlay.py): handlers, panel rows, and the draw
function rendered into an off-screen buffer with a given view/projection."""

from __future__ import annotations

import math

import bpy
import numpy as np
import pytest
from mathutils import Matrix

from conftest import factory_reset

ATTRIBUTE = "translucency_radiance"
SIZE = 64
BACKGROUND = (0.25, 0.25, 0.25, 1.0)


# --- helpers ---------------------------------------------------------------------------

@pytest.fixture
def overlay(blender, addon):
    """ops.overlay, registered (by the add-on when ops/__init__.py lists it, else here)."""
    from translucency.ops import overlay as module

    own = module not in addon.ops.MODULES
    if own:
        for cls in module.CLASSES:
            bpy.utils.register_class(cls)
        module.on_register()
    try:
        yield module
    finally:
        if own and module.TranslucencyDisplaySettings.is_registered:
            module.on_unregister()
            for cls in reversed(module.CLASSES):
                bpy.utils.unregister_class(cls)


def perspective(fov_deg=40.0, aspect=1.0, near=0.1, far=100.0) -> Matrix:
    t = math.tan(math.radians(fov_deg) / 2.0)
    return Matrix((
        (1.0 / (aspect * t), 0.0, 0.0, 0.0),
        (0.0, 1.0 / t, 0.0, 0.0),
        (0.0, 0.0, (far + near) / (near - far), 2.0 * far * near / (near - far)),
        (0.0, 0.0, -1.0, 0.0),
    ))


VIEW = Matrix.Translation((0.0, 0.0, -5.0))  # camera at z = 5 looking down -z
PROJECTION = perspective()


def radiance_sphere(name="Sphere", location=(0.0, 0.0, 0.0), enabled=True):
    """UV sphere (radius 1) whose radiance grows with object-space x: brighter on +x."""
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, location=location, segments=48, ring_count=24)
    obj = bpy.context.object
    obj.name = name
    obj.translucency.enabled = enabled
    write_radiance(obj, lambda co: np.stack([0.4 * (1 + co[:, 0]), 0.3 * (1 + co[:, 0]), 0.2 * (1 + co[:, 0])], 1))
    return obj


def write_radiance(obj, func):
    mesh = obj.data
    n = len(mesh.vertices)
    co = np.empty(n * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    rgb = func(co.reshape(n, 3))
    rgba = np.ones((n, 4), np.float32)
    rgba[:, :3] = rgb
    attr = mesh.color_attributes.get(ATTRIBUTE) or mesh.color_attributes.new(ATTRIBUTE, 'FLOAT_COLOR', 'POINT')
    attr.data.foreach_set("color", rgba.ravel())
    mesh.update()


def exact_display(scene):
    d = scene.translucency_display
    d.auto_exposure = False
    d.exposure = 0.0
    d.tone_map = 'CLAMP'


def render(draw, background=(0.0, 0.0, 0.0, 0.0), before=None):
    """Bind an off-screen buffer, clear it, call ``draw()``, return RGBA floats (rows bottom-up)."""
    import gpu

    offscreen = gpu.types.GPUOffScreen(SIZE, SIZE, format='RGBA32F')
    try:
        with offscreen.bind():
            fb = gpu.state.active_framebuffer_get()
            fb.clear(color=background, depth=1.0)
            with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
                gpu.matrix.load_matrix(VIEW)
                gpu.matrix.load_projection_matrix(PROJECTION)
                if before is not None:
                    before()
                result = draw()
            pixels = np.array(fb.read_color(0, 0, SIZE, SIZE, 4, 0, 'FLOAT').to_list(), np.float32)
    finally:
        offscreen.free()
    return pixels.reshape(SIZE, SIZE, 4), result


def draw_with(overlay, mode):
    def draw():
        dg = bpy.context.evaluated_depsgraph_get()
        return overlay.draw_overlay(dg, bpy.context.scene, mode=mode)
    return draw


def object_mask(radius_px_margin=1.5):
    """Pixels well inside / well outside the unit sphere's silhouette for VIEW/PROJECTION."""
    t = math.tan(math.radians(20.0))
    # Silhouette of a unit sphere seen from distance 5: angular radius asin(1/5).
    r_ndc = math.tan(math.asin(1.0 / 5.0)) / t
    r_px = r_ndc * SIZE / 2.0
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d = np.hypot(xx - SIZE / 2.0, yy - SIZE / 2.0)
    return d < r_px - radius_px_margin, d > r_px + radius_px_margin


# --- registration (no GPU needed) ----------------------------------------------------------

def _count(handlers, func):
    return sum(1 for h in handlers if getattr(h, "__name__", None) == func.__name__
               and getattr(h, "__module__", None) == func.__module__)


def test_register_adds_one_draw_handler_and_load_handlers(overlay):
    assert overlay.draw_handler_active()
    assert _count(bpy.app.handlers.load_pre, overlay._on_load_pre) == 1
    assert _count(bpy.app.handlers.load_post, overlay._on_load_post) == 1
    handle = overlay._handle
    overlay.on_register()  # again: nothing is duplicated
    overlay.add_draw_handler()
    assert overlay._handle is handle
    assert _count(bpy.app.handlers.load_pre, overlay._on_load_pre) == 1
    assert _count(bpy.app.handlers.load_post, overlay._on_load_post) == 1
    assert "translucency_display" in bpy.types.Scene.bl_rna.properties


def test_unregister_removes_every_handler(overlay):
    handle = overlay._handle
    overlay.on_unregister()
    try:
        assert not overlay.draw_handler_active()
        assert _count(bpy.app.handlers.load_pre, overlay._on_load_pre) == 0
        assert _count(bpy.app.handlers.load_post, overlay._on_load_post) == 0
        assert "translucency_display" not in bpy.types.Scene.bl_rna.properties
        # The old handle is really gone from the View-3D space type.
        with pytest.raises(ValueError):
            bpy.types.SpaceView3D.draw_handler_remove(handle, 'WINDOW')
    finally:
        overlay.on_register()  # the fixture unregisters it again


def test_addon_unregister_removes_the_overlay(overlay, addon):
    assert overlay in addon.ops.MODULES, "ops/__init__.py must list ops.overlay"
    handle = overlay._handle
    addon.unregister()
    assert not overlay.draw_handler_active()
    assert _count(bpy.app.handlers.load_post, overlay._on_load_post) == 0
    with pytest.raises(ValueError):
        bpy.types.SpaceView3D.draw_handler_remove(handle, 'WINDOW')
    addon.register()


def test_file_load_replaces_the_draw_handler(overlay, tmp_path):
    bpy.ops.mesh.primitive_cube_add()
    path = str(tmp_path / "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    overlay._cache["stale"] = object()
    old = overlay._handle
    bpy.ops.wm.open_mainfile(filepath=path)
    # load_pre removed the old handler and cleared the cache, load_post added a new one.
    assert overlay.draw_handler_active()
    assert overlay._handle is not old
    assert "stale" not in overlay._cache
    with pytest.raises(ValueError):
        bpy.types.SpaceView3D.draw_handler_remove(old, 'WINDOW')
    factory_reset()  # also a file load
    assert overlay.draw_handler_active()
    assert _count(bpy.app.handlers.load_post, overlay._on_load_post) == 1


def test_draw_settings(overlay, ui):
    bpy.ops.mesh.primitive_cube_add()
    layout = ui.FakeLayout()
    overlay.draw_settings(layout, ui.draw_context(bpy.context.object))
    assert {"overlay_enabled", "overlay_mode", "exposure", "auto_exposure", "tone_map"} <= set(layout.props())
    assert any("No solved radiance" in text for text in layout.labels())
    write_radiance(bpy.context.object, lambda co: np.ones_like(co))
    layout = ui.FakeLayout()
    overlay.draw_settings(layout, ui.draw_context(bpy.context.object))
    assert not any("No solved radiance" in text for text in layout.labels())


def test_overlay_objects_needs_enabled_visible_and_attribute(overlay):
    a = radiance_sphere("A")
    b = radiance_sphere("B", enabled=False)
    bpy.ops.mesh.primitive_cube_add()
    c = bpy.context.object
    c.translucency.enabled = True  # no attribute
    d = radiance_sphere("D")
    d.hide_set(True)
    names = {o.name for o in overlay.overlay_objects(bpy.context.scene, bpy.context.view_layer)}
    assert names == {a.name}
    assert b and c


def test_tone_map_matches_documentation(overlay):
    x = np.array([[-1.0, 0.5, 4.0], [np.nan, np.inf, 1.0]])
    np.testing.assert_allclose(overlay.tone_map(x, 1.0, soft=False), [[0, 0.5, 1.0], [0, 0, 1.0]])
    np.testing.assert_allclose(overlay.tone_map(x, 2.0, soft=True),
                               [[0, 1 - math.exp(-1), 1 - math.exp(-8)], [0, 0, 1 - math.exp(-2)]])
    assert overlay.display_scale(np.array([[0.0, 0.0, 0.0]])) == 0.0


def test_import_and_register_make_no_gpu_calls(overlay):
    # Registration happened in background mode in the fixture; the shader is created lazily.
    assert overlay._shader is None


# --- drawing into an off-screen buffer --------------------------------------------------------

@pytest.mark.gpu
def test_only_mode_draws_radiance_on_the_object_and_nothing_elsewhere(overlay):
    scene = bpy.context.scene
    exact_display(scene)
    radiance_sphere()
    pixels, drawn = render(draw_with(overlay, 'ONLY'))
    assert drawn == 1
    inside, outside = object_mask()
    assert np.all(pixels[inside][:, :3].max(axis=1) > 0.01), "pixels on the object must be lit"
    assert np.all(pixels[inside][:, 3] == 1.0), "ONLY mode is opaque"
    assert np.all(pixels[outside] == 0.0), "nothing is drawn off the object"
    # With CLAMP and exposure 0 the pixel is the interpolated radiance itself: at the centre
    # of the image the visible point has x ~ 0, so L ~ (0.4, 0.3, 0.2).
    centre = pixels[SIZE // 2 - 1:SIZE // 2 + 1, SIZE // 2 - 1:SIZE // 2 + 1, :3].mean(axis=(0, 1))
    np.testing.assert_allclose(centre, [0.4, 0.3, 0.2], atol=0.03)
    # Brighter on the +x side (right half of the image).
    row = pixels[SIZE // 2, :, 0]
    assert row[SIZE // 2 + 8] > row[SIZE // 2] > row[SIZE // 2 - 8] > 0.0


@pytest.mark.gpu
def test_add_mode_adds_to_the_existing_shading(overlay):
    scene = bpy.context.scene
    exact_display(scene)
    radiance_sphere()
    only, _ = render(draw_with(overlay, 'ONLY'), background=BACKGROUND)
    added, _ = render(draw_with(overlay, 'ADD'), background=BACKGROUND)
    inside, outside = object_mask()
    # Off the object the background is untouched in both modes.
    np.testing.assert_allclose(added[outside], np.broadcast_to(BACKGROUND, added[outside].shape), atol=1e-6)
    np.testing.assert_allclose(only[outside], np.broadcast_to(BACKGROUND, only[outside].shape), atol=1e-6)
    # On the object ONLY replaces the background, ADD adds to it.
    np.testing.assert_allclose(added[inside][:, :3], only[inside][:, :3] + 0.25, atol=1e-4)
    assert np.all(only[inside][:, :3] < added[inside][:, :3])


@pytest.mark.gpu
def test_overlay_is_depth_tested(overlay):
    """A quad in front of the right half of the sphere hides the overlay there, in both modes."""
    import gpu
    from gpu_extras.batch import batch_for_shader

    exact_display(bpy.context.scene)
    radiance_sphere()

    def occluder():
        shader = gpu.shader.from_builtin('UNIFORM_COLOR')
        quad = [(0.0, -2.0, 2.0), (2.0, -2.0, 2.0), (2.0, 2.0, 2.0), (0.0, 2.0, 2.0)]
        batch = batch_for_shader(shader, 'TRIS', {"pos": quad}, indices=[(0, 1, 2), (0, 2, 3)])
        gpu.state.depth_test_set('LESS_EQUAL')
        gpu.state.depth_mask_set(True)
        shader.bind()
        shader.uniform_float("color", (0.0, 0.0, 1.0, 1.0))
        batch.draw(shader)
        gpu.state.depth_test_set('NONE')
        gpu.state.depth_mask_set(False)

    inside, _outside = object_mask()
    right = np.zeros_like(inside)
    right[:, SIZE // 2 + 2:] = True
    left = np.zeros_like(inside)
    left[:, :SIZE // 2 - 2] = True
    for mode in ('ONLY', 'ADD'):
        pixels, _ = render(draw_with(overlay, mode), before=occluder)
        hidden = pixels[inside & right]
        np.testing.assert_allclose(hidden, np.broadcast_to((0, 0, 1, 1), hidden.shape), atol=1e-6, err_msg=mode)
        assert np.all(pixels[inside & left][:, 0] > 0.01), mode


@pytest.mark.gpu
def test_draws_the_evaluated_mesh_with_the_world_matrix(overlay):
    exact_display(bpy.context.scene)
    obj = radiance_sphere()
    obj.location = (1.0, 0.0, 0.0)  # world matrix moves it to the right
    obj.scale = (0.5, 0.5, 0.5)
    obj.modifiers.new("Subdivision", 'SUBSURF')
    pixels, drawn = render(draw_with(overlay, 'ONLY'))
    assert drawn == 1
    lit = pixels[..., 3] > 0
    cols = np.nonzero(lit.any(axis=0))[0]
    assert cols.min() > SIZE // 2, "the sphere is drawn right of the image centre"
    entry = overlay._cache[obj.name]
    dg = bpy.context.evaluated_depsgraph_get()
    assert entry.key[1] == len(obj.evaluated_get(dg).data.vertices) > len(obj.data.vertices)


@pytest.mark.gpu
def test_batches_are_cached_until_the_attribute_changes(overlay):
    exact_display(bpy.context.scene)
    obj = radiance_sphere()
    first, _ = render(draw_with(overlay, 'ONLY'))
    entry = overlay._cache[obj.name]
    render(draw_with(overlay, 'ONLY'))
    assert overlay._cache[obj.name] is entry, "unchanged data reuses the batch"
    write_radiance(obj, lambda co: np.full_like(co, 0.1))
    second, _ = render(draw_with(overlay, 'ONLY'))
    assert overlay._cache[obj.name] is not entry
    inside, _ = object_mask()
    np.testing.assert_allclose(second[inside][:, :3], 0.1, atol=1e-4)
    assert not np.allclose(first[inside], second[inside])
    obj.translucency.enabled = False
    third, drawn = render(draw_with(overlay, 'ONLY'))
    assert drawn == 0 and not third.any()
    assert obj.name not in overlay._cache


@pytest.mark.gpu
def test_exposure_and_auto_exposure(overlay):
    scene = bpy.context.scene
    exact_display(scene)
    radiance_sphere()
    base, _ = render(draw_with(overlay, 'ONLY'))
    scene.translucency_display.exposure = -1.0
    half, _ = render(draw_with(overlay, 'ONLY'))
    inside, _ = object_mask()
    np.testing.assert_allclose(half[inside][:, :3], base[inside][:, :3] / 2.0, atol=1e-4)
    scene.translucency_display.exposure = 0.0
    scene.translucency_display.auto_exposure = True
    auto, _ = render(draw_with(overlay, 'ONLY'))
    # The brightest vertices (red 0.8) map to ~1 with auto exposure.
    assert 0.9 < auto[inside][:, 0].max() <= 1.0
    scene.translucency_display.tone_map = 'SOFT'
    soft, _ = render(draw_with(overlay, 'ONLY'))
    assert np.all(soft[inside][:, :3] <= auto[inside][:, :3] + 1e-5)


@pytest.mark.gpu
def test_draw_callback_follows_the_scene_toggle(overlay):
    """The real draw handler callback, with the current matrices, draws only when enabled."""
    scene = bpy.context.scene
    exact_display(scene)
    radiance_sphere()
    scene.translucency.overlay_enabled = True
    scene.translucency.overlay_mode = 'ONLY'
    on, _ = render(overlay._draw_callback)
    assert overlay._last_error == ""
    inside, outside = object_mask()
    assert np.all(on[inside][:, 0] > 0.01) and not on[outside].any()
    scene.translucency.overlay_enabled = False
    off, _ = render(overlay._draw_callback)
    assert not off.any()


# --- integration with the real bake and solve ----------------------------------------------------

@pytest.mark.gpu
def test_overlay_draws_a_real_solve(overlay):
    """Bake and solve a sphere through the add-on's operators, light at +x: the overlay shows it."""
    scene = bpy.context.scene
    scene.unit_settings.scale_length = 0.05  # one unit = 50 mm: a 100 mm marble sphere
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, segments=32, ring_count=16)
    obj = bpy.context.object
    obj.translucency.enabled = True
    obj.translucency.quality = 'DRAFT'
    light = bpy.data.objects.new("Light", bpy.data.lights.new("Light", 'POINT'))
    light.data.energy = 1000.0
    light.location = (3.0, 0.0, 1.0)
    scene.collection.objects.link(light)
    assert bpy.ops.translucency.bake() == {'FINISHED'}, obj.translucency.status.bake_status
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    assert obj.data.attributes.get(ATTRIBUTE) is not None
    scene.translucency_display.auto_exposure = True
    pixels, drawn = render(draw_with(overlay, 'ONLY'))
    assert drawn == 1
    inside, outside = object_mask()
    assert not pixels[outside].any()
    right = inside & (np.arange(SIZE)[None, :] > SIZE // 2 + 2)
    left = inside & (np.arange(SIZE)[None, :] < SIZE // 2 - 2)
    assert pixels[right][:, 0].mean() > 2.0 * pixels[left][:, 0].mean() > 0.0
    # Moving the light re-solves (solve operator), and the cached batch follows.
    light.location = (-3.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    assert bpy.ops.translucency.solve() == {'FINISHED'}
    moved, _ = render(draw_with(overlay, 'ONLY'))
    assert moved[left][:, 0].mean() > 2.0 * moved[right][:, 0].mean()
