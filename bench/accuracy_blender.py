# SPDX-License-Identifier: GPL-3.0-or-later
"""The Blender user path of the accuracy benchmark (run by ``bench/accuracy.py --sections user``).

    .venv/bin/python -m bench.accuracy_blender SCENE OUT.npz [--quick|--full]

Builds the matched scene in a fresh Blender (bpy, background mode) with the
add-on loaded from this working tree: the mesh as an object (object units,
``mm_per_unit`` set by the override), the material preset, the world colour
(uniform environments only: the add-on reads a uniform world) and an
orthographic camera equal to the reference's.  Then the user's operators:
``bpy.ops.translucency.bake`` and the render-time solve toward the scene
camera (``ops.runtime.solve_scene(use_camera=True)``, what F12 runs before a
frame), and reads the ``translucency_radiance`` attribute.  Writes the
attribute, its raster from the reference camera and what ran to ``OUT.npz``.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    name, out = argv[0], Path(argv[1])
    quick = "--quick" in argv
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="translucency-accuracy-"))
    sys.path.insert(0, str(ROOT))
    import bpy
    import numpy as np

    from bench import accuracy_scenes as scenes
    from bench.reference.raster import rasterize

    spec = {s.name: s for s in scenes.reference_scenes(quick)}[name]
    if spec.environment.sh is not None or spec.material.heterogeneous:
        raise SystemExit("the user path needs a uniform world and a preset material")
    spec_mod = importlib.util.spec_from_file_location("translucency", ROOT / "__init__.py",
                                                      submodule_search_locations=[str(ROOT)])
    addon = importlib.util.module_from_spec(spec_mod)
    sys.modules["translucency"] = addon
    spec_mod.loader.exec_module(addon)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    scene = bpy.context.scene
    scene.translucency.cache_directory = tempfile.mkdtemp(prefix="translucency-accuracy-cache-") + os.sep
    # world: uniform radiance
    world = bpy.data.worlds.new("World")
    scene.world = world
    world.color = tuple(spec.environment.radiance)
    if world.node_tree is None and hasattr(world, "use_nodes"):
        world.use_nodes = True
    bg = next((n for n in world.node_tree.nodes if n.type == 'BACKGROUND'), None) if world.node_tree else None
    if bg is not None:
        bg.inputs["Color"].default_value = (*spec.environment.radiance, 1.0)
        bg.inputs["Strength"].default_value = 1.0
    # the object
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(spec.V.tolist(), [], spec.F.tolist())
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    s = obj.translucency
    s.enabled = True
    quality = "draft" if quick else "preview"
    s.quality = quality.upper()
    s.use_mm_per_unit_override = True
    s.mm_per_unit = spec.mm_per_unit
    s.material_preset = spec.material.name.upper()
    # camera = the reference's orthographic camera
    cam = spec.camera
    r, u, f = cam.basis()
    cd = bpy.data.cameras.new("cam")
    cd.type = 'ORTHO'
    cd.ortho_scale = cam.width
    co = bpy.data.objects.new("cam", cd)
    scene.collection.objects.link(co)
    from mathutils import Matrix

    eye = np.asarray(cam.position) - f * 10.0 * float(np.ptp(spec.V, axis=0).max())
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = r, u, -f, eye  # Blender cameras look along -Z, up +Y
    co.matrix_world = Matrix(M.tolist())
    scene.camera = co
    scene.render.resolution_x, scene.render.resolution_y = spec.resolution
    for other in bpy.context.view_layer.objects:
        other.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    t0 = time.perf_counter()
    res = bpy.ops.translucency.bake()
    t_bake = time.perf_counter() - t0
    if res != {'FINISHED'}:
        raise SystemExit(f"bake returned {res}")
    from translucency.ops import attributes, runtime, state

    t0 = time.perf_counter()
    runtime.solve_scene(scene, bpy.context.evaluated_depsgraph_get(), use_camera=True, force=True)
    t_solve = time.perf_counter() - t0
    L = attributes.read_radiance(obj)
    if L is None:
        raise SystemExit("no translucency_radiance attribute after the solve")
    from bench.accuracy_core import SUPERSAMPLE

    ras = rasterize(spec.V, spec.F, L.astype(np.float64), spec.camera, spec.resolution, supersample=SUPERSAMPLE)
    st = state.get_state(obj)
    levels = [[int(lv.n_surface), int(lv.n_inner)] for lv in st.bake.levels] if st and st.bake else []
    meta = {"quality": quality, "bake_s": t_bake, "solve_s": t_solve, "backend": str(st.backend if st else ""),
            "levels": levels,
            "path": "bpy.ops.translucency.bake + ops.runtime.solve_scene(use_camera=True) + attribute"}
    np.savez_compressed(out, image=ras.image, mask=ras.mask, vertex=L, meta=json.dumps(meta))
    print(json.dumps(meta))


if __name__ == "__main__":
    main()
