# SPDX-License-Identifier: GPL-3.0-or-later
"""Viewport overlay: the solved subsurface radiance drawn in the 3D View.

A ``SpaceView3D`` draw handler (``'WINDOW'``, ``'POST_VIEW'``) draws every
visible mesh object with ``object.translucency.enabled`` that carries the
per-vertex radiance attribute ``translucency_radiance`` (a FLOAT_COLOR POINT
attribute on the mesh data, written by the solver).  It draws the
depsgraph-evaluated mesh (modifiers applied) with the object's world matrix.

Modes (``scene.translucency.overlay_mode``):

* ``ONLY`` -- "translucency only": opaque, depth test LESS_EQUAL, depth write
  on.  The object shows the radiance alone.
* ``ADD``  -- "add to shading": additive blending over the normal viewport
  shading, depth test LESS_EQUAL.  A depth-only pre-pass first writes the
  overlay's depth, so only the nearest surface adds its radiance.

Both modes pull the overlay's depth a little towards the camera
(``DEPTH_BIAS`` of clip-space w) so it does not z-fight with the viewport's
own drawing of the same surface.

Display mapping (the *exposure*), settings in ``scene.translucency_display``
(:class:`TranslucencyDisplaySettings`, registered by this module)::

    x       = L * gain * 2**exposure          L: radiance, W/(m^2 sr), per channel
    gain    = 1 / L99  if auto_exposure else 1
    display = 1 - exp(-x)    (tone_map SOFT)   or   min(x, 1)   (tone_map CLAMP)

``L99`` is the 99th percentile of the per-vertex maximum channel over every
object drawn, so with auto exposure the brightest 1 % of vertices saturate
towards white and the rest keep their relative brightness.  The result is
written as is (no sRGB encoding: the viewport treats draw-handler colours as
linear and applies the display transform itself).  Negative or non-finite
radiance draws as black.

Batches are cached per object and rebuilt only when the evaluated mesh, its
vertex positions, its triangles or the attribute values change (a CRC of the
arrays is compared each draw; reading them is a few milliseconds for a
100k-vertex mesh).  No ``gpu`` call happens at import or register time: the
shader is created on the first draw.

Registration (called by ``ops/__init__.py``): :func:`on_register` after the
module's ``CLASSES`` are registered (it adds the Scene pointer, the draw
handler and the load_pre/load_post handlers), :func:`on_unregister` before
they are unregistered.  The draw handler is removed on load_pre and added again
on load_post, and there is never more than one.
"""

from __future__ import annotations

import os
import zlib

import bpy
import numpy as np
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty, FloatProperty, PointerProperty

from .attributes import ATTRIBUTE_NAME as ATTRIBUTE  # the one spelling of the name

DEPTH_BIAS = 2e-5  # fraction of clip-space w the overlay is moved towards the camera
AUTO_PERCENTILE = 99.0
SCENE_PROPERTY = "translucency_display"


# --- settings ---------------------------------------------------------------------------

class TranslucencyDisplaySettings(bpy.types.PropertyGroup):
    """Viewport display of the solved radiance (``scene.translucency_display``)."""

    exposure: FloatProperty(
        name="Exposure",
        description="Brightness of the overlay in stops (each +1 doubles the radiance before tone mapping)",
        default=0.0,
        soft_min=-10.0,
        soft_max=10.0,
        step=10,
        precision=2,
    )
    auto_exposure: BoolProperty(
        name="Auto Exposure",
        description=(
            "Scale the radiance so that its 99th percentile over the drawn objects maps to 1 before "
            "tone mapping (the exposure is applied on top); off: 1 W/(m^2 sr) maps to 1"
        ),
        default=True,
    )
    tone_map: EnumProperty(
        name="Tone Map",
        description="How the exposed radiance is mapped to display values",
        items=(
            ("SOFT", "Soft", "1 - exp(-x): bright regions roll off smoothly towards white"),
            ("CLAMP", "Clamp", "min(x, 1): linear up to 1, then clipped"),
        ),
        default="SOFT",
    )


CLASSES = (TranslucencyDisplaySettings,)


def display_settings(scene):
    """``scene.translucency_display`` or ``None`` when this module is not registered."""
    return getattr(scene, SCENE_PROPERTY, None)


# --- mesh data -> arrays ------------------------------------------------------------------

def _radiance_attribute(mesh):
    attr = mesh.attributes.get(ATTRIBUTE)
    if attr is None or attr.domain not in {'POINT', 'CORNER'}:
        return None
    if attr.data_type not in {'FLOAT_COLOR', 'BYTE_COLOR', 'FLOAT_VECTOR'}:
        return None
    return attr


def _attribute_rgb(attr, count: int) -> np.ndarray:
    if attr.data_type == 'FLOAT_VECTOR':
        buf = np.empty(count * 3, np.float32)
        attr.data.foreach_get("vector", buf)
        return buf.reshape(count, 3)
    buf = np.empty(count * 4, np.float32)
    attr.data.foreach_get("color", buf)  # BYTE_COLOR reads back as linear floats too
    return buf.reshape(count, 4)[:, :3]


def has_radiance(obj) -> bool:
    """True when ``obj`` is a mesh whose data carries the radiance attribute."""
    return obj is not None and obj.type == 'MESH' and _radiance_attribute(obj.data) is not None


def mesh_arrays(obj, depsgraph):
    """Evaluated geometry and radiance of ``obj``: ``(positions, rgb, triangles, mesh)``.

    ``positions`` (V, 3) and ``rgb`` (V, 3) are per drawn vertex and
    ``triangles`` (T, 3) indexes them; all in object space.  Colours come from
    the original mesh when the evaluated one has the same vertex count (the
    original is always up to date, even before the depsgraph re-evaluates),
    otherwise from the attribute the modifiers interpolated.  ``None`` when
    there is nothing to draw.
    """
    obj_eval = obj.evaluated_get(depsgraph)
    mesh = obj_eval.data
    if mesh is None or len(mesh.vertices) == 0:
        return None
    n_verts = len(mesh.vertices)
    if hasattr(mesh, "calc_loop_triangles"):  # Blender < 5.0; later versions compute them lazily
        mesh.calc_loop_triangles()
    n_tris = len(mesh.loop_triangles)
    if n_tris == 0:
        return None
    positions = np.empty(n_verts * 3, np.float32)
    mesh.vertices.foreach_get("co", positions)
    positions = positions.reshape(n_verts, 3)

    source = None
    original = obj.original.data if obj.original is not None else obj.data
    attr = _radiance_attribute(original)
    if attr is not None and attr.domain == 'POINT' and len(original.vertices) == n_verts:
        source = attr
    else:
        attr = _radiance_attribute(mesh)
        if attr is not None:
            source = attr
    if source is None:
        return None

    if source.domain == 'POINT':
        rgb = _attribute_rgb(source, n_verts)
        triangles = np.empty(n_tris * 3, np.int32)
        mesh.loop_triangles.foreach_get("vertices", triangles)
        return positions, rgb, triangles.reshape(n_tris, 3), mesh
    # CORNER domain: one drawn vertex per face corner.
    n_loops = len(mesh.loops)
    if len(source.data) != n_loops:
        return None
    rgb = _attribute_rgb(source, n_loops)
    loop_vertex = np.empty(n_loops, np.int32)
    mesh.loops.foreach_get("vertex_index", loop_vertex)
    triangles = np.empty(n_tris * 3, np.int32)
    mesh.loop_triangles.foreach_get("loops", triangles)
    return positions[loop_vertex], rgb, triangles.reshape(n_tris, 3), mesh


def display_scale(rgb: np.ndarray) -> float:
    """The radiance that auto exposure maps to 1 for this object (99th percentile)."""
    peak = np.nan_to_num(np.max(rgb, axis=1), nan=0.0, posinf=0.0, neginf=0.0)
    peak = peak[peak > 0.0]
    if peak.size == 0:
        return 0.0
    return float(np.percentile(peak, AUTO_PERCENTILE))


def tone_map(rgb, gain: float, soft: bool) -> np.ndarray:
    """The shader's display mapping, in numpy (for tests and documentation)."""
    x = np.maximum(np.nan_to_num(np.asarray(rgb, np.float64), nan=0.0, posinf=0.0, neginf=0.0), 0.0) * gain
    return 1.0 - np.exp(-x) if soft else np.minimum(x, 1.0)


# --- GPU resources (created lazily, in the draw callback) -----------------------------

_shader = None
_cache: dict[str, "_Entry"] = {}


class _Entry:
    __slots__ = ("key", "batch", "scale")

    def __init__(self, key, batch, scale):
        self.key = key
        self.batch = batch
        self.scale = scale


def _glsl(name: str) -> str:
    """A stage of the overlay shader from ``gpu_shaders/`` (where every .glsl of the extension lives)."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "gpu_shaders", name)
    with open(path, encoding="utf-8") as f:
        return f.read()


def get_shader():
    """The overlay shader (created on first use; needs Blender's GPU backend)."""
    global _shader
    if _shader is None:
        import gpu

        info = gpu.types.GPUShaderCreateInfo()
        iface = gpu.types.GPUStageInterfaceInfo("translucency_overlay_iface")
        iface.smooth('VEC4', "v_radiance")
        info.vertex_in(0, 'VEC3', "pos")
        info.vertex_in(1, 'VEC4', "radiance")
        info.vertex_out(iface)
        info.push_constant('MAT4', "ModelViewProjectionMatrix")
        info.push_constant('FLOAT', "depth_bias")
        info.push_constant('FLOAT', "gain")
        info.push_constant('FLOAT', "soft")
        info.fragment_out(0, 'VEC4', "FragColor")
        info.vertex_source(_glsl("overlay_vert.glsl"))
        info.fragment_source(_glsl("overlay_frag.glsl"))
        _shader = gpu.shader.create_from_info(info)
    return _shader


def clear_cache() -> None:
    """Drop every cached batch (and the shader, which is recreated on demand)."""
    global _shader
    _cache.clear()
    _shader = None


def _crc(array: np.ndarray) -> int:
    return zlib.crc32(memoryview(np.ascontiguousarray(array)).cast("B"))


def _batch_for(obj, depsgraph, shader):
    arrays = mesh_arrays(obj, depsgraph)
    if arrays is None:
        _cache.pop(obj.name, None)
        return None
    positions, rgb, triangles, mesh = arrays
    key = (mesh.as_pointer(), len(positions), len(triangles), _crc(positions), _crc(rgb), _crc(triangles))
    entry = _cache.get(obj.name)
    if entry is not None and entry.key == key:
        return entry
    from gpu_extras.batch import batch_for_shader

    radiance = np.ones((len(rgb), 4), np.float32)
    radiance[:, :3] = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    batch = batch_for_shader(shader, 'TRIS', {"pos": positions, "radiance": radiance}, indices=triangles)
    entry = _Entry(key, batch, display_scale(rgb))
    _cache[obj.name] = entry
    return entry


def overlay_objects(scene, view_layer=None, space=None):
    """Objects the overlay draws: visible enabled meshes with the radiance attribute."""
    view_layer = view_layer or scene.view_layers[0]
    result = []
    for obj in scene.objects:
        if obj.type != 'MESH':
            continue
        settings = getattr(obj, "translucency", None)
        if settings is not None and not settings.enabled:
            continue
        try:
            visible = obj.visible_get(view_layer=view_layer, viewport=space) if space is not None \
                else obj.visible_get(view_layer=view_layer)
        except (TypeError, RuntimeError):
            visible = obj.visible_get()
        if visible and _radiance_attribute(obj.data) is not None:
            result.append(obj)
    return result


def draw_overlay(depsgraph, scene=None, *, mode=None, view_layer=None, space=None,
                 view_matrix=None, projection_matrix=None) -> int:
    """Draw the radiance of every overlay object into the bound framebuffer.

    Uses the current ``gpu.matrix`` state (the viewport's, inside the draw
    handler) unless ``view_matrix``/``projection_matrix`` are given, which is
    how tests and off-screen renders call it.  ``mode`` is ``'ONLY'`` or
    ``'ADD'`` (default: ``scene.translucency.overlay_mode``).  Restores the
    GPU state it changes.  Returns the number of objects drawn.
    """
    import gpu

    scene = scene or depsgraph.scene
    if mode is None:
        mode = getattr(getattr(scene, "translucency", None), "overlay_mode", "ADD")
    if mode not in {'ONLY', 'ADD'}:
        raise ValueError(f"overlay mode must be 'ONLY' or 'ADD', got {mode!r}")
    display = display_settings(scene)
    exposure = display.exposure if display is not None else 0.0
    auto = display.auto_exposure if display is not None else True
    soft = (display.tone_map if display is not None else 'SOFT') == 'SOFT'

    objects = overlay_objects(scene, view_layer or depsgraph.view_layer, space)
    names = {obj.name for obj in objects}
    for name in list(_cache):
        if name not in names:
            del _cache[name]
    if not objects:
        return 0
    shader = get_shader()
    drawn = []
    for obj in objects:
        entry = _batch_for(obj, depsgraph, shader)
        if entry is not None:
            drawn.append((obj, entry))
    if not drawn:
        return 0

    gain = 2.0 ** exposure
    if auto:
        scale = max(entry.scale for _obj, entry in drawn)
        gain = gain / scale if scale > 0.0 else gain

    old_blend = gpu.state.blend_get()
    old_depth = gpu.state.depth_test_get()
    old_mask = gpu.state.depth_mask_get()
    try:
        gpu.state.depth_test_set('LESS_EQUAL')
        if mode == 'ONLY':
            gpu.state.blend_set('NONE')
            gpu.state.depth_mask_set(True)
        else:
            gpu.state.blend_set('ADDITIVE')
            gpu.state.depth_mask_set(False)
        with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
            if view_matrix is not None:
                gpu.matrix.load_matrix(view_matrix)
            if projection_matrix is not None:
                gpu.matrix.load_projection_matrix(projection_matrix)
            shader.bind()
            shader.uniform_float("depth_bias", DEPTH_BIAS)
            shader.uniform_float("gain", gain)
            shader.uniform_float("soft", 1.0 if soft else 0.0)
            matrices = [obj.evaluated_get(depsgraph).matrix_world.copy() for obj, _entry in drawn]
            if mode == 'ADD':
                # Depth pre-pass, so only the nearest surface is added (hidden and back
                # faces would otherwise add up as well where the depth buffer is empty).
                gpu.state.color_mask_set(False, False, False, False)
                gpu.state.depth_mask_set(True)
                _draw_batches(drawn, matrices, shader)
                gpu.state.color_mask_set(True, True, True, True)
                gpu.state.depth_mask_set(False)
            _draw_batches(drawn, matrices, shader)
    finally:
        gpu.state.color_mask_set(True, True, True, True)
        gpu.state.blend_set(old_blend)
        gpu.state.depth_test_set(old_depth)
        gpu.state.depth_mask_set(old_mask)
    return len(drawn)


def _draw_batches(drawn, matrices, shader) -> None:
    import gpu

    for (_obj, entry), matrix in zip(drawn, matrices):
        with gpu.matrix.push_pop():
            gpu.matrix.multiply_matrix(matrix)
            entry.batch.draw(shader)


# --- the draw handler ----------------------------------------------------------------------

_handle = None
_last_error = ""


def _draw_callback() -> None:
    global _last_error
    context = bpy.context
    scene = context.scene
    settings = getattr(scene, "translucency", None) if scene is not None else None
    if settings is None or not settings.overlay_enabled:
        return
    space = getattr(context, "space_data", None)
    overlay = getattr(space, "overlay", None)
    if overlay is not None and not overlay.show_overlays:
        return
    try:
        draw_overlay(context.evaluated_depsgraph_get(), scene, view_layer=context.view_layer, space=space)
        _last_error = ""
    except Exception as ex:  # noqa: BLE001 - a draw callback must never raise into Blender
        message = f"{type(ex).__name__}: {ex}"
        if message != _last_error:  # report once, not every redraw
            print(f"Translucency overlay: {message}")
        _last_error = message


def add_draw_handler() -> None:
    """Add the View-3D draw handler (once; a second call does nothing)."""
    global _handle
    if _handle is None:
        _handle = bpy.types.SpaceView3D.draw_handler_add(_draw_callback, (), 'WINDOW', 'POST_VIEW')


def remove_draw_handler() -> None:
    global _handle
    if _handle is not None:
        try:
            bpy.types.SpaceView3D.draw_handler_remove(_handle, 'WINDOW')
        except (ValueError, RuntimeError):
            pass
        _handle = None
    _cache.clear()


def draw_handler_active() -> bool:
    return _handle is not None


@persistent
def _on_load_pre(*_args) -> None:
    remove_draw_handler()
    clear_cache()


@persistent
def _on_load_post(*_args) -> None:
    add_draw_handler()


_APP_HANDLERS = (("load_pre", _on_load_pre), ("load_post", _on_load_post))


def _remove_app_handlers() -> None:
    # By name as well as identity, so a reloaded module never leaves a stale copy behind.
    for list_name, func in _APP_HANDLERS:
        handlers = getattr(bpy.app.handlers, list_name)
        for h in list(handlers):
            if h is func or (getattr(h, "__module__", None) == func.__module__
                             and getattr(h, "__name__", None) == func.__name__):
                handlers.remove(h)


def on_register() -> None:
    """After ``CLASSES`` are registered: Scene pointer, draw handler, load handlers."""
    bpy.types.Scene.translucency_display = PointerProperty(
        type=TranslucencyDisplaySettings,
        name="Translucency Display",
        description="Viewport display of the solved subsurface radiance",
    )
    _remove_app_handlers()
    for list_name, func in _APP_HANDLERS:
        getattr(bpy.app.handlers, list_name).append(func)
    add_draw_handler()


def on_unregister() -> None:
    """Before ``CLASSES`` are unregistered: removes everything :func:`on_register` added."""
    remove_draw_handler()
    _remove_app_handlers()
    clear_cache()
    if hasattr(bpy.types.Scene, SCENE_PROPERTY):
        try:
            del bpy.types.Scene.translucency_display
        except (AttributeError, RuntimeError):
            pass


# --- panel ---------------------------------------------------------------------------------

def draw_settings(layout, context) -> None:
    """Overlay rows for the Translucency panel (on/off, mode, exposure)."""
    scene = context.scene
    settings = getattr(scene, "translucency", None)
    if settings is None:
        return
    box = layout.box()
    box.label(text="Viewport Overlay", icon='OVERLAY')
    box.prop(settings, "overlay_enabled")
    col = box.column()
    col.active = settings.overlay_enabled
    col.prop(settings, "overlay_mode")
    display = display_settings(scene)
    if display is not None:
        col.prop(display, "auto_exposure")
        col.prop(display, "exposure")
        col.prop(display, "tone_map")
    obj = getattr(context, "object", None)
    if obj is not None and obj.type == 'MESH' and not has_radiance(obj):
        col.label(text="No solved radiance on this object yet", icon='INFO')
