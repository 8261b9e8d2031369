# SPDX-License-Identifier: GPL-3.0-or-later
"""Blender scene -> engine inputs, in the translucent object's local space.

Everything the engine receives is in the **object's space** (the space of its
QuadGraph) with ``mm_per_unit`` converting object units to millimetres
(``docs/architecture.md``).  This module converts:

* Blender lights -> :class:`translucency_addon.scene.lights.Light`;
* the world -> :class:`translucency_addon.scene.lights.Environment`;
* other visible meshes -> occluder triangles ``(V, F)`` in object space;
* a texture / mesh attribute / vertex group -> the heterogeneity field at
  every level's nodes;
* the panel's material settings -> :class:`translucency_addon.scene.materials.Material`.

Radiometric conversion (Blender's conventions, measured against Cycles)
-----------------------------------------------------------------------
``tests/test_light_units.py`` renders a white Lambertian plane (albedo 1, so
its radiance is ``E / pi``) with Cycles and compares every pixel with the
irradiance the engine computes from the converted light.  The factors:

===========  =====================================  ==========================
Blender      Blender setting                        engine value
===========  =====================================  ==========================
Point        power P [W]                            intensity ``P / (4 pi)`` W/sr
Spot         power P [W], spot size, blend          intensity ``P / (4 pi)`` W/sr
             (the power of the *whole sphere*:      times Blender's cone mask
             a spot is a masked point light)        ``smoothstep((cos - cos_half) /
                                                    (blend (1 - cos_half)))``
Area         power P [W]                            one-sided Lambertian emitter,
                                                    ``P / pi`` W/sr along its normal
                                                    (``x cos`` off the normal, far field)
Area, Normalize off  power P per unit area          ``P A / pi`` (A = area in world units)
Sun          strength S [W/m^2]                     irradiance ``S`` W/m^2
World        Background colour C, strength S        uniform radiance ``C S`` W/(m^2 sr)
World        any other node tree (``ops/world.py``)  order-2 SH radiance + an HDRI's
                                                    sun as a ``sun`` light (W/m^2)
===========  =====================================  ==========================

Every light power is also multiplied by ``2 ** exposure`` (Blender 4.0+) and
its colour by the blackbody colour when "Temperature" is on (Blender 4.5+).

**Scene scale.**  Cycles and EEVEE ignore ``unit_settings.scale_length``: a
1000 W point light 2 units away gives the same irradiance whatever the unit
scale (measured), i.e. the renderers treat one world unit as one metre for
light falloff.  The engine divides intensities by the distance in *metres*
computed with ``mm_per_unit``.  So that the subsurface result matches what
the renderer shows next to it, point, spot and area intensities are
multiplied by ``(metres per world unit)^2`` (``scale_length^2`` unless the
scale is overridden); sun irradiance and world radiance do not depend on
distance and are passed unchanged.

Spot lights whose object is scaled non-uniformly (an elliptical cone),
area-light ``spread`` below 180 degrees, light node trees and light linking
are not modelled; the near field of area lights is approximated by a point
(exact far from the light).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import bpy
import numpy as np
from mathutils import Vector

from . import compat

# ------------------------------------------------------------------ object scale


def matrix_to_numpy(m) -> np.ndarray:
    return np.array([list(row) for row in m], dtype=np.float64)


def object_scale(obj, matrix=None) -> tuple[float, str | None]:
    """``(uniform scale, warning)`` of an object's world matrix.

    A non-uniform scale gives the geometric mean (the volume-preserving
    uniform scale) and a warning.
    """
    m = obj.matrix_world if matrix is None else matrix
    sx, sy, sz = (abs(v) for v in m.to_scale())
    mean = (max(sx, 1e-30) * max(sy, 1e-30) * max(sz, 1e-30)) ** (1.0 / 3.0)
    if max(sx, sy, sz) - min(sx, sy, sz) > 1e-4 * max(sx, sy, sz):
        return mean, (f"'{obj.name}' has a non-uniform scale ({sx:.4g}, {sy:.4g}, {sz:.4g}); the "
                      f"optical scale uses their geometric mean {mean:.4g}: apply the scale "
                      "(Ctrl+A) for exact units")
    return mean, None


def mm_per_unit(obj, scene, matrix=None) -> tuple[float, str | None]:
    """Millimetres per object unit: ``scale_length * 1000 * uniform object scale``,
    or the object's override.  Returns ``(mm_per_unit, warning or None)``."""
    settings = obj.translucency
    if settings.use_mm_per_unit_override:
        return float(settings.mm_per_unit), None
    scale, warning = object_scale(obj, matrix)
    return float(scene.unit_settings.scale_length) * 1000.0 * scale, warning


def metres_per_world_unit(obj, scene, mm: float, matrix=None) -> float:
    """Metres per *world* unit implied by ``mm`` per object unit (for light falloff)."""
    scale, _ = object_scale(obj, matrix)
    return mm * 1e-3 / max(scale, 1e-30)


# ------------------------------------------------------------------ mesh access


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """``(V float64 (n, 3), F int64 (m, 3))`` of a mesh's loop triangles (mesh space)."""
    n = len(mesh.vertices)
    co = np.empty(n * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    tris = mesh.loop_triangles
    if len(tris) == 0 and len(mesh.polygons) > 0:
        mesh.calc_loop_triangles()
        tris = mesh.loop_triangles
    f = np.empty(len(tris) * 3, dtype=np.int32)
    tris.foreach_get("vertices", f)
    return co.reshape(-1, 3).astype(np.float64), f.reshape(-1, 3).astype(np.int64)


def vertex_positions(mesh) -> np.ndarray:
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def evaluated_triangles(obj, depsgraph) -> tuple[np.ndarray, np.ndarray]:
    """The object's evaluated mesh (after modifiers), triangulated, in object space."""
    obj_eval = obj.evaluated_get(depsgraph)
    mesh = obj_eval.to_mesh()
    try:
        return mesh_arrays(mesh)
    finally:
        obj_eval.to_mesh_clear()


def evaluated_positions(obj, depsgraph) -> np.ndarray:
    obj_eval = obj.evaluated_get(depsgraph)
    mesh = obj_eval.data if obj_eval.type == 'MESH' else None
    if mesh is None:
        return np.zeros((0, 3))
    return vertex_positions(mesh)


def array_digest(*arrays) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def mesh_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; zero-area vertices get +Z)."""
    n = np.zeros_like(V)
    if len(F):
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        for k in range(3):
            np.add.at(n, F[:, k], fn)
    length = np.linalg.norm(n, axis=1)
    bad = length <= 1e-30
    n[bad] = (0.0, 0.0, 1.0)
    length[bad] = 1.0
    return n / length[:, None]


# ------------------------------------------------------------------ lights


def _light_color(data) -> tuple[float, float, float]:
    c = np.array(tuple(data.color)[:3], dtype=np.float64)
    if getattr(data, "use_temperature", False) and hasattr(data, "temperature_color"):
        c = c * np.array(tuple(data.temperature_color)[:3], dtype=np.float64)
    return tuple(float(x) for x in c)


def area_light_area(data, matrix) -> float:
    """Area of an area light in world units^2 (its object scale included)."""
    sx, sy, _ = (abs(v) for v in matrix.to_scale())
    a = data.size * sx
    b = (data.size_y if data.shape in {'RECTANGLE', 'ELLIPSE'} else data.size) * sy
    if data.shape in {'DISK', 'ELLIPSE'}:
        return math.pi * 0.25 * a * b
    return a * b


def convert_light(data, light_matrix, to_object, metres_per_bu: float, name: str = ""):
    """One Blender light (evaluated data + world matrix) -> engine ``Light`` in object space.

    ``to_object``: the inverse world matrix of the translucent object.
    Returns ``None`` for a light that emits nothing.  See the module docstring
    for the factors.
    """
    from ..translucency_addon.scene.lights import Light

    power = float(data.energy) * 2.0 ** float(getattr(data, "exposure", 0.0))
    color = _light_color(data)
    if power <= 0.0 or max(color) <= 0.0:
        return None
    pos = to_object @ light_matrix.translation
    world_dir = (light_matrix.to_3x3() @ Vector((0.0, 0.0, -1.0))).normalized()
    obj_dir = to_object.to_3x3() @ world_dir
    if obj_dir.length <= 0:
        return None
    obj_dir.normalize()
    position = (float(pos.x), float(pos.y), float(pos.z))
    direction = (float(obj_dir.x), float(obj_dir.y), float(obj_dir.z))
    falloff = metres_per_bu * metres_per_bu
    kind = data.type
    if kind == 'SUN':
        return Light("sun", color=color, irradiance=power, direction=direction, name=name)
    # Blender's Radius (world units) in object units: a sphere light's soft shadow and horizon
    scale = to_object.to_scale()
    radius = float(getattr(data, "shadow_soft_size", 0.0)) * (abs(scale.x) + abs(scale.y) + abs(scale.z)) / 3.0
    if kind == 'POINT':
        return Light("point", color=color, intensity=power / (4.0 * math.pi) * falloff,
                     position=position, direction=direction, name=name, radius=radius)
    if kind == 'SPOT':
        return Light("spot", color=color, intensity=power / (4.0 * math.pi) * falloff,
                     position=position, direction=direction, spot_size=float(data.spot_size),
                     spot_blend=float(data.spot_blend), name=name, radius=radius)
    if kind == 'AREA':
        intensity = power / math.pi
        if not getattr(data, "normalize", True):
            intensity *= area_light_area(data, light_matrix)
        # The emitter's full edges in object space (Blender scales an area light with its object),
        # integrated over by the engine (scene.lights.emitter_samples).
        sx = data.size
        sy = data.size_y if data.shape in {'RECTANGLE', 'ELLIPSE'} else data.size
        m3 = to_object.to_3x3() @ light_matrix.to_3x3()
        ex, ey = m3 @ Vector((sx, 0.0, 0.0)), m3 @ Vector((0.0, sy, 0.0))
        return Light("area", color=color, intensity=intensity * falloff, position=position,
                     direction=direction, name=name,
                     shape="ellipse" if data.shape in {'DISK', 'ELLIPSE'} else "rectangle",
                     edge_x=(float(ex.x), float(ex.y), float(ex.z)), edge_y=(float(ey.x), float(ey.y), float(ey.z)))
    return None


def collect_lights(depsgraph, obj_matrix, metres_per_bu: float) -> list:
    """Every light visible in ``depsgraph`` (viewport or render), converted to object space.

    Light instances (e.g. lights in an instanced collection) are included.
    """
    to_object = obj_matrix.inverted_safe()
    lights = []
    for inst in depsgraph.object_instances:
        ob = inst.object
        if ob.type != 'LIGHT':
            continue
        light = convert_light(ob.data, inst.matrix_world.copy(), to_object, metres_per_bu,
                              name=ob.original.name if ob.original else ob.name)
        if light is not None:
            lights.append(light)
    return lights


# ------------------------------------------------------------------ world


def _follow_reroutes(socket):
    node = socket.links[0].from_node if socket.is_linked and socket.links else None
    while node is not None and node.type == 'REROUTE':
        inp = node.inputs[0]
        node = inp.links[0].from_node if inp.is_linked and inp.links else None
    return node


def _active_world_output(tree):
    outputs = [n for n in tree.nodes if n.type == 'OUTPUT_WORLD']
    for n in outputs:
        if getattr(n, "is_active_output", False):
            return n
    return outputs[0] if outputs else None


def world_environment(world, obj_matrix=None, can_render: bool = True):
    """``(Environment or None, warning or None, lights)`` for the scene's world, in the object's space.

    A world without nodes (its colour) and a Background node with unlinked
    Color and Strength are a uniform radiance, exact.  Any other node tree is
    evaluated as Cycles sees it from the object (:mod:`.world`: images, a Sky
    Texture baked by Cycles, Mapping, mixes, Light Path's Is Camera Ray),
    projected to SH, and an HDRI's sun comes back in ``lights`` as a
    directional light.  What :mod:`.world` cannot evaluate falls back to the
    world's viewport colour times the Background strength, with a warning that
    names the node and what to change.
    """
    from ..translucency_addon.scene.lights import Environment
    from ..translucency_addon.scene.world_nodes import WorldNodeError
    from .world import set_status_line, world_light

    if world is None:
        set_status_line("World: none; only the lights reach the object")
        return None, None, ()
    tree = world.node_tree
    if not compat.uses_nodes(world):
        rgb = tuple(float(c) for c in world.color[:3])
        set_status_line(f"World: uniform radiance ({rgb[0]:.3g}, {rgb[1]:.3g}, {rgb[2]:.3g}), exact")
        return (Environment(radiance=rgb) if max(rgb) > 0 else None), None, ()
    out = _active_world_output(tree)
    if out is not None and not out.inputs["Surface"].is_linked:
        set_status_line(f"World: '{world.name}' has nothing linked to its output; it sends no light")
        return None, None, ()
    node = _follow_reroutes(out.inputs["Surface"]) if out is not None else None
    if node is not None and node.type == 'BACKGROUND':
        color_in, strength_in = node.inputs["Color"], node.inputs["Strength"]
        if not color_in.is_linked and not strength_in.is_linked:
            strength = float(strength_in.default_value)
            rgb = tuple(float(c) * strength for c in color_in.default_value[:3])
            set_status_line(f"World: uniform Background ({rgb[0]:.3g}, {rgb[1]:.3g}, {rgb[2]:.3g}) W/(m\u00b2 sr), "
                            "exact")
            return (Environment(radiance=rgb) if max(rgb) > 0 and strength > 0 else None), None, ()
    try:
        env, sun, _ = world_light(world, obj_matrix, can_render)
        return env, None, (() if sun is None else (sun,))
    except WorldNodeError as ex:
        strength = 1.0
        if node is not None and node.type == 'BACKGROUND' and not node.inputs["Strength"].is_linked:
            strength = float(node.inputs["Strength"].default_value)
        rgb = tuple(float(c) * strength for c in world.color[:3])
        warning = (f"world '{world.name}' approximated by its viewport colour x strength "
                   f"({rgb[0]:.3g}, {rgb[1]:.3g}, {rgb[2]:.3g}) (World > Viewport Display): {ex}")
        return (Environment(radiance=rgb) if max(rgb) > 0 else None), warning, ()


def environment_signature(env) -> tuple | None:
    """What a solve depends on in an environment: its uniform radiance and its SH coefficients."""
    if env is None:
        return None
    sh = None if env.sh is None else array_digest(np.asarray(env.sh, dtype=np.float64))
    return (tuple(env.radiance), sh)


# ------------------------------------------------------------------ occluders


@dataclass
class OccluderCache:
    """Per-object cache of occluder triangles, so unchanged meshes are not re-read."""

    meshes: dict = field(default_factory=dict)  # name -> (digest, F)
    key: tuple | None = None
    value: tuple | None = None


def collect_occluders(depsgraph, obj, obj_matrix, cache: OccluderCache | None = None, exclude=()):
    """Other visible mesh objects' evaluated triangles in ``obj``'s space.

    ``exclude``: names of further objects that cast no shadow on ``obj`` (a
    fluid's emitter, the object's own inner parts).  Returns ``((V, F) or
    None, signature)``; the signature changes when an occluder moves (relative
    to ``obj``), deforms, appears or disappears.
    """
    to_object = matrix_to_numpy(obj_matrix.inverted_safe())
    own = obj.original if obj.original is not None else obj
    parts = []
    sig = []
    for inst in depsgraph.object_instances:
        ob = inst.object
        if ob.type != 'MESH':
            continue
        orig = ob.original if ob.original is not None else ob
        if orig == own or orig.name in exclude:
            continue
        mesh = ob.data
        if mesh is None or len(mesh.vertices) == 0:
            continue
        V = vertex_positions(mesh)
        digest = array_digest(V)
        key = orig.name
        cached = cache.meshes.get(key) if cache is not None else None
        if cached is not None and cached[0] == digest and cached[1] is not None:
            F = cached[1]
        else:
            _, F = mesh_arrays(mesh)
            if cache is not None:
                cache.meshes[key] = (digest, F)
        if len(F) == 0:
            continue
        rel = to_object @ matrix_to_numpy(inst.matrix_world)
        sig.append((key, bool(inst.is_instance), tuple(np.round(rel, 9).ravel()), digest))
        parts.append((V @ rel[:3, :3].T + rel[:3, 3], F))
    signature = tuple(sig)
    if cache is not None and cache.key == signature:
        return cache.value, signature
    if not parts:
        value = None
    else:
        Vs, Fs, off = [], [], 0
        for V, F in parts:
            Vs.append(V)
            Fs.append(F + off)
            off += len(V)
        value = (np.vstack(Vs), np.vstack(Fs))
    if cache is not None:
        cache.key, cache.value = signature, value
    return value, signature


# ------------------------------------------------------------------ material


def build_medium(settings, name: str = "custom"):
    """The engine ``Medium`` of settings with ``material_preset``, ``sigma_a`` and ``sigma_s`` (an object's,
    or an inner part's): the preset, or the Custom coefficients named ``name``."""
    from ..translucency_addon.scene.materials import Medium, preset

    if settings.material_preset == 'CUSTOM':
        return Medium(tuple(float(x) for x in settings.sigma_a), tuple(float(x) for x in settings.sigma_s), name)
    return preset(settings.material_preset)


def build_material(settings):
    """The engine ``Material`` of an object's settings (raises ``MaterialError``)."""
    from ..translucency_addon.scene.materials import Material, preset

    medium_b = preset(settings.second_preset) if settings.use_heterogeneity else None
    return Material(build_medium(settings), medium_b, eta=float(settings.eta), name=settings.material_preset.lower())


# ------------------------------------------------------------------ heterogeneity field


def rna_signature(struct, skip=("rna_type", "name", "name_full", "users", "session_uid", "tag",
                                 "is_evaluated", "original", "preview", "is_editable")) -> tuple:
    """A hashable snapshot of a struct's plain (non-pointer) properties."""
    out = []
    for prop in struct.bl_rna.properties:
        ident = prop.identifier
        if ident in skip or prop.type in {'POINTER', 'COLLECTION'}:
            continue
        try:
            value = getattr(struct, ident)
        except Exception:  # noqa: BLE001 - some properties refuse to be read in some states
            continue
        if isinstance(value, set):
            value = tuple(sorted(value))
        elif hasattr(value, "__len__") and not isinstance(value, str):
            value = tuple(value)
        out.append((ident, value))
    return tuple(out)


def texture_signature(tex) -> tuple:
    """Everything that changes what ``tex.evaluate`` returns: its settings and colour ramp."""
    sig = [tex.name, tex.type, rna_signature(tex)]
    if getattr(tex, "use_color_ramp", False) and tex.color_ramp is not None:
        ramp = tex.color_ramp
        sig.append((ramp.interpolation, getattr(ramp, "color_mode", ""),
                    tuple((round(e.position, 7), tuple(e.color)) for e in ramp.elements)))
    image = getattr(tex, "image", None)
    if image is not None:
        sig.append((image.name, tuple(image.size), image.is_dirty))
    return tuple(sig)


def evaluate_texture(tex, points: np.ndarray) -> np.ndarray:
    """The mixing weight from ``Texture.evaluate`` at object-space points, clipped to [0, 1].

    ``Texture.evaluate(value)`` (Blender 4.2 to 5.0) takes a 3-vector and
    returns a 4-vector ``(r, g, b, intensity)``: for greyscale procedural
    textures r, g, b are 0 and the fourth component is the intensity.  With a
    colour ramp r, g, b are the ramp's colour; we then use its luminance
    (Rec. 709), otherwise the intensity.
    """
    ramp = bool(getattr(tex, "use_color_ramp", False))
    evaluate = tex.evaluate
    out = np.empty(len(points))
    if ramp:
        for i, p in enumerate(points.tolist()):
            r, g, b, _a = evaluate(p)
            out[i] = 0.2126 * r + 0.7152 * g + 0.0722 * b
    else:
        for i, p in enumerate(points.tolist()):
            out[i] = evaluate(p)[3]
    return np.clip(np.nan_to_num(out, nan=0.0), 0.0, 1.0)


def attribute_values(attr, label: str) -> np.ndarray:
    """An attribute's values as floats: float, integer and boolean as they are, a colour by its luminance
    (Rec. 709).  ``label`` names it in the error for any other type."""
    n = len(attr.data)
    if attr.data_type in {'FLOAT', 'INT', 'BOOLEAN', 'INT8'}:
        raw = np.empty(n, dtype={'FLOAT': np.float64, 'BOOLEAN': bool}.get(attr.data_type, np.int64))
        attr.data.foreach_get("value", raw)
        return raw.astype(np.float64)
    if attr.data_type in {'FLOAT_COLOR', 'BYTE_COLOR'}:
        raw = np.empty(n * 4, dtype=np.float32)
        attr.data.foreach_get("color", raw)
        rgba = raw.reshape(-1, 4)
        return 0.2126 * rgba[:, 0] + 0.7152 * rgba[:, 1] + 0.0722 * rgba[:, 2]
    from ..translucency_addon.errors import MaterialError

    raise MaterialError(f"{label} has type {attr.data_type}; the field needs a float, integer, boolean or colour "
                        "attribute")


def _attribute_values(mesh, name: str):
    """Per-vertex float values of a mesh attribute, or None if the mesh lacks it."""
    attr = mesh.attributes.get(name)
    if attr is None:
        return None
    values = attribute_values(attr, f"attribute {name!r}")
    if attr.domain == 'POINT':
        return values
    if attr.domain == 'CORNER':
        corner_vert = np.empty(len(mesh.loops), dtype=np.int32)
        mesh.loops.foreach_get("vertex_index", corner_vert)
        total = np.bincount(corner_vert, weights=values, minlength=len(mesh.vertices))
        count = np.bincount(corner_vert, minlength=len(mesh.vertices))
        return total / np.maximum(count, 1)
    from ..translucency_addon.errors import MaterialError

    raise MaterialError(f"attribute {name!r} is on the {attr.domain.lower()} domain; use a point "
                        "(vertex) or face-corner attribute for the field")


def _vertex_group_values(obj, mesh, name: str):
    from ..translucency_addon.errors import MaterialError

    group = obj.vertex_groups.get(name)
    if group is None:
        raise MaterialError(f"'{obj.name}' has no vertex group {name!r} for the heterogeneity field")
    gi = group.index
    values = np.zeros(len(mesh.vertices))
    for v in mesh.vertices:
        for g in v.groups:
            if g.group == gi:
                values[v.index] = g.weight
                break
    return values


def mesh_field(obj, settings, depsgraph, rest=None) -> tuple[np.ndarray, np.ndarray]:
    """``(positions (n, 3) object space, values (n,))`` of an attribute or vertex-group field.

    Read from the evaluated mesh (modifiers carry attributes and groups), or
    from the original mesh when the evaluated one lost the layer.  ``rest``:
    the baked positions of the evaluated mesh's vertices when it is a pose of
    the bake (``ops.deformation``): the field stays attached to the rest pose,
    so its values are placed there.
    """
    from ..translucency_addon.errors import MaterialError

    source = settings.field_source
    name = settings.field_attribute if source == 'ATTRIBUTE' else settings.field_vertex_group
    if not name:
        what = "attribute" if source == 'ATTRIBUTE' else "vertex group"
        raise MaterialError(f"'{obj.name}': Heterogeneous is on but no {what} is chosen for the field")
    if source == 'ATTRIBUTE' and name.startswith("translucency_radiance"):
        raise MaterialError(f"'{obj.name}': the solver's own output {name!r} cannot be the heterogeneity field")
    candidates = []
    if depsgraph is not None:
        candidates.append((obj.evaluated_get(depsgraph).data, False))
    candidates.append((obj.data, True))
    for mesh, is_original in candidates:
        if source == 'ATTRIBUTE':
            values = _attribute_values(mesh, name)
        else:
            # An evaluated mesh whose modifiers dropped the weights has no groups at all.
            values = _vertex_group_values(obj, mesh, name) if is_original or _has_groups(mesh) else None
        if values is not None:
            at_rest = rest is not None and not is_original and len(rest) == len(mesh.vertices)
            return (np.asarray(rest) if at_rest else vertex_positions(mesh)), values
    raise MaterialError(f"'{obj.name}' has no mesh attribute {name!r} for the heterogeneity field")


def _has_groups(mesh) -> bool:
    return any(len(v.groups) for v in mesh.vertices)


def field_signature(obj, settings, depsgraph, vertex_group_epoch=0, rest=None):
    """A hashable key of the field's inputs (``None`` for a homogeneous material).

    Vertex-group weights cannot be read in bulk (one Python loop over the
    vertices), so they are not hashed on every check: ``vertex_group_epoch``
    (bumped by the handlers on mesh edits and frame changes) stands for them.
    ``rest``: as in :func:`mesh_field`.
    """
    from ..translucency_addon.errors import MaterialError

    if not settings.use_heterogeneity:
        return None
    source = settings.field_source
    if source == 'TEXTURE':
        tex = settings.field_texture
        if tex is None:
            raise MaterialError(f"'{obj.name}': Heterogeneous is on but no texture is chosen for the field")
        return ('TEXTURE', texture_signature(tex), round(float(settings.field_scale), 9))
    if source == 'ATTRIBUTE':
        positions, values = mesh_field(obj, settings, depsgraph, rest)
        return ('ATTRIBUTE', settings.field_attribute, array_digest(positions, values))
    return ('VERTEX_GROUP', settings.field_vertex_group, len(obj.data.vertices), vertex_group_epoch)


def sample_field(obj, settings, node_positions, depsgraph, rest=None) -> list[np.ndarray] | None:
    """The mixing weight (0..1) at every level's nodes, or ``None`` when homogeneous.

    ``node_positions``: one (N_l, 3) array per level, object space; ``rest``: as in :func:`mesh_field`.
    """
    if not settings.use_heterogeneity:
        return None
    if settings.field_source == 'TEXTURE':
        from ..translucency_addon.errors import MaterialError

        tex = settings.field_texture
        if tex is None:
            raise MaterialError(f"'{obj.name}': Heterogeneous is on but no texture is chosen for the field")
        scale = float(settings.field_scale)
        return [evaluate_texture(tex, np.asarray(p) * scale) for p in node_positions]
    from ..translucency_addon.scene.fields import vertex_field_at_nodes

    positions, values = mesh_field(obj, settings, depsgraph, rest)
    return [vertex_field_at_nodes(positions, values, p) for p in node_positions]


# ------------------------------------------------------------------ view


def camera_view(scene, depsgraph, obj_matrix):
    """``('PERSP', eye) or ('ORTHO', towards_camera)`` in object space, or None without a camera."""
    cam = scene.camera
    if cam is None:
        return None
    cam_eval = cam.evaluated_get(depsgraph) if depsgraph is not None else cam
    m = cam_eval.matrix_world
    to_object = obj_matrix.inverted_safe()
    if getattr(cam_eval.data, "type", 'PERSP') == 'ORTHO':
        d = to_object.to_3x3() @ (m.to_3x3() @ Vector((0.0, 0.0, 1.0)))
        d.normalize()
        return ('ORTHO', (float(d.x), float(d.y), float(d.z)))
    eye = to_object @ m.translation
    return ('PERSP', (float(eye.x), float(eye.y), float(eye.z)))


def in_camera_view(scene, depsgraph, obj) -> bool:
    """Whether any part of the object's bounding box lies inside the scene camera's frustum.

    Conservative: True without a camera, and True when the box straddles the
    camera plane (the planner only skips objects that are certainly unseen).
    """
    cam = scene.camera
    if cam is None:
        return True
    cam_eval = cam.evaluated_get(depsgraph) if depsgraph is not None else cam
    obj_eval = obj.evaluated_get(depsgraph) if depsgraph is not None else obj
    try:
        r = scene.render
        proj = cam_eval.calc_matrix_camera(depsgraph, x=r.resolution_x, y=r.resolution_y,
                                           scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y)
    except Exception:  # noqa: BLE001 - an unusual camera: assume visible
        return True
    m = proj @ cam_eval.matrix_world.inverted_safe() @ obj_eval.matrix_world
    corners = np.array([tuple(c) + (1.0,) for c in obj_eval.bound_box], dtype=np.float64)
    clip = corners @ np.array(m, dtype=np.float64).T
    w = clip[:, 3]
    if np.any(w <= 1e-9):
        return not np.all(w <= 1e-9)  # all behind the camera: unseen; straddling: assume seen
    ndc = clip[:, :3] / w[:, None]
    # outside if all corners are beyond the same side of one frustum plane
    for axis in range(3):
        if np.all(ndc[:, axis] > 1.0) or np.all(ndc[:, axis] < -1.0):
            return False
    return True


def view_directions(view, positions: np.ndarray) -> np.ndarray | None:
    """Unit vectors from each vertex towards the viewer (None: along the normal); the engine's
    :func:`translucency_addon.frame.view_directions`."""
    from ..translucency_addon.frame import view_directions as towards_viewer

    return towards_viewer(view, positions)


# ------------------------------------------------------------------ single scattering


def viewport_view(obj_matrix):
    """The first 3D viewport's view in object space, like :func:`camera_view`, or None.

    None in background mode (no windows) and when no 3D viewport is open.
    Single scattering uses it for live solves; moving the view alone does not
    trigger a solve (the next live solve, or Solve, picks the new view up).
    """
    try:
        windows = bpy.context.window_manager.windows
    except Exception:  # noqa: BLE001 - no window manager (background) or a restricted context
        return None
    to_object = obj_matrix.inverted_safe()
    for window in windows:
        screen = getattr(window, "screen", None)
        for area in getattr(screen, "areas", ()):
            if area.type != 'VIEW_3D':
                continue
            r3d = getattr(area.spaces.active, "region_3d", None)
            if r3d is None:
                continue
            inv = r3d.view_matrix.inverted_safe()
            if r3d.is_perspective:
                eye = to_object @ inv.translation
                return ('PERSP', (float(eye.x), float(eye.y), float(eye.z)))
            d = to_object.to_3x3() @ (inv.to_3x3() @ Vector((0.0, 0.0, 1.0)))
            d.normalize()
            return ('ORTHO', (float(d.x), float(d.y), float(d.z)))
    return None


def ss_field_fingerprint(obj, settings, depsgraph, field_sig=None) -> str | None:
    """A fingerprint of the heterogeneity field that stays the same across sessions (None: homogeneous).

    Recorded by the single-scattering bake and compared at solve time (a field
    change makes the baked optical depth stale).  Textures: their settings and
    scale; attributes: a digest of positions and values; vertex groups: a
    digest of the weights (one loop over the vertices, so callers cache it per
    :func:`field_signature`).
    """
    if not settings.use_heterogeneity:
        return None
    sig = field_sig if field_sig is not None else field_signature(obj, settings, depsgraph)
    if sig is None:
        return None
    if sig[0] == 'VERTEX_GROUP':
        positions, values = mesh_field(obj, settings, depsgraph)
        sig = ('VERTEX_GROUP', settings.field_vertex_group, array_digest(positions, values))
    return "blender:" + hashlib.sha256(repr(sig).encode("utf-8")).hexdigest()[:32]


def ss_field_sampler(obj, settings, depsgraph, V, quality):
    """The field sampled now (main thread) on the voxel grid the single-scattering bake will use.

    Returns a bpy-free :class:`GridField` the bake thread can call, or None
    for a homogeneous material.
    """
    if not settings.use_heterogeneity:
        return None
    from ..translucency_addon.single_scattering import GridField

    origin, h, shape, points = GridField.grid_points(V, quality)
    values = sample_field(obj, settings, [points], depsgraph)[0]
    return GridField(origin, h, shape, values)


def ss_settings(settings):
    """The engine's :class:`SingleScatteringSettings` of an object's panel settings (validated)."""
    from ..translucency_addon.errors import TranslucencyError
    from ..translucency_addon.single_scattering import SingleScatteringSettings

    s = SingleScatteringSettings(quality=settings.ss_quality.lower(), n_dirs=int(settings.ss_directions),
                                 n_samples=int(settings.ss_samples), sh_order=int(settings.ss_sh_order))
    try:
        return s.validated()
    except ValueError as ex:
        raise TranslucencyError(f"single-scattering settings: {ex}") from None
