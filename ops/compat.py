# SPDX-License-Identifier: GPL-3.0-or-later
"""What differs between the supported Blender releases (4.2 LTS to 5.2 LTS), in one place.

Every other module asks here instead of testing ``bpy.app.version`` itself.
Each function names the releases it tells apart; the tests run on 5.2 (the
default environment) and, through ``TRANSLUCENCY_BPY``, on 5.0, 4.5 and 4.2.

* Node trees: before 5.0 a material or world has ``use_nodes`` (off for a
  new world); from 5.0 they always use nodes and ``use_nodes`` is deprecated
  (a ``DeprecationWarning`` on access).
* EEVEE's engine id: ``BLENDER_EEVEE_NEXT`` in 4.2-4.5, ``BLENDER_EEVEE``
  from 5.0.
* Image output: 5.0 added ``ImageFormatSettings.media_type``, which must be
  set (``MULTI_LAYER_IMAGE``) before a multilayer EXR can be chosen.
* Path properties: 4.5 added the ``PATH_SUPPORTS_BLEND_RELATIVE`` option and
  warns for a ``//`` value without it; 4.2 does not know the option.
* The compositor: 5.0 moved the scene's tree from ``scene.node_tree`` to
  ``scene.compositing_node_group``.
* An object's evaluated point cloud (what Geometry Nodes output): 4.3 added
  ``Object.evaluated_geometry()``; 4.2 lists the component among the
  depsgraph's object instances.
"""

from __future__ import annotations

import bpy

ALWAYS_NODES = bpy.app.version >= (5, 0, 0)


def uses_nodes(idblock) -> bool:
    """True if a material or world is evaluated through its node tree."""
    if getattr(idblock, "node_tree", None) is None:
        return False
    return ALWAYS_NODES or bool(getattr(idblock, "use_nodes", False))


def ensure_node_tree(idblock):
    """The node tree of a material or world, turning nodes on where the release needs it."""
    if not ALWAYS_NODES and (idblock.node_tree is None or not idblock.use_nodes):
        idblock.use_nodes = True
    elif idblock.node_tree is None:  # 5.x: a tree is always there; an old file may lack one
        idblock.use_nodes = True
    return idblock.node_tree


def eevee_engine_id() -> str:
    """EEVEE's ``scene.render.engine`` id: BLENDER_EEVEE_NEXT in 4.2-4.5, BLENDER_EEVEE from 5.0."""
    return 'BLENDER_EEVEE_NEXT' if bpy.app.version < (5, 0, 0) else 'BLENDER_EEVEE'


def set_media_type(image_settings, multilayer: bool) -> None:
    """5.0+: choose the media type before the file format; 4.x has only the file format."""
    if hasattr(image_settings, "media_type"):
        image_settings.media_type = 'MULTI_LAYER_IMAGE' if multilayer else 'IMAGE'


def compositor_tree(scene):
    """The scene's compositor node tree, or None (5.0 moved it to ``compositing_node_group``)."""
    if hasattr(scene, "compositing_node_group"):
        return scene.compositing_node_group
    return getattr(scene, "node_tree", None)


def read_evaluated_pointcloud(obj_eval, depsgraph, read):
    """``read(pointcloud, world matrix)`` on an evaluated object's point-cloud component, or None without one.

    A point-cloud object's own data; otherwise (a Geometry Nodes object) the
    ``pointcloud`` of ``evaluated_geometry()`` (4.3+; the component lives only
    as long as that geometry set, hence the callback), or in 4.2 the
    point-cloud instance the depsgraph lists for the object.
    """
    if obj_eval.type == 'POINTCLOUD':
        return read(obj_eval.data, obj_eval.matrix_world.copy())
    if hasattr(obj_eval, "evaluated_geometry"):
        geometry = obj_eval.evaluated_geometry()
        pc = geometry.pointcloud
        return None if pc is None else read(pc, obj_eval.matrix_world.copy())
    original = obj_eval.original
    for inst in depsgraph.object_instances:  # 4.2
        parent = inst.parent
        if (inst.is_instance and inst.object.type == 'POINTCLOUD' and parent is not None
                and parent.original == original):
            return read(inst.object.data, inst.matrix_world.copy())
    return None


PATH_OPTIONS = {'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (4, 5, 0) else set()

CLASSES = ()
