# SPDX-License-Identifier: GPL-3.0-or-later
"""The scene's World as the engine's environment: SH radiance plus an HDRI's sun.

:func:`world_light` reads the World's node tree into the engine's bpy-free
description (``translucency_addon.scene.world_nodes``), evaluates the radiance
arriving from every direction of an equirectangular grid (as wide as the
widest map, at most 2048 pixels), takes an HDRI's sun out as a directional
light (``environment_map.extract_sun``: direction, irradiance in W/m^2,
angular size) and projects the rest to order-2 SH
(``environment_map.project_samples``, exact per-pixel solid angles).  That
happens once per change: the result is cached, keyed on the node tree's
content (``world_nodes.content_hash``) and on each image's name, file path,
size, file size and modification time (packed: the packed size).  Every frame
the cached world-space result is only rotated into the object's space.

Pixels: an Environment Texture's image is read from Blender's loaded image
(``Image.pixels``; byte images in sRGB are linearised, float images are scene
linear already) and reduced to at most 2048 x 1024 by solid-angle-weighted
block averages before anything else (``environment_map.downsample``), so a
16k HDRI costs its own read buffer once (16384 x 8192 RGBA float32 = 2 GiB)
and a few seconds, measured in ``bench/world.py``.

A Sky Texture is evaluated by Blender itself: the sky node alone is rendered
by Cycles through an equirectangular camera (1024 x 512, 16 samples; a scene,
world, camera and image created for it and removed afterwards, the file in a
temporary folder deleted) and then sampled like an image.  That render cannot
run inside another render, so a sky met first in an F12 or command-line render
falls back (with a message saying so) until a solve outside a render (the
viewport, the Solve button) has baked it; the bake is kept for the session.

Anything the evaluator does not reproduce (an OSL Script node, a node group,
an image that failed to load, a Light Path output other than Is Camera Ray,
no World Output) gives the old fallback -- the world's viewport colour -- and
a warning that names the node and what to change; nothing is written.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from dataclasses import dataclass

import bpy
import numpy as np

from . import compat

MAX_WIDTH = 2048  # evaluation grid and image reduction: 0.18 degree pixels resolve a 0.5 degree sun
SKY_SIZE = (1024, 512)
SKY_SAMPLES = 16
_CACHE: dict = {}  # key -> WorldResult (the last few worlds)
_CACHE_SIZE = 4
_BAKING: list = []  # the sky node being baked (no bake inside a bake)


@dataclass(frozen=True)
class WorldResult:
    """A World evaluated once, in world space."""

    sh: np.ndarray  # (9, 3) radiance SH, world space, the sun taken out
    sun: object  # environment_map.ExtractedSun or None
    note: str  # the panel's line: what was projected and whether a sun became a light
    seconds: float


def status_line() -> str:
    """The last World evaluation's line for the panel ('' before one)."""
    return _LAST.get("note", "")


_LAST: dict = {}


def set_status_line(text: str) -> None:
    """Record what the World became when it did not go through :func:`world_light` (a uniform colour, none)."""
    _LAST["note"] = text


# ------------------------------------------------------------------ node tree -> description


def _active_output(tree):
    outputs = [n for n in tree.nodes if n.type == 'OUTPUT_WORLD' and n.target in {'ALL', 'CYCLES'}]
    for n in outputs:
        if getattr(n, "is_active_output", False):
            return n
    return outputs[0] if outputs else None


def _value(sock):
    v = getattr(sock, "default_value", None)
    if v is None:
        return None
    try:
        return tuple(float(x) for x in v)
    except TypeError:
        return float(v)


def describe_tree(world):
    """``(WorldGraph without pixels, [(node name, image or sky node)])`` of the nodes the output reaches."""
    from ..translucency_addon.scene.world_nodes import WorldGraph, WorldNode, WorldNodeError

    tree = world.node_tree
    out = _active_output(tree)
    if out is None:
        raise WorldNodeError(f"world '{world.name}' has no World Output node (for Cycles or All) in its node tree")
    nodes, sources, todo = {}, [], [out]
    while todo:
        nd = todo.pop()
        if nd.name in nodes:
            continue
        wn = WorldNode(name=nd.name, type=nd.type)
        if nd.mute:
            raise WorldNodeError(f"node '{nd.name}' in world '{world.name}' is muted; unmute or remove it")
        for sock in nd.inputs:
            if not sock.enabled:
                continue
            links = [lk for lk in sock.links if not lk.is_muted] if sock.is_linked else []
            if links:
                wn.links[sock.identifier] = (links[0].from_node.name, links[0].from_socket.name)
                todo.append(links[0].from_node)
            elif not sock.hide_value:  # a hidden value is an implicit input (a texture's coordinates)
                v = _value(sock)
                if v is not None:
                    wn.values[sock.identifier] = v
        for prop in ("vector_type", "operation", "use_clamp", "blend_type", "data_type", "clamp_factor",
                     "clamp_result", "interpolation", "projection"):
            if hasattr(nd, prop):
                wn.props[prop] = getattr(nd, prop)
        if nd.type == 'TEX_COORD':
            wn.props["object"] = nd.object.name if getattr(nd, "object", None) else ""
        elif nd.type == 'RGB':
            wn.props["color"] = tuple(float(x) for x in nd.outputs[0].default_value[:3])
        elif nd.type == 'VALUE':
            wn.props["value"] = float(nd.outputs[0].default_value)
        elif nd.type == 'TEX_ENVIRONMENT':
            if nd.projection != 'EQUIRECTANGULAR':
                raise WorldNodeError(f"Environment Texture '{nd.name}' uses the {nd.projection.title()} "
                                     "projection; only Equirectangular is evaluated")
            if nd.image is None:
                raise WorldNodeError(f"Environment Texture '{nd.name}' has no image")
            wn.props["image"] = image_key(nd.image)
            sources.append((nd.name, nd.image))
        elif nd.type == 'TEX_SKY':
            wn.props["sky"] = sky_key(nd)
            sources.append((nd.name, nd))
        nodes[nd.name] = wn
    return WorldGraph(nodes=nodes, output=out.name), sources


def image_key(img) -> tuple:
    """What identifies an image's pixels: name, path, size, file size and time, packed size, colour space."""
    path = bpy.path.abspath(img.filepath_raw or "", library=img.library) if img.filepath_raw else ""
    try:
        st = os.stat(path) if path else None
    except OSError:
        st = None
    packed = img.packed_file.size if img.packed_file is not None else 0
    return (img.name, img.filepath_raw, img.source, tuple(img.size), packed,
            (st.st_size, st.st_mtime_ns) if st else None, img.colorspace_settings.name)


def sky_key(node) -> tuple:
    props = [p.identifier for p in node.bl_rna.properties
             if not p.is_readonly and p.identifier not in {"name", "label", "location", "location_absolute", "width",
                                                          "height", "select", "hide", "color", "use_custom_color",
                                                          "show_options", "show_preview", "show_texture", "parent",
                                                          "mute", "color_tag", "warning_propagation"}
             and p.type in {'FLOAT', 'INT', 'BOOLEAN', 'ENUM'}]
    vals = []
    for p in props:
        v = getattr(node, p)
        try:
            v = tuple(v)
        except TypeError:
            pass
        vals.append((p, v))
    return (tuple(vals), tuple(bpy.app.version))


# ------------------------------------------------------------------ pixels


def image_pixels(img, name: str) -> np.ndarray:
    """An image's linear radiance, reduced to at most MAX_WIDTH wide; raises WorldNodeError if it did not load."""
    from ..translucency_addon.scene.environment_map import downsample
    from ..translucency_addon.scene.world_nodes import WorldNodeError

    w, h = img.size
    if w == 0 or h == 0 or not img.has_data and (img.pixels is None or len(img.pixels) == 0):
        path = bpy.path.abspath(img.filepath_raw) if img.filepath_raw else "(no file)"
        missing = img.filepath_raw and not os.path.exists(path)
        why = "the file does not exist" if missing else "Blender could not read it"
        raise WorldNodeError(f"Environment Texture '{name}': image '{img.name}' did not load ({why}: {path}); "
                             "fix the path (File > External Data > Find Missing Files) or pick another image")
    c = img.channels
    buf = np.empty(w * h * c, dtype=np.float32)
    img.pixels.foreach_get(buf)
    px = downsample(buf.reshape(h, w, c), MAX_WIDTH)
    del buf
    space = img.colorspace_settings.name
    if not img.is_float and space == 'sRGB':
        px = np.where(px <= 0.04045, px / 12.92, ((px + 0.055) / 1.055) ** 2.4).astype(np.float32)
    elif not img.is_float and space not in {'Non-Color', 'Linear Rec.709', 'Linear', 'Raw'}:
        raise WorldNodeError(f"Environment Texture '{name}': image '{img.name}' is in the '{space}' colour space; "
                             "only sRGB, Linear Rec.709 and Non-Color are converted: set one of them")
    return px


def bake_sky(node, can_render: bool = True) -> np.ndarray:
    """The Sky Texture ``node`` as Cycles evaluates it: an equirectangular (512, 1024, 3) map of its radiance.

    Renders the sky alone (Background strength 1) in a temporary scene through an
    equirectangular camera turned (90, 0, -90) degrees, which maps the image onto
    world directions in Cycles' equirectangular convention (checked in
    ``tests/test_world.py``: the sun found in the bake lies where the node's
    Sun Elevation and Sun Rotation put it, within 0.1 degree).  Everything
    created is removed again (the Render Result too, unless it existed; if it
    did, it now shows the sky).
    """
    from ..translucency_addon.scene.world_nodes import WorldNodeError

    if not can_render or _BAKING or bpy.app.is_job_running('RENDER'):
        raise WorldNodeError(f"Sky Texture '{node.name}' is evaluated by a Cycles render of the sky, which cannot "
                             "run inside another render; solve once outside a render (the Solve button or the "
                             "viewport) to bake it for this session")
    _BAKING.append(node.name)
    scene = bpy.data.scenes.new("translucency_sky_bake")
    world = bpy.data.worlds.new("translucency_sky_bake")
    cam = bpy.data.cameras.new("translucency_sky_bake")
    cam_ob = bpy.data.objects.new("translucency_sky_bake", cam)
    tmp = tempfile.mkdtemp(prefix="translucency-sky-")
    path = os.path.join(tmp, "sky.exr")
    img = None
    had_result = bpy.data.images.get("Render Result") is not None
    try:
        tree = compat.ensure_node_tree(world)
        tree.nodes.clear()
        sky = tree.nodes.new('ShaderNodeTexSky')
        for key, val in sky_key(node)[0]:
            try:
                setattr(sky, key, val)
            except (AttributeError, TypeError, ValueError):
                pass
        bg = tree.nodes.new('ShaderNodeBackground')
        out = tree.nodes.new('ShaderNodeOutputWorld')
        tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
        tree.links.new(bg.outputs[0], out.inputs["Surface"])
        cam.type = 'PANO'
        cam.panorama_type = 'EQUIRECTANGULAR'
        cam_ob.rotation_euler = (np.pi / 2, 0.0, -np.pi / 2)
        scene.collection.objects.link(cam_ob)
        scene.camera = cam_ob
        scene.world = world
        r = scene.render
        r.engine = 'CYCLES'
        r.resolution_x, r.resolution_y = SKY_SIZE
        r.resolution_percentage = 100
        r.filter_size = 0.01
        r.use_compositing = False
        r.use_sequencer = False
        scene.cycles.samples = SKY_SAMPLES
        scene.cycles.device = 'CPU'
        scene.cycles.use_denoising = False
        r.image_settings.file_format = 'OPEN_EXR'
        r.image_settings.color_depth = '32'
        r.filepath = path
        try:
            bpy.ops.render.render(write_still=True, scene=scene.name)
        except RuntimeError as ex:  # the operator's poll refuses while another render runs
            raise WorldNodeError(f"Sky Texture '{node.name}': the Cycles render that evaluates the sky could not "
                                 f"run ({str(ex).strip()}); solve once outside a render to bake it") from None
        if not os.path.exists(path):
            raise WorldNodeError(f"Sky Texture '{node.name}': the Cycles render of the sky wrote nothing")
        img = bpy.data.images.load(path)
        buf = np.empty(SKY_SIZE[0] * SKY_SIZE[1] * 4, dtype=np.float32)
        img.pixels.foreach_get(buf)
        return np.ascontiguousarray(buf.reshape(SKY_SIZE[1], SKY_SIZE[0], 4)[..., :3])
    finally:
        _BAKING.clear()
        shutil.rmtree(tmp, ignore_errors=True)
        for collection, block in ((bpy.data.images, img), (bpy.data.scenes, scene), (bpy.data.objects, cam_ob),
                                  (bpy.data.cameras, cam), (bpy.data.worlds, world)):
            if block is not None:
                collection.remove(block)
        result = bpy.data.images.get("Render Result")
        if result is not None and not had_result:
            bpy.data.images.remove(result)


# ------------------------------------------------------------------ evaluation, cached


def evaluate_world(world, can_render: bool = True) -> WorldResult:
    """The World's SH and sun in world space, evaluated once per change (cached)."""
    from ..translucency_addon.scene import environment_map as em
    from ..translucency_addon.scene.world_nodes import content_hash, evaluate, sample_grid

    graph, sources = describe_tree(world)
    key = (world.name, content_hash(graph))
    hit = _CACHE.get(key)
    if hit is not None:
        return hit
    t0 = time.perf_counter()
    names = []
    for node_name, src in sources:
        if isinstance(src, bpy.types.Image):
            graph.images[node_name] = image_pixels(src, node_name)
            names.append(f"HDRI '{os.path.basename(src.filepath_raw) or src.name}'")
        else:
            graph.images[node_name] = bake_sky(src, can_render)
            names.append(f"Sky Texture '{node_name}' ({src.sky_type.replace('_', ' ').title()}, baked by Cycles)")
    h, w = sample_grid(graph, MAX_WIDTH)
    dirs = em.equirect_directions(h, w).reshape(-1, 3)
    L = evaluate(graph, dirs).reshape(h, w, 3)
    sun, rest, why = em.extract_sun(L)
    sh = em.project_equirect(rest, em.ENGINE_ORDER)
    what = " + ".join(names) if names else f"world '{world.name}'"
    note = f"World: {what} projected to SH order {em.ENGINE_ORDER}"
    if sun is not None:
        lum = float(np.dot(sun.irradiance, [0.2126, 0.7152, 0.0722]))
        note += (f"; its sun ({sun.angle_degrees:.2g}\u00b0 across, {lum:.4g} W/m\u00b2, "
                 f"{100 * sun.fraction:.0f} % of its light) became a directional light")
    elif why and names:
        note += f"; {why}"
    res = WorldResult(sh=sh, sun=sun, note=note, seconds=time.perf_counter() - t0)
    if len(_CACHE) >= _CACHE_SIZE:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = res
    return res


def clear_cache() -> None:
    _CACHE.clear()
    _LAST.clear()


def world_light(world, obj_matrix=None, can_render: bool = True):
    """``(Environment or None, sun Light or None, warning or None)`` in the object's space.

    ``obj_matrix``: the object's world matrix (None: world space).  ``can_render``: False inside a
    render (a render depsgraph, a render thread), where a Sky Texture cannot be baked.  Raises
    :class:`translucency_addon.scene.world_nodes.WorldNodeError` when the World holds
    something that is not evaluated (the caller falls back and warns).
    """
    from ..translucency_addon.scene.environment_map import rotate_sh
    from ..translucency_addon.scene.lights import Environment, Light

    res = evaluate_world(world, can_render)
    _LAST["note"] = res.note
    Q = np.eye(3)
    if obj_matrix is not None:
        m = np.array([list(row)[:3] for row in list(obj_matrix)[:3]], dtype=np.float64)
        u, _, vt = np.linalg.svd(m)
        Q = u @ vt  # object -> world directions (the orthogonal part)
    sh = rotate_sh(res.sh, Q) if obj_matrix is not None else res.sh
    env = Environment(radiance=(0.0, 0.0, 0.0), sh=sh) if np.any(sh) else None
    light = None
    if res.sun is not None:
        d = Q.T @ np.asarray(res.sun.direction)
        E = np.asarray(res.sun.irradiance)
        peak = float(E.max())
        if peak > 0:
            light = Light("sun", color=tuple(float(x) for x in E / peak), irradiance=peak,
                          direction=tuple(float(x) for x in -d / np.linalg.norm(d)), name="World sun")
    return env, light, None


CLASSES = ()
