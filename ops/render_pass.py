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

:func:`read_exr` reads a (multilayer) OpenEXR file without Blender, for the
tests and the demo: ``read_exr(path)["ViewLayer.Translucency.R"]``.
"""

from __future__ import annotations

import struct
import zlib

import bpy
from bpy.props import BoolProperty, FloatProperty

from .attributes import ATTRIBUTE_NAME as ATTRIBUTE  # the one spelling of the names
from .attributes import SS_ATTRIBUTE_NAME as SS_ATTRIBUTE

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


def _role_node(tree, role):
    nodes = _role_nodes(tree, role)
    return nodes[0] if nodes else None


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

def _poll_mesh(context):
    obj = context.object
    return obj is not None and obj.type == 'MESH'


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
        if obj.data.attributes.get(ATTRIBUTE) is None:
            self.report({'WARNING'}, f"'{obj.name}' has no solved radiance yet: the pass stays black until a solve")
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
    if obj is None or obj.type != 'MESH':
        box.label(text="Select a mesh object")
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


# --- reading the pass back: a small OpenEXR reader (no Blender needed) --------------------

_PIXEL_TYPES = {0: ("<u4", 4), 1: ("<f2", 2), 2: ("<f4", 4)}
_LINES_PER_BLOCK = {0: 1, 1: 1, 2: 1, 3: 16}  # NONE, RLE, ZIPS, ZIP
_COMPRESSION_NAMES = {0: "NONE", 1: "RLE", 2: "ZIPS", 3: "ZIP", 4: "PIZ", 5: "PXR24",
                      6: "B44", 7: "B44A", 8: "DWAA", 9: "DWAB"}


def _undo_predictor(raw: bytes) -> bytes:
    import numpy as np

    t = np.frombuffer(raw, np.uint8).astype(np.int64)
    if t.size:
        t[1:] -= 128
        t = np.cumsum(t) & 0xFF  # t[i] = t[i-1] + t[i] - 128 (mod 256)
    t = t.astype(np.uint8)
    half = (t.size + 1) // 2
    out = np.empty_like(t)
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def _rle_decode(data: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(data):
        count = struct.unpack_from("b", data, i)[0]
        i += 1
        if count < 0:
            out += data[i:i - count]
            i -= count
        else:
            out += data[i:i + 1] * (count + 1)
            i += 1
    return bytes(out)


def _parse_header(data: bytes, pos: int):
    header = {}
    while data[pos] != 0:
        end = data.index(b"\0", pos)
        name = data[pos:end].decode()
        pos = end + 1
        end = data.index(b"\0", pos)
        kind = data[pos:end].decode()
        pos = end + 1
        size = struct.unpack_from("<i", data, pos)[0]
        pos += 4
        header[name] = (kind, data[pos:pos + size])
        pos += size
    return header, pos + 1


def _parse_channels(raw: bytes, path):
    channels = []
    i = 0
    while raw[i] != 0:
        end = raw.index(b"\0", i)
        name = raw[i:end].decode()
        pixel_type, _linear, xs, ys = struct.unpack_from("<iB3xii", raw, end + 1)
        if (xs, ys) != (1, 1):
            raise ValueError(f"{path}: subsampled channel {name!r} is not supported")
        channels.append((name, pixel_type))
        i = end + 1 + 16
    return channels


class _Part:
    def __init__(self, header, path):
        if header.get("type", ("", b"scanlineimage"))[1].rstrip(b"\0") != b"scanlineimage":
            raise ValueError(f"{path}: only scanline OpenEXR images are supported")
        self.channels = _parse_channels(header["channels"][1], path)
        self.compression = header["compression"][1][0]
        if self.compression not in _LINES_PER_BLOCK:
            raise ValueError(f"{path}: {_COMPRESSION_NAMES.get(self.compression, self.compression)} compression "
                             "is not supported (save with ZIP, ZIPS, RLE or no compression)")
        self.xmin, self.ymin, self.xmax, self.ymax = struct.unpack("<iiii", header["dataWindow"][1])
        self.width = self.xmax - self.xmin + 1
        self.height = self.ymax - self.ymin + 1
        self.lines = _LINES_PER_BLOCK[self.compression]
        if "chunkCount" in header:
            self.n_chunks = struct.unpack("<i", header["chunkCount"][1])[0]
        else:
            self.n_chunks = (self.height + self.lines - 1) // self.lines
        self.row_bytes = sum(_PIXEL_TYPES[t][1] for _n, t in self.channels) * self.width

    def decode(self, chunk: bytes, y: int, out: dict, path) -> None:
        import numpy as np

        n_lines = min(self.lines, self.ymax + 1 - y)
        expected = self.row_bytes * n_lines
        if len(chunk) != expected:  # stored raw when compression did not help
            if self.compression == 1:
                chunk = _undo_predictor(_rle_decode(chunk))
            elif self.compression in (2, 3):
                chunk = _undo_predictor(zlib.decompress(chunk))
        if len(chunk) != expected:
            raise ValueError(f"{path}: corrupt chunk at scanline {y}")
        at = 0
        for line in range(n_lines):
            row = y - self.ymin + line
            for name, pixel_type in self.channels:
                dtype, nbytes = _PIXEL_TYPES[pixel_type]
                out[name][row] = np.frombuffer(chunk, dtype, self.width, at).astype(np.float32)
                at += nbytes * self.width


def read_exr(path) -> dict:
    """Channels of a scanline OpenEXR file: ``{name: (height, width) float32}``.

    Single-part and multi-part files (Blender 5.0 writes a multilayer EXR as
    one part per pass, 4.x as one part).  Row 0 is the top of the image.
    Supports the NONE, RLE, ZIPS and ZIP codecs (Blender's default is ZIP)
    and raises ``ValueError`` for others.  Multilayer files name channels
    ``<view layer>.<pass>.<channel>``, e.g. ``ViewLayer.Translucency.R``.
    """
    import numpy as np

    with open(path, "rb") as fh:
        data = fh.read()
    if data[:4] != b"\x76\x2f\x31\x01":
        raise ValueError(f"{path}: not an OpenEXR file")
    flags = struct.unpack_from("<I", data, 4)[0]
    if flags & 0x200 or flags & 0x800:
        raise ValueError(f"{path}: tiled or deep OpenEXR files are not supported")
    multipart = bool(flags & 0x1000)
    pos = 8
    parts = []
    while True:
        header, pos = _parse_header(data, pos)
        parts.append(_Part(header, path))
        if not multipart or data[pos] == 0:
            break
    if multipart:
        pos += 1  # the empty header that ends the list
    offsets = []
    for part in parts:
        offsets.append(struct.unpack_from(f"<{part.n_chunks}Q", data, pos))
        pos += 8 * part.n_chunks

    out = {}
    for part in parts:
        for name, _t in part.channels:
            out[name] = np.zeros((part.height, part.width), np.float32)
    for index, part in enumerate(parts):
        for offset in offsets[index]:
            if multipart:
                number = struct.unpack_from("<i", data, offset)[0]
                if number != index:
                    raise ValueError(f"{path}: chunk of part {number} in the table of part {index}")
                offset += 4
            y, size = struct.unpack_from("<ii", data, offset)
            part.decode(data[offset + 8:offset + 8 + size], y, out, path)
    return out


def exr_pass(path, pass_name=AOV_NAME, view_layer=None):
    """One pass of a multilayer EXR as an (height, width, channels) array, top row first.

    Channels in R, G, B, A order (those present).  ``view_layer`` defaults to
    the only (or first) view layer that has the pass.
    """
    import numpy as np

    channels = read_exr(path)
    layers = []
    for name in channels:
        parts = name.rsplit(".", 2)
        if len(parts) == 3 and parts[1] == pass_name and parts[0] not in layers:
            layers.append(parts[0])
    if view_layer is None:
        if not layers:
            raise KeyError(f"{path}: no pass {pass_name!r}; channels: {sorted(channels)}")
        view_layer = layers[0]
    prefix = f"{view_layer}.{pass_name}."
    present = [c for c in "RGBA" if prefix + c in channels]
    if not present:
        present = sorted(name[len(prefix):] for name in channels if name.startswith(prefix))
        if not present:
            raise KeyError(f"{path}: no pass {pass_name!r} in view layer {view_layer!r}")
    return np.stack([channels[prefix + c] for c in present], axis=-1)
