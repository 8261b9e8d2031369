# SPDX-License-Identifier: GPL-3.0-or-later
"""Demo: milk poured onto a plate, a particle fluid solved every frame (Kang & Kim 2013).

    bash tools/setup.sh && .venv/bin/python demo/fluid_demo.py [--quick] [--output DIR] [--frames 6 14 20]

or, with a Blender binary: ``blender -b --python demo/fluid_demo.py -- [options]``.

What it does, through the add-on's own user path (settings, operators and handlers):

1. loads the extension from this checkout and registers it (a temporary
   Blender user directory, so your profile is never touched);
2. builds a scene with bpy (1 unit = 1 m): a point cloud "Milk Particles"
   (2.5 mm apart, each with an ``id``) that pours from a spout 11 cm above a
   plate -- a column falling at 0.45 m/s into a puddle that spreads in two
   layers.  The pour is procedural: this script's ``frame_change_pre``
   handler moves the points (in your scenes a particle system, a point cloud
   or Geometry Nodes do that).  "Milk" is the surface the camera sees:
   Geometry Nodes turn the points into a mesh (Points to Volume, Volume to
   Mesh), as Mantaflow's liquid mesh is made from its particles;
3. makes "Milk" translucent with the **Fluid** source (Particles: Point
   Cloud, Source Object "Milk Particles", Auto Radius, Skim Milk) -- no bake;
   a sun and a dim world light it;
4. adds the ``Translucency`` AOV and an Emission of the radiance to the milk's
   material (``translucency.add_to_material``); its base is black under a
   clear specular layer, so everything diffuse on the milk is the solved
   subsurface light;
5. renders the frames (6, 14 and 20 by default) with Cycles: each frame the
   add-on's handlers rebuild the Voronoi-fluid cells from the moved points
   and solve again (warm-started by particle id), and write the radiance onto
   the generated mesh through its ``Translucency Radiance`` modifier.  For
   each frame it writes into ``out/fluid_demo/`` (git-ignored):
   ``frame_0014.png`` (beauty), ``frame_0014.exr`` (multilayer OpenEXR with
   the ``Translucency`` pass) and ``translucency_0014.png`` (the pass alone),
   and prints where they are and what each frame's solve cost.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

if "bpy" not in sys.modules and not os.environ.get("TRANSLUCENCY_KEEP_USER_RESOURCES"):
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="translucency-demo-user-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from bpy.app.handlers import persistent  # noqa: E402


def _bunny_demo():
    """demo/demo.py, for its add-on loading and frame rendering helpers (one copy of them)."""
    spec = importlib.util.spec_from_file_location("translucency_bunny_demo", ROOT / "demo" / "demo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


demo = _bunny_demo()

SPACING = 0.0025  # m between particles
STREAM_RADIUS = 0.0045  # m
SPOUT_HEIGHT = 0.11  # m above the plate
SPEED = 0.45  # m/s down the stream
FPS = 24
LAYERS = 2  # of the puddle


def parse_args(argv=None):
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    ap = argparse.ArgumentParser(prog="fluid_demo.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="two small frames, few samples (for tests: under a minute)")
    ap.add_argument("--output", default=str(ROOT / "out" / "fluid_demo"), help="output directory")
    ap.add_argument("--frames", type=int, nargs="+", default=None, help="frames to render (default 6 14 20; "
                                                                        "--quick: 8 14)")
    ap.add_argument("--resolution", type=int, nargs=2, default=None, metavar=("W", "H"),
                    help="render size (default 480 360; --quick: 96 72)")
    ap.add_argument("--samples", type=int, default=None, help="Cycles samples (default 16; --quick: 4)")
    args = ap.parse_args(argv)
    args.frames = args.frames or ([8, 14] if args.quick else [6, 14, 20])
    args.resolution = args.resolution or ((96, 72) if args.quick else (480, 360))
    args.samples = args.samples or (4 if args.quick else 16)
    return args


# --- the pour (procedural: what a particle simulation would give) -------------------------------

def _disc(radius: float, spacing: float) -> np.ndarray:
    """Offsets of a hexagonal lattice inside a disc: the stream's cross-section."""
    k = int(math.ceil(radius / spacing)) + 1
    i, j = np.mgrid[-k:k + 1, -k:k + 1].reshape(2, -1)
    xy = np.stack([(i + 0.5 * (j % 2)) * spacing, j * spacing * math.sqrt(3.0) / 2.0], axis=1)
    return xy[np.linalg.norm(xy, axis=1) <= radius]


CROSS = _disc(STREAM_RADIUS, SPACING)


def pour(frame: float) -> tuple[np.ndarray, np.ndarray]:
    """``(points (N, 3), ids (N,))`` at ``frame``: the stream's layers leave the spout one after another,
    fall at SPEED and, reaching the puddle, take its next free places (a sunflower spiral per layer, so the
    puddle spreads at the rim with the density of the stream)."""
    t = max(frame - 1.0, 0.0) / FPS
    layer_dt = SPACING / SPEED
    n_layers = int(t / layer_dt) + 1
    n = len(CROSS)
    L = np.repeat(np.arange(n_layers), n)
    ids = np.arange(n_layers * n)
    z = SPOUT_HEIGHT - (t - L * layer_dt) * SPEED
    top = LAYERS * SPACING
    falling = z > top
    P = np.zeros((len(ids), 3))
    wobble = 0.0006 * np.sin(z[falling] * 140.0 + 6.0 * t)
    P[falling, :2] = CROSS[ids[falling] % n] + np.stack([wobble, 0.5 * wobble], axis=1)
    P[falling, 2] = z[falling]
    landed = np.nonzero(~falling)[0]  # in landing order: their index is their place in the puddle
    m, layer = landed // LAYERS, landed % LAYERS
    c = SPACING / math.sqrt(math.pi)  # a sunflower of spacing^2 per point
    r = c * np.sqrt(m + 0.5)
    theta = m * math.pi * (3.0 - math.sqrt(5.0)) + layer * 1.3
    rim = c * math.sqrt(len(landed) / LAYERS + 0.5)
    P[landed, 0], P[landed, 1] = r * np.cos(theta), r * np.sin(theta)
    P[landed, 2] = SPACING * (0.5 + layer) + 0.6 * SPACING * np.clip(1.0 - (r / max(rim, 1e-9)) ** 2, 0.0, 1.0)
    jitter = np.random.default_rng(7).uniform(-0.08, 0.08, (len(ids), 3)) * SPACING  # fixed per particle
    return P + jitter, ids


@persistent
def _move_the_points(scene, *_args):
    """frame_change_pre: put the points where the pour has them at this frame (before the add-on reads them)."""
    obj = bpy.data.objects.get("Milk Particles")
    if obj is not None:
        set_points(obj.data, *pour(scene.frame_current))


def set_points(pc, points, ids) -> None:
    if len(pc.points) != len(points):
        pc.resize(len(points))
    pc.attributes["position"].data.foreach_set("vector", points.astype(np.float32).ravel())
    attr = pc.attributes.get("id") or pc.attributes.new("id", 'INT', 'POINT')
    attr.data.foreach_set("value", ids.astype(np.int32))
    pc.update_tag()


# --- the scene ---------------------------------------------------------------------------------

def _socket_or_property(node, name: str, value, prop: str) -> None:
    """A node setting that is an input socket in Blender 5.x and a property in 4.x."""
    if name in node.inputs:
        node.inputs[name].default_value = value
    else:
        setattr(node, prop, value.upper())


def surface_nodes(points_obj, material):
    """Geometry Nodes: Object Info (the points) -> Points to Volume -> Volume to Mesh -> material, smooth shading."""
    group = bpy.data.node_groups.new("Milk Surface", 'GeometryNodeTree')
    group.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    group.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    nodes, links = group.nodes, group.links
    out = nodes.new('NodeGroupOutput')
    info = nodes.new('GeometryNodeObjectInfo')
    info.inputs["Object"].default_value = points_obj
    info.transform_space = 'RELATIVE'
    volume = nodes.new('GeometryNodePointsToVolume')
    _socket_or_property(volume, "Resolution Mode", "Size", "resolution_mode")
    volume.inputs["Voxel Size"].default_value = 0.35 * SPACING
    volume.inputs["Radius"].default_value = 1.3 * SPACING
    mesh = nodes.new('GeometryNodeVolumeToMesh')
    smooth = nodes.new('GeometryNodeSetShadeSmooth')
    shade = nodes.new('GeometryNodeSetMaterial')  # a generated mesh has no material of its own
    shade.inputs["Material"].default_value = material
    links.new(info.outputs["Geometry"], volume.inputs["Points"])
    links.new(volume.outputs[0], mesh.inputs[0])
    links.new(mesh.outputs[0], smooth.inputs["Geometry"])
    links.new(smooth.outputs[0], shade.inputs["Geometry"])
    links.new(shade.outputs[0], out.inputs[0])
    return group


def principled(name: str, color, roughness: float, ior: float | None = None):
    """A material with its Principled BSDF set: the milk (a black base: its diffuse light is the solved
    radiance, added by Add to Material) and the plate."""
    from translucency.ops.compat import ensure_node_tree

    mat = bpy.data.materials.new(name)
    bsdf = next(n for n in ensure_node_tree(mat).nodes if n.type == 'BSDF_PRINCIPLED')
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    if ior is not None:
        bsdf.inputs["IOR"].default_value = ior
    return mat


def build_scene(args):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.unit_settings.scale_length = 1.0
    scene.render.fps = FPS
    scene.frame_start, scene.frame_end = 1, max(args.frames)

    pc = bpy.data.pointclouds.new("Milk Particles")
    set_points(pc, *pour(1))
    points = bpy.data.objects.new("Milk Particles", pc)
    for ray in ("camera", "diffuse", "glossy", "transmission", "volume_scatter", "shadow"):
        setattr(points, f"visible_{ray}", False)  # the surface below is what renders
    scene.collection.objects.link(points)

    milk = bpy.data.objects.new("Milk", bpy.data.meshes.new("Milk"))
    scene.collection.objects.link(milk)
    material = principled("Milk", (0.0, 0.0, 0.0), 0.12, ior=1.35)
    milk.data.materials.append(material)  # the slot that Add to Material wires the pass into
    milk.modifiers.new("Surface", 'NODES').node_group = surface_nodes(points, material)
    s = milk.translucency
    s.enabled = True
    s.source = 'FLUID'
    s.fluid_kind = 'POINT_CLOUD'
    s.fluid_object = points
    s.fluid_radius_auto = True
    s.material_preset = 'SKIMMILK'

    bpy.ops.mesh.primitive_circle_add(vertices=64, radius=0.12, fill_type='NGON', location=(0.0, 0.0, 0.0))
    plate = bpy.context.object
    plate.name = "Plate"
    plate.data.materials.append(principled("Plate", (0.08, 0.11, 0.16), 0.35))

    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", 'SUN'))
    sun.data.energy = 4.0
    sun.data.angle = math.radians(5.0)
    sun.rotation_euler = (math.radians(55.0), 0.0, math.radians(-120.0))  # from the left, behind the milk
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("World")
    from translucency.ops.compat import ensure_node_tree

    background = next(n for n in ensure_node_tree(world).nodes if n.type == 'BACKGROUND')
    background.inputs["Color"].default_value = (0.35, 0.4, 0.5, 1.0)
    background.inputs["Strength"].default_value = 0.25
    world.color = (0.35 * 0.25, 0.4 * 0.25, 0.5 * 0.25)
    scene.world = world

    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.lens = 50.0
    camera.location = (0.0, -0.27, 0.14)
    scene.collection.objects.link(camera)
    demo.look_at(camera, (0.0, 0.0, 0.035))
    scene.camera = camera

    scene.render.engine = 'CYCLES'
    scene.cycles.device = 'CPU'
    scene.cycles.samples = args.samples
    scene.cycles.use_denoising = False
    scene.render.resolution_x, scene.render.resolution_y = args.resolution
    scene.render.resolution_percentage = 100
    return milk


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    out = Path(args.output).resolve()
    out.mkdir(parents=True, exist_ok=True)

    addon = demo.load_addon()
    rp = demo.ensure_render_pass_registered(addon)
    milk = build_scene(args)
    scene = bpy.context.scene
    bpy.app.handlers.frame_change_pre.append(_move_the_points)
    from translucency.ops import state

    demo.log(f"scene: milk poured onto a plate, {SPACING * 1000:g} mm particles, Skim Milk, "
             f"{args.resolution[0]}x{args.resolution[1]}, Cycles, {args.samples} samples, frames {args.frames}")
    scene.frame_set(args.frames[0])
    bpy.context.view_layer.objects.active = milk
    milk.select_set(True)
    if bpy.ops.translucency.solve() != {'FINISHED'}:
        raise SystemExit(f"demo: the Fluid solve failed: {state.solve_error('Milk')}")
    if bpy.ops.translucency.add_to_material(use_emission=True) != {'FINISHED'}:
        raise SystemExit("demo: translucency.add_to_material failed")

    results = []
    try:
        for frame in args.frames:
            stats = demo.render_frame(rp, scene, frame, out)
            st = state.fluid_state_of("Milk")
            if state.solve_errors():
                raise SystemExit(f"demo: frame {frame}: {state.solve_errors()}")
            demo.log(f"frame {frame}: {st.particles:,} particles -> {st.output}; the fluid frame took {st.seconds:.2f} s "
                     f"(cells {st.stages.get('cells', 0.0):.2f} s, {st.iterations} sweeps"
                     f"{', warm start' if st.warm_started else ''}); rendered in {stats['seconds']:.1f} s; the "
                     f"Translucency pass covers {stats['covered'] * 100:.0f} % of the image")
            results.append(stats)
    finally:
        bpy.app.handlers.frame_change_pre.remove(_move_the_points)

    return demo.report_files(results, t_start)


if __name__ == "__main__":
    sys.exit(main())
