# SPDX-License-Identifier: GPL-3.0-or-later
"""Render pass: the solved radiance as the ``Translucency`` AOV of F12 renders.

``translucency.add_to_material`` ("Add to Material") puts, into every material
of the active object (creating one when it has none):

* an Attribute node reading the mesh attribute ``translucency_radiance``
  (the solver's FLOAT_COLOR POINT attribute), feeding
* an AOV Output node writing the ``Translucency`` AOV, which the operator
  registers on every view layer of the scene (``view_layer.aovs``, type COLOR),
* with *Emission* on, also an Emission shader (colour = the attribute) added to
  whatever feeds the Material Output's Surface (through an Add Shader), so the
  beauty pass includes the radiance;
* when the mesh has the single-scattering attribute
  ``translucency_radiance_ss``, the same pair for the ``Translucency_SS`` AOV.

The operator is declarative and idempotent: running it again with the same
options changes nothing, and with other options (Emission off, say) it brings
the material to that state.  ``translucency.remove_from_material`` removes
everything it added, restores the original Surface link, and unregisters the
AOVs when no material uses them any more.  Both operators are undoable.

The nodes are recognised by a custom property ``translucency_role`` (so a user
may rename or move them).  The pass holds the radiance itself, in
W/(m^2 sr) (scene linear, no exposure applied), and is zero wherever a surface
has no such attribute.  EEVEE and Cycles both evaluate it.

Reading the pass back without Blender (tests, demo) is ``tools/exr.py``'s
``read_exr(path)["ViewLayer.Translucency.R"]``, outside the shipped extension.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, FloatProperty

from .attributes import ATTRIBUTE_NAME as ATTRIBUTE  # the one spelling of the names
from .attributes import SS_ATTRIBUTE_NAME as SS_ATTRIBUTE
from .attributes import carrier_modifier

AOV_NAME = "Translucency"
SS_AOV_NAME = "Translucency_SS"
ROLE = "translucency_role"

# role -> (node type, default name)
_NODES = {
    "attribute": ("ShaderNodeAttribute", "Translucency Attribute"),
    "aov": ("ShaderNodeOutputAOV", "Translucency AOV"),
    "ss_attribute": ("ShaderNodeAttribute", "Translucency SS Attribute"),
    "ss_aov": ("ShaderNodeOutputAOV", "Translucency SS AOV"),
    "emission": ("ShaderNodeEmission", "Translucency Emission"),
    "add_shader": ("ShaderNodeAddShader", "Translucency Add Shader"),
}


# --- node helpers ------------------------------------------------------------------------

def _role_nodes(tree, role):
    return [node for node in tree.nodes if node.get(ROLE) == role]


def _new_node(tree, role, location):
    bl_idname, name = _NODES[role]
    node = tree.nodes.new(bl_idname)
    node.name = name
    node.label = name
    node[ROLE] = role
    node.location = location
    return node


def _ensure_node(tree, role, location):
    nodes = _role_nodes(tree, role)
    for extra in nodes[1:]:  # a duplicated node (Shift+D keeps custom properties)
        tree.nodes.remove(extra)
    return nodes[0] if nodes else _new_node(tree, role, location)


def _link(tree, from_socket, to_socket):
    for link in list(to_socket.links):
        if link.from_socket != from_socket:
            tree.links.remove(link)
    if not to_socket.is_linked:
        tree.links.new(from_socket, to_socket)


def _output_nodes(tree):
    """The active Material Output nodes (one for all engines, or one per engine)."""
    outputs = []
    for target in ('ALL', 'EEVEE', 'CYCLES'):
        node = tree.get_output_node(target)
        if node is not None and node not in outputs:
            outputs.append(node)
    return outputs


def has_translucency_nodes(material) -> bool:
    tree = getattr(material, "node_tree", None)
    return tree is not None and any(node.get(ROLE) for node in tree.nodes)


def material_uses_aov(material, aov_name) -> bool:
    tree = getattr(material, "node_tree", None)
    if tree is None:
        return False
    return any(node.get(ROLE) in {"aov", "ss_aov"} and node.aov_name == aov_name for node in tree.nodes)


def _ensure_node_tree(material):
    from .compat import ensure_node_tree

    return ensure_node_tree(material)


def _add_aov_pair(tree, attr_role, aov_role, attribute, aov_name, origin, row):
    x, y = origin
    attr = _ensure_node(tree, attr_role, (x - 500, y - 260 - row * 200))
    attr.attribute_type = 'GEOMETRY'
    attr.attribute_name = attribute
    aov = _ensure_node(tree, aov_role, (x, y - 260 - row * 200))
    aov.aov_name = aov_name
    _link(tree, attr.outputs["Color"], aov.inputs["Color"])
    return attr


def _add_emission(tree, attr, strength, origin):
    x, y = origin
    emission = _ensure_node(tree, "emission", (x - 250, y - 100))
    emission.inputs["Strength"].default_value = strength
    _link(tree, attr.outputs["Color"], emission.inputs["Color"])
    for output in _output_nodes(tree):
        surface = output.inputs["Surface"]
        mine = [n for n in _role_nodes(tree, "add_shader") if n.get("translucency_output") == output.name]
        if mine:
            add = mine[0]
        else:
            add = _new_node(tree, "add_shader", (output.location.x - 180, output.location.y))
            add["translucency_output"] = output.name
            add.name = f"Translucency Add Shader ({output.name})"
            previous = surface.links[0].from_socket if surface.is_linked else None
            for link in list(surface.links):
                tree.links.remove(link)
            if previous is not None:
                tree.links.new(previous, add.inputs[0])
            output.location.x += 200
        _link(tree, add.outputs["Shader"], surface)
        _link(tree, emission.outputs["Emission"], add.inputs[1])


def _remove_emission(tree):
    for add in _role_nodes(tree, "add_shader"):
        # Restore: whatever fed the Add Shader's first input goes back to the output.
        previous = add.inputs[0].links[0].from_socket if add.inputs[0].is_linked else None
        targets = [link.to_socket for link in add.outputs["Shader"].links]
        tree.nodes.remove(add)
        if previous is not None:
            for socket in targets:
                if not socket.is_linked:
                    tree.links.new(previous, socket)
    for node in _role_nodes(tree, "emission"):
        tree.nodes.remove(node)


def _remove_roles(tree, roles):
    for role in roles:
        for node in _role_nodes(tree, role):
            tree.nodes.remove(node)


def add_to_material(material, *, emission=False, emission_strength=1.0, single_scattering=False) -> None:
    """Bring ``material``'s nodes to the requested state (idempotent)."""
    tree = _ensure_node_tree(material)
    outputs = _output_nodes(tree)
    origin = (outputs[0].location.x, outputs[0].location.y) if outputs else (300.0, 300.0)
    attr = _add_aov_pair(tree, "attribute", "aov", ATTRIBUTE, AOV_NAME, origin, 0)
    if single_scattering:
        _add_aov_pair(tree, "ss_attribute", "ss_aov", SS_ATTRIBUTE, SS_AOV_NAME, origin, 1)
    else:
        _remove_roles(tree, ("ss_attribute", "ss_aov"))
    if emission:
        _add_emission(tree, attr, emission_strength, origin)
    else:
        _remove_emission(tree)


def remove_from_material(material) -> bool:
    """Remove every node :func:`add_to_material` added; True if there were any."""
    tree = getattr(material, "node_tree", None)
    if tree is None or not has_translucency_nodes(material):
        return False
    _remove_emission(tree)
    _remove_roles(tree, ("attribute", "aov", "ss_attribute", "ss_aov"))
    return True


# --- AOVs --------------------------------------------------------------------------------

def ensure_aov(view_layer, name):
    aov = view_layer.aovs.get(name) if hasattr(view_layer.aovs, "get") else None
    if aov is None:
        aov = next((a for a in view_layer.aovs if a.name == name), None)
    if aov is None:
        aov = view_layer.aovs.add()
        aov.name = name
    aov.type = 'COLOR'
    return aov


def remove_aov(view_layer, name) -> None:
    for aov in list(view_layer.aovs):
        if aov.name == name:
            view_layer.aovs.remove(aov)


def sync_aovs(scene) -> None:
    """Register the AOVs some material writes and drop ours that none does."""
    for name in (AOV_NAME, SS_AOV_NAME):
        used = any(material_uses_aov(m, name) for m in bpy.data.materials)
        for view_layer in scene.view_layers:
            if used:
                ensure_aov(view_layer, name)
            else:
                remove_aov(view_layer, name)


def object_materials(obj, create=False):
    """Unique materials of ``obj``; with ``create``, a new one when it has none."""
    materials = []
    for slot in obj.material_slots:
        if slot.material is not None and slot.material not in materials:
            materials.append(slot.material)
    if not materials and create:
        material = bpy.data.materials.new(name=f"{obj.name} Translucency")
        _ensure_node_tree(material)
        if len(obj.material_slots) == 0:
            obj.data.materials.append(material)
        else:
            for slot in obj.material_slots:
                slot.material = material
        materials.append(material)
    return materials


# --- operators -----------------------------------------------------------------------------

SHADED_TYPES = {'MESH', 'POINTCLOUD'}  # what carries the attribute: a mesh, or a fluid's point cloud


def _poll_mesh(context):
    obj = context.object
    return obj is not None and obj.type in SHADED_TYPES


class TRANSLUCENCY_OT_add_to_material(bpy.types.Operator):
    """Write the solved radiance into a "Translucency" render pass (AOV) from every material of the object"""

    bl_idname = "translucency.add_to_material"
    bl_label = "Add to Material"
    bl_options = {'REGISTER', 'UNDO'}

    use_emission: BoolProperty(
        name="Emission",
        description="Also add the radiance as an Emission shader to the surface, so the beauty pass includes it",
        default=False,
    )
    emission_strength: FloatProperty(
        name="Strength",
        description="Strength of the added Emission shader",
        default=1.0,
        min=0.0,
        soft_max=10.0,
    )
    use_single_scattering: BoolProperty(
        name="Single Scattering Pass",
        description=f"Also write the '{SS_AOV_NAME}' AOV when the mesh has the '{SS_ATTRIBUTE}' attribute",
        default=True,
    )

    @classmethod
    def poll(cls, context):
        return _poll_mesh(context)

    def execute(self, context):
        obj = context.object
        single = self.use_single_scattering and obj.data.attributes.get(SS_ATTRIBUTE) is not None
        materials = object_materials(obj, create=True)
        for material in materials:
            add_to_material(material, emission=self.use_emission,
                            emission_strength=self.emission_strength, single_scattering=single)
        sync_aovs(context.scene)
        passes = AOV_NAME + (f" and {SS_AOV_NAME}" if single else "")
        self.report({'INFO'}, f"{passes} pass added to {len(materials)} material(s)")
        if obj.data.attributes.get(ATTRIBUTE) is None and carrier_modifier(obj) is None:
            self.report({'WARNING'}, f"'{obj.name}' has no solved radiance yet: the pass stays black until a "
                                          "solve (press Solve; renders solve every frame of a baked object)")
        return {'FINISHED'}


class TRANSLUCENCY_OT_remove_from_material(bpy.types.Operator):
    """Remove the Translucency render pass nodes from every material of the object"""

    bl_idname = "translucency.remove_from_material"
    bl_label = "Remove from Material"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        return _poll_mesh(context)

    def execute(self, context):
        removed = sum(remove_from_material(m) for m in object_materials(context.object))
        sync_aovs(context.scene)
        self.report({'INFO'}, f"Translucency pass removed from {removed} material(s)")
        return {'FINISHED'}


CLASSES = (TRANSLUCENCY_OT_add_to_material, TRANSLUCENCY_OT_remove_from_material)


def draw_settings(layout, context) -> None:
    """Render-pass rows for the Translucency panel."""
    obj = getattr(context, "object", None)
    box = layout.box()
    box.label(text="Render Pass", icon='RENDERLAYERS')
    if obj is None or obj.type not in SHADED_TYPES:
        box.label(text="Select a mesh or point-cloud object")
        return
    row = box.row(align=True)
    row.operator(TRANSLUCENCY_OT_add_to_material.bl_idname, icon='NODE_MATERIAL')
    row.operator(TRANSLUCENCY_OT_remove_from_material.bl_idname, text="", icon='X')
    materials = object_materials(obj)
    wired = sum(has_translucency_nodes(m) for m in materials)
    if materials:
        box.label(text=f"AOV '{AOV_NAME}' in {wired} of {len(materials)} material(s)")
    else:
        box.label(text="No material yet (Add to Material creates one)")


# --- render settings helpers (tests, demo, scripts) --------------------------------------

def eevee_engine_id() -> str:
    """EEVEE's ``scene.render.engine`` id (:func:`.compat.eevee_engine_id`)."""
    from .compat import eevee_engine_id as engine_id

    return engine_id()


def configure_output(image_settings, file_format, codec='ZIP') -> None:
    """Set ``image_settings`` to write ``'PNG'`` or a multilayer ``'OPEN_EXR_MULTILAYER'`` (all passes).

    Blender 5.0 first needs the media type (``MULTI_LAYER_IMAGE`` for a
    multilayer EXR); 4.x has only the file format.
    """
    from .compat import set_media_type

    set_media_type(image_settings, file_format == 'OPEN_EXR_MULTILAYER')
    image_settings.file_format = file_format
    if file_format.startswith('OPEN_EXR'):
        image_settings.exr_codec = codec
        image_settings.color_depth = '32'
    elif file_format == 'PNG':
        image_settings.color_mode = 'RGBA'
        image_settings.color_depth = '8'
