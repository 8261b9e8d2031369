# SPDX-License-Identifier: GPL-3.0-or-later
"""Where results go on the mesh: the radiance attributes the overlay, the AOV and renders read.

* :data:`ATTRIBUTE_NAME` = ``"translucency_radiance"``: a ``FLOAT_COLOR``
  attribute on the ``POINT`` domain of the object's **original** mesh
  (``obj.data``), RGB = outgoing radiance in W/(m^2 sr), alpha = 1; modifiers
  carry it to the evaluated mesh.
* :data:`SS_ATTRIBUTE_NAME` = ``"translucency_radiance_ss"``: single
  scattering alone, when the object's "Split Pass" is on.

The attribute lives on ``obj.data``: a mesh's vertices or a point cloud's
points (a Fluid source's target may be either).  Where the geometry Blender
renders is *generated* by modifiers (Mantaflow's liquid mesh, Geometry Nodes,
a Subdivision Surface), an attribute on ``obj.data`` never reaches it; there
:func:`write_radiance_carried` writes one value per *evaluated* point into a
hidden **carrier** mesh (one vertex per point, not linked to any scene) and a
Geometry Nodes modifier, ``Translucency Radiance``, last in the object's
stack, stores it on the evaluated geometry by index (Object Info -> Sample
Index -> Store Named Attribute), so renders, the AOV and the viewport read
the same attribute.  :func:`uses_carrier` says which path an object takes.

The only place these names are spelled; ``overlay`` and ``render_pass`` import them.
"""

from __future__ import annotations

import threading

import bpy
import numpy as np

from . import state

ATTRIBUTE_NAME = "translucency_radiance"
SS_ATTRIBUTE_NAME = "translucency_radiance_ss"
ATTRIBUTE_DOMAIN = 'POINT'
ATTRIBUTE_TYPE = 'FLOAT_COLOR'
CARRIER_MODIFIER = "Translucency Radiance"
CARRIER_ROLE = "translucency_role"  # custom property of the carrier object and its node group
CARRIER = "radiance_carrier"
_CARRIER_NODE = "Translucency Carrier"  # the Object Info node that points at the carrier


def point_count(data) -> int:
    """Vertices of a mesh, points of a point cloud."""
    return len(data.vertices) if hasattr(data, "vertices") else len(data.points)


def write_radiance(obj, rgb: np.ndarray, name: str = ATTRIBUTE_NAME) -> None:
    """Write (n, 3) radiance into ``obj.data``'s ``translucency_radiance`` attribute (a mesh or a point cloud).

    Only the attribute's values change: never the topology, never another
    attribute.  A layer of the wrong type or domain under our name is replaced.
    """
    mesh = obj.data
    n = point_count(mesh)
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.shape != (n, 3):
        raise ValueError(f"radiance has shape {rgb.shape}, the {mesh.id_type.lower()} has {n} points")
    attr = mesh.attributes.get(name)
    if attr is not None and (attr.domain != ATTRIBUTE_DOMAIN or attr.data_type != ATTRIBUTE_TYPE):
        mesh.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = mesh.attributes.new(name, ATTRIBUTE_TYPE, ATTRIBUTE_DOMAIN)
    rgba = np.ones((n, 4), dtype=np.float32)
    rgba[:, :3] = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    attr.data.foreach_set("color", rgba.ravel())
    state.mark_own_write(obj.name)
    state.count("writes")
    mesh.update_tag()


def read_radiance(obj, name: str = ATTRIBUTE_NAME) -> np.ndarray | None:
    """The attribute (default: the total radiance) as (n, 3) float32, or None."""
    mesh = obj.data
    attr = mesh.attributes.get(name) if mesh is not None else None
    if attr is None or attr.domain != ATTRIBUTE_DOMAIN or attr.data_type != ATTRIBUTE_TYPE:
        return None
    rgba = np.empty(len(attr.data) * 4, dtype=np.float32)
    attr.data.foreach_get("color", rgba)
    return rgba.reshape(-1, 4)[:, :3].copy()


def remove_attribute(obj, name: str = ATTRIBUTE_NAME) -> bool:
    mesh = obj.data
    attr = mesh.attributes.get(name) if mesh is not None else None
    if attr is None:
        return False
    mesh.attributes.remove(attr)
    mesh.update_tag()
    return True


def attribute_ok(obj, name: str = ATTRIBUTE_NAME) -> bool:
    attr = obj.data.attributes.get(name)
    return (attr is not None and attr.domain == ATTRIBUTE_DOMAIN and attr.data_type == ATTRIBUTE_TYPE
            and len(attr.data) == point_count(obj.data))


# ------------------------------------------------------------------ generated geometry: the carrier


def carrier_modifier(obj):
    """The object's ``Translucency Radiance`` modifier (recognised by its node group), or None."""
    for mod in obj.modifiers:
        group = getattr(mod, "node_group", None) if mod.type == 'NODES' else None
        if group is not None and group.get(CARRIER_ROLE) == CARRIER:
            return mod
    return None


def _carrier_object(mod):
    node = mod.node_group.nodes.get(_CARRIER_NODE) if mod is not None else None
    return node.inputs["Object"].default_value if node is not None else None


def uses_carrier(obj, n_evaluated: int) -> bool:
    """Whether the radiance must go through the carrier: a modifier (other than ours) makes the geometry
    Blender renders, or it has another point count than ``obj.data``."""
    ours = carrier_modifier(obj)
    return n_evaluated != point_count(obj.data) or any(m != ours for m in obj.modifiers)


def _build_group(name: str, carrier):
    """Object Info (the carrier) -> Sample Index (its attribute at this point's index) -> Store Named Attribute."""
    group = bpy.data.node_groups.new(name, 'GeometryNodeTree')
    group[CARRIER_ROLE] = CARRIER
    group.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    group.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    nodes, links = group.nodes, group.links
    inp, out = nodes.new('NodeGroupInput'), nodes.new('NodeGroupOutput')
    info = nodes.new('GeometryNodeObjectInfo')
    info.name = info.label = _CARRIER_NODE
    info.inputs["Object"].default_value = carrier
    value = nodes.new('GeometryNodeInputNamedAttribute')
    value.data_type = ATTRIBUTE_TYPE
    value.inputs["Name"].default_value = ATTRIBUTE_NAME
    sample = nodes.new('GeometryNodeSampleIndex')
    sample.data_type, sample.domain = ATTRIBUTE_TYPE, ATTRIBUTE_DOMAIN
    store = nodes.new('GeometryNodeStoreNamedAttribute')
    store.data_type, store.domain = ATTRIBUTE_TYPE, ATTRIBUTE_DOMAIN
    store.inputs["Name"].default_value = ATTRIBUTE_NAME
    links.new(info.outputs["Geometry"], sample.inputs["Geometry"])
    links.new(value.outputs["Attribute"], sample.inputs["Value"])
    links.new(nodes.new('GeometryNodeInputIndex').outputs["Index"], sample.inputs["Index"])
    links.new(inp.outputs[0], store.inputs["Geometry"])
    links.new(sample.outputs["Value"], store.inputs["Value"])
    links.new(store.outputs["Geometry"], out.inputs[0])
    return group


def _ensure_carrier(obj):
    """The carrier object of ``obj``, made (with its node group and modifier) when missing; the modifier last."""
    mod = carrier_modifier(obj)
    carrier = _carrier_object(mod)
    if carrier is None:
        if threading.current_thread() is not threading.main_thread():
            from ..translucency_addon.errors import TranslucencyError

            raise TranslucencyError(f"'{obj.name}': its radiance needs the '{CARRIER_MODIFIER}' modifier, which can be "
                                    "added only outside a render: solve once in the viewport (Solve) first")
        remove_carrier(obj)
        name = f"{obj.name} {CARRIER_MODIFIER}"
        carrier = bpy.data.objects.new(name, bpy.data.meshes.new(name))
        carrier[CARRIER_ROLE] = CARRIER
        mod = obj.modifiers.new(CARRIER_MODIFIER, 'NODES')
        mod.node_group = _build_group(f"{CARRIER_MODIFIER} ({obj.name})", carrier)
    index = list(obj.modifiers).index(mod)
    if index != len(obj.modifiers) - 1 and threading.current_thread() is threading.main_thread():
        obj.modifiers.move(index, len(obj.modifiers) - 1)
    return carrier


def carrier_ok(obj, n_evaluated: int) -> bool:
    """The carrier modifier is in place and its carrier holds a current-length attribute."""
    carrier = _carrier_object(carrier_modifier(obj))
    return (carrier is not None and carrier.type == 'MESH' and len(carrier.data.vertices) == n_evaluated
            and attribute_ok(carrier))


def write_radiance_carried(obj, rgb: np.ndarray) -> None:
    """Write (n, 3) radiance for the n points of ``obj``'s *evaluated* geometry, through its carrier."""
    carrier = _ensure_carrier(obj)
    rgb = np.asarray(rgb)
    mesh = carrier.data
    if len(mesh.vertices) != len(rgb):
        mesh.clear_geometry()
        mesh.vertices.add(len(rgb))
    write_radiance(carrier, rgb)
    state.mark_own_write(obj.name)


def remove_carrier(obj) -> bool:
    """Remove ``obj``'s carrier modifier, its node group and the carrier object; True if there was one."""
    mod = carrier_modifier(obj)
    if mod is None:
        return False
    group, carrier = mod.node_group, _carrier_object(mod)
    obj.modifiers.remove(mod)
    if group.users == 0:
        bpy.data.node_groups.remove(group)
    if carrier is not None and carrier.get(CARRIER_ROLE) == CARRIER and carrier.users == 0:
        mesh = carrier.data
        bpy.data.objects.remove(carrier)
        if mesh is not None and mesh.users == 0:
            bpy.data.meshes.remove(mesh)
    return True
