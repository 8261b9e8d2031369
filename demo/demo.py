# SPDX-License-Identifier: GPL-3.0-or-later
"""Demo: the Stanford bunny in heterogeneous marble under a moving light.

    bash tools/setup.sh && .venv/bin/python demo/demo.py [--quick] [--engine cycles|eevee]
                                                          [--output DIR] [--frames 1 40]

or, with a Blender binary: ``blender -b --python demo/demo.py -- [options]``.

What it does, through the add-on's own user path (operators and handlers):

1. loads the extension from this checkout and registers it (a temporary
   Blender user directory, so your profile is never touched);
2. builds a scene with bpy: the Stanford bunny, ``data/meshes/stanford-bunny.obj``
   in this repository (``data/README.md`` gives its source and terms; 0.155
   units across; the scene unit scale is 1 m per unit, so it is ~155 mm,
   the size the Jensen coefficients per mm expect), marble mixed with ketchup
   by a Blender *Marble* texture (red veins), a point light that moves from
   the camera side to behind the bunny (keyframes), a camera, a floor;
3. bakes the bunny's QuadGraph (``translucency.bake``, quality Preview, or
   Draft with ``--quick``) and solves (``translucency.solve``);
4. adds the ``Translucency`` AOV and an Emission of the radiance to the
   bunny's material (``translucency.add_to_material``): the bunny's material
   is a clear-coat-like specular layer on a black base, so everything
   diffuse you see on it is the solved subsurface light;
5. renders two frames (1 and 40 by default) with Cycles (or EEVEE); before
   each frame the add-on's frame/render handlers re-solve for the moved
   light.  For each frame it writes into ``out/demo/`` (git-ignored):
   ``frame_0001.png`` (beauty), ``frame_0001.exr`` (multilayer OpenEXR with
   the ``Translucency`` pass) and ``translucency_0001.png`` (the pass alone,
   exposure-normalised), and prints where they are.

The bake cache goes to ``<output>/cache/``.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from data import mesh_path  # noqa: E402 - the repository's own meshes (data/README.md)

PACKAGE = "translucency"

if "bpy" not in sys.modules and not os.environ.get("TRANSLUCENCY_KEEP_USER_RESOURCES"):
    # bpy from PyPI: keep Blender's user directories out of the user's profile.
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="translucency-demo-user-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Matrix, Vector  # noqa: E402


def parse_args(argv=None):
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    ap = argparse.ArgumentParser(prog="demo.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="tiny resolution, draft bake, few samples (for tests: seconds, not minutes)")
    ap.add_argument("--engine", choices=["cycles", "eevee"], default="cycles")
    ap.add_argument("--output", default=str(ROOT / "out" / "demo"), help="output directory (default out/demo)")
    ap.add_argument("--frames", type=int, nargs=2, default=(1, 40), metavar=("A", "B"),
                    help="the two frames to render (default 1 40)")
    ap.add_argument("--resolution", type=int, nargs=2, default=None, metavar=("W", "H"),
                    help="render size (default 480 360; --quick: 64 48)")
    ap.add_argument("--samples", type=int, default=None, help="render samples (default 24; --quick: 2)")
    ap.add_argument("--quality", choices=["draft", "preview", "final"], default=None,
                    help="bake quality (default preview; --quick: draft)")
    args = ap.parse_args(argv)
    if args.resolution is None:
        args.resolution = (64, 48) if args.quick else (480, 360)
    if args.samples is None:
        args.samples = 2 if args.quick else 24
    if args.quality is None:
        args.quality = "draft" if args.quick else "preview"
    return args


def log(message: str) -> None:
    print(f"demo: {message}", flush=True)


# --- the add-on -----------------------------------------------------------------------------

def load_addon():
    """Import this checkout as the extension package ``translucency`` and register it."""
    module = sys.modules.get(PACKAGE)
    if module is None:
        spec = importlib.util.spec_from_file_location(
            PACKAGE, ROOT / "__init__.py", submodule_search_locations=[str(ROOT)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[PACKAGE] = module
        spec.loader.exec_module(module)
    module.register()
    return module


def operator_exists(name: str) -> bool:
    """``bpy.ops.translucency.<name>`` is registered (``hasattr`` on bpy.ops is always true)."""
    try:
        getattr(bpy.ops.translucency, name).get_rna_type()
    except (KeyError, AttributeError):
        return False
    return True


def operators_available() -> bool:
    return operator_exists("bake") and operator_exists("solve")


def render_pass_module(addon):
    from importlib import import_module

    return import_module(f"{addon.__name__}.ops.render_pass")


def ensure_render_pass_registered(addon):
    """Register the render-pass operators if ops/__init__.py does not (older checkouts)."""
    rp = render_pass_module(addon)
    if not operator_exists("add_to_material"):
        for cls in rp.CLASSES:
            bpy.utils.register_class(cls)
    return rp


# --- the scene ---------------------------------------------------------------------------------

def look_at(obj, target) -> None:
    direction = Vector(target) - obj.location
    obj.rotation_euler = direction.to_track_quat('-Z', 'Y').to_euler()


def import_bunny():
    try:
        mesh = mesh_path("stanford-bunny")
    except FileNotFoundError as exc:
        raise SystemExit(f"demo: {exc}") from None
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=str(mesh))  # Y-up OBJ -> Z-up (a 90 degree X rotation)
    obj = next(o for o in bpy.data.objects if o not in before)
    obj.name = obj.data.name = "Bunny"
    # Bake the import rotation into the mesh, and stand the bunny on z = 0, centred on x, y.
    obj.data.transform(obj.matrix_world)
    obj.matrix_world = Matrix.Identity(4)
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(axis=0), co.max(axis=0)
    obj.data.transform(Matrix.Translation((-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2])))
    for poly in obj.data.polygons:
        poly.use_smooth = True
    obj.data.update()
    return obj


def bunny_material():
    """Black base + clear specular: all diffuse light on the bunny is the subsurface solve."""
    mat = bpy.data.materials.new("Bunny Marble")
    from translucency.ops.compat import ensure_node_tree

    ensure_node_tree(mat)
    bsdf = next(n for n in mat.node_tree.nodes if n.type == 'BSDF_PRINCIPLED')
    bsdf.inputs["Base Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.25
    return mat


def floor_material():
    mat = bpy.data.materials.new("Floor")
    from translucency.ops.compat import ensure_node_tree

    ensure_node_tree(mat)
    bsdf = next(n for n in mat.node_tree.nodes if n.type == 'BSDF_PRINCIPLED')
    bsdf.inputs["Base Color"].default_value = (0.18, 0.18, 0.2, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.6
    return mat


def build_scene(args):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.unit_settings.system = 'METRIC'
    scene.unit_settings.scale_length = 1.0  # 1 unit = 1 m: the 0.155-unit bunny is 155 mm
    frame_a, frame_b = args.frames
    scene.frame_start, scene.frame_end = min(frame_a, frame_b), max(frame_a, frame_b)

    bunny = import_bunny()
    bunny.data.materials.append(bunny_material())

    bpy.ops.mesh.primitive_plane_add(size=2.0, location=(0.0, 0.0, 0.0))
    floor = bpy.context.object
    floor.name = "Floor"
    floor.data.materials.append(floor_material())

    # Heterogeneity: marble (field 0) with ketchup veins (field 1) from a Marble texture,
    # evaluated in the bunny's object space (units: metres, so the noise scale is small).
    texture = bpy.data.textures.new("Marble Veins", 'MARBLE')
    # Blender's brightness/contrast: out = (in - 0.5) contrast + brightness - 0.5, so with
    # these ~20 % of the volume (the bright bands) is mostly ketchup.
    texture.marble_type = 'SOFT'
    texture.noise_basis_2 = 'SIN'
    texture.noise_scale = 0.05
    texture.turbulence = 6.0
    texture.noise_depth = 2
    texture.contrast = 1.5
    texture.intensity = 0.7
    settings = bunny.translucency
    settings.enabled = True
    settings.quality = args.quality.upper()
    if args.quick:
        settings.levels = 2  # the coarse two of the three levels: a bake of seconds
    settings.material_preset = 'MARBLE'
    settings.use_heterogeneity = True
    settings.second_preset = 'KETCHUP'
    settings.field_source = 'TEXTURE'
    settings.field_texture = texture

    # A point light that moves from the camera side (front left) to behind the bunny.
    light_data = bpy.data.lights.new("Moving Light", 'POINT')
    light_data.energy = 6.0  # W
    light_data.shadow_soft_size = 0.01
    light = bpy.data.objects.new("Moving Light", light_data)
    scene.collection.objects.link(light)
    for frame, location in ((frame_a, (-0.22, -0.25, 0.24)), (frame_b, (0.10, 0.22, 0.20))):
        light.location = location
        light.keyframe_insert("location", frame=frame)

    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.data.lens = 50.0
    camera.location = (0.05, -0.52, 0.16)
    look_at(camera, (0.0, 0.0, 0.075))
    scene.collection.objects.link(camera)
    scene.camera = camera

    world = bpy.data.worlds.new("Dim World")
    from translucency.ops.compat import ensure_node_tree

    ensure_node_tree(world)
    background = world.node_tree.nodes.get("Background")
    if background is not None:
        background.inputs["Color"].default_value = (0.02, 0.022, 0.03, 1.0)
        background.inputs["Strength"].default_value = 1.0
    scene.world = world

    render = scene.render
    render.resolution_x, render.resolution_y = args.resolution
    render.resolution_percentage = 100
    if args.engine == "cycles":
        render.engine = 'CYCLES'
        scene.cycles.device = 'CPU'
        scene.cycles.samples = args.samples
        scene.cycles.use_denoising = False
        scene.cycles.max_bounces = 4
    else:
        from importlib import import_module

        render.engine = import_module(f"{PACKAGE}.ops.render_pass").eevee_engine_id()
        scene.eevee.taa_render_samples = args.samples
    scene.view_settings.view_transform = 'AgX' if 'AgX' in _enum(scene.view_settings, "view_transform") \
        else 'Filmic'
    bpy.context.view_layer.objects.active = bunny
    bunny.select_set(True)
    return bunny


def _enum(struct, prop):
    try:
        return {item.identifier for item in struct.bl_rna.properties[prop].enum_items}
    except KeyError:
        return set()


# --- bake and solve --------------------------------------------------------------------------------

def bake_and_solve_with_operators(bunny):
    bpy.context.view_layer.objects.active = bunny
    t0 = time.perf_counter()
    result = bpy.ops.translucency.bake()
    if result != {'FINISHED'}:
        raise SystemExit(f"demo: translucency.bake returned {result}: {bunny.translucency.status.bake_status}")
    log(f"baked in {time.perf_counter() - t0:.1f} s ({bunny.translucency.status.bake_status}; "
        f"{bunny.translucency.status.bake_stats})")
    t0 = time.perf_counter()
    result = bpy.ops.translucency.solve()
    if result != {'FINISHED'}:
        raise SystemExit(f"demo: translucency.solve returned {result}")
    log(f"solved in {time.perf_counter() - t0:.1f} s")


# --- render -----------------------------------------------------------------------------------------

def radiance_digest(bunny) -> tuple[float, float]:
    attr = bunny.data.attributes.get("translucency_radiance")
    if attr is None:
        return (0.0, 0.0)
    buf = np.empty(len(attr.data) * 4, np.float32)
    attr.data.foreach_get("color", buf)
    rgb = buf.reshape(-1, 4)[:, :3]
    return float(rgb.mean()), float(rgb.max())


def save_pass_png(rp, exr_path: Path, png_path: Path) -> dict:
    """The Translucency pass alone, scaled so its 99th percentile is white, as a PNG."""
    sys.path.insert(0, str(ROOT))
    from tools.exr import exr_pass  # the repo's small EXR reader (not part of the extension)

    translucency = exr_pass(exr_path, rp.AOV_NAME)[..., :3]
    lit = translucency.max(axis=2)
    scale = float(np.percentile(lit[lit > 0], 99.0)) if np.any(lit > 0) else 1.0
    display = np.clip(translucency / max(scale, 1e-12), 0.0, 1.0) ** (1.0 / 2.2)
    h, w = display.shape[:2]
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = display[::-1]  # Blender images start at the bottom row
    image = bpy.data.images.new(png_path.stem, w, h, alpha=True)
    image.pixels.foreach_set(rgba.ravel())
    image.filepath_raw = str(png_path)
    image.file_format = 'PNG'
    image.save()
    bpy.data.images.remove(image)
    return {"mean": float(translucency.mean()), "max": float(translucency.max()),
            "covered": float((lit > 0).mean())}


def render_frame(rp, scene, frame: int, out: Path) -> dict:
    scene.frame_set(frame)  # the add-on's frame_change handler re-solves for the moved light
    render = scene.render
    t0 = time.perf_counter()
    exr = out / f"frame_{frame:04d}.exr"
    png = out / f"frame_{frame:04d}.png"
    rp.configure_output(render.image_settings, 'OPEN_EXR_MULTILAYER')
    render.filepath = str(exr)
    bpy.ops.render.render(write_still=True)  # render_pre handlers re-solve with the render camera
    rendered = time.perf_counter() - t0
    # The same render result as a PNG (display transform applied), without rendering again.
    rp.configure_output(render.image_settings, 'PNG')
    bpy.data.images["Render Result"].save_render(str(png), scene=scene)
    stats = save_pass_png(rp, exr, out / f"translucency_{frame:04d}.png")
    stats.update(seconds=rendered, exr=exr, png=png, pass_png=out / f"translucency_{frame:04d}.png")
    return stats


def main(argv=None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    out = Path(args.output).resolve()
    out.mkdir(parents=True, exist_ok=True)

    addon = load_addon()
    rp = ensure_render_pass_registered(addon)
    bunny = build_scene(args)
    scene = bpy.context.scene
    scene.translucency.cache_directory = str(out / "cache") + os.sep
    log(f"scene: {mesh_path('stanford-bunny').name} ({len(bunny.data.vertices)} vertices, "
        f"{max(bunny.dimensions) * scene.unit_settings.scale_length * 1000:.0f} mm), marble + ketchup veins, "
        f"{args.resolution[0]}x{args.resolution[1]}, {scene.render.engine}, {args.samples} samples, "
        f"bake quality {args.quality}")

    scene.frame_set(args.frames[0])
    if not operators_available():
        raise SystemExit("demo: the add-on registered no translucency.bake/solve operators")
    bake_and_solve_with_operators(bunny)
    mean, peak = radiance_digest(bunny)
    if not np.isfinite(mean) or peak <= 0.0:
        raise SystemExit("demo: the solve left no radiance on the bunny")
    bpy.context.view_layer.objects.active = bunny
    result = bpy.ops.translucency.add_to_material(use_emission=True)
    if result != {'FINISHED'}:
        raise SystemExit(f"demo: translucency.add_to_material returned {result}")

    results = []
    for frame in args.frames:
        stats = render_frame(rp, scene, frame, out)
        mean, peak = radiance_digest(bunny)
        log(f"frame {frame}: rendered in {stats['seconds']:.1f} s; radiance on the bunny: mean {mean:.3g}, "
            f"max {peak:.3g} W/(m^2 sr); Translucency pass covers {stats['covered'] * 100:.0f} % of the image")
        results.append(stats)

    return report_files(results, t_start)


def report_files(results, t_start: float) -> int:
    """Print where every frame's files are; the exit code: 1 when a Translucency pass is black."""
    log(f"done in {time.perf_counter() - t_start:.1f} s. Images:")
    for stats in results:
        for key in ("png", "pass_png", "exr"):
            print(f"  {stats[key]}")
    if any(stats["max"] <= 0.0 for stats in results):
        print("demo: a Translucency pass is black", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
