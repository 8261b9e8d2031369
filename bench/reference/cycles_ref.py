# SPDX-License-Identifier: GPL-3.0-or-later
"""One-time cross-check of the Mitsuba reference against Cycles (bpy as a module).

    python -m bench.reference.cycles_ref [--spp 1024] [--res 32] [--material marble|white] [--mm-per-unit 12]

This is a script, not a test.  The same sphere as ``sphere_env`` (R = 12 mm,
eta 1.3, uniform environment radiance 1, orthographic view) is rendered by
Cycles with

* surface: **Glass BSDF** (sharp, IOR = eta).  Cycles' Refraction BSDF alone
  has no Fresnel reflection, so it would remove the internal reflections that
  are half of the boundary condition (F_dr,internal = 0.44 at eta 1.3); the
  Glass BSDF is the Fresnel mix of reflection and refraction, i.e. Mitsuba's
  ``dielectric``.  ``--bsdf refraction`` renders the Refraction-only variant
  to show the difference;
* volume: Volume Scatter (Henyey-Greenstein, anisotropy 0) + Volume Absorption,
  densities per **Blender unit**: the mesh is built in object units and
  density = sigma [1/mm] x mm_per_unit [mm/unit];
* world colour 1, strength 1; camera orthographic; box pixel filter of 1 px;
* all bounce limits at Cycles' hard maximum (1024), ``min_light_bounces``
  1024 (no Russian roulette before the cap), no clamping, no glossy filter,
  caustics on, no denoising, no light-path guiding;
* one grey render per colour channel, as for Mitsuba.

Both renderers are compared on the *plain* image (translucency + surface
reflection), so no subtraction is involved on either side.  Cycles caps paths
at 1024 bounces; Mitsuba is run twice, uncapped (the reference) and with
``max_depth`` = 1024 + 2, to separate the cap from any other difference.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CYCLES_MAX = 1024


def _setup_blender_user_dir():
    if "bpy" in sys.modules:
        return
    d = tempfile.mkdtemp(prefix="translucency-cycles-user-")
    os.environ.setdefault("BLENDER_USER_RESOURCES", d)


def empty_node_tree(idblock):
    """The node tree of a new material or world, emptied (before Blender 5 it exists once ``use_nodes`` is set)."""
    if getattr(idblock, "node_tree", None) is None:
        idblock.use_nodes = True
    tree = idblock.node_tree
    tree.nodes.clear()
    return tree


def volume_material(bpy, name: str, sigma_s, sigma_a, per_unit: float, *, surface: str | None = "glass",
                    eta: float = 1.0):
    """A Cycles material for a homogeneous medium: Volume Scatter + Volume Absorption inside.

    ``sigma_s``, ``sigma_a``: RGB coefficients [1/mm]; ``per_unit``: mm per Blender unit (the mesh is in
    object units), so a density is sigma x per_unit.  Cycles' Volume Scatter has sigma_s = Color x
    Density and Volume Absorption sigma_a = (1 - Color) x Density, so each gets Density = its largest
    channel and the colour the ratio (a grey medium: scatter colour 1, absorption colour 0; the nodes'
    default colour 0.8 would scale sigma_s by 0.8).  Henyey-Greenstein with anisotropy 0 (isotropic),
    distance sampling.  ``surface``: ``"glass"`` (Fresnel mix of reflection and refraction, Mitsuba's
    ``dielectric``), ``"refraction"`` (no Fresnel reflection) -- both sharp GGX at IOR ``eta`` -- or None
    (index-matched: no surface shader).  Returns ``(material, (scatter density, absorption density))``.
    """
    ss = np.broadcast_to(np.asarray(sigma_s, dtype=np.float64), (3,))
    sa = np.broadcast_to(np.asarray(sigma_a, dtype=np.float64), (3,))
    smax, amax = float(ss.max()), float(sa.max())
    mat = bpy.data.materials.new(name)
    nt = empty_node_tree(mat)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    scat = nt.nodes.new("ShaderNodeVolumeScatter")
    if hasattr(scat, "phase"):
        scat.phase = "HENYEY_GREENSTEIN"
    scat.inputs["Anisotropy"].default_value = 0.0
    scat.inputs["Color"].default_value = (*(ss / smax if smax > 0 else np.ones(3)), 1.0)
    scat.inputs["Density"].default_value = smax * per_unit
    absn = nt.nodes.new("ShaderNodeVolumeAbsorption")
    absn.inputs["Color"].default_value = (*(1.0 - sa / amax if amax > 0 else np.zeros(3)), 1.0)
    absn.inputs["Density"].default_value = amax * per_unit
    add = nt.nodes.new("ShaderNodeAddShader")
    nt.links.new(scat.outputs[0], add.inputs[0])
    nt.links.new(absn.outputs[0], add.inputs[1])
    nt.links.new(add.outputs[0], out.inputs["Volume"])
    if surface is not None:
        if surface not in ("glass", "refraction"):
            raise ValueError(f"unknown surface {surface!r}; choose glass, refraction or None")
        surf = nt.nodes.new("ShaderNodeBsdfGlass" if surface == "glass" else "ShaderNodeBsdfRefraction")
        surf.distribution = "GGX"
        surf.inputs["Roughness"].default_value = 0.0
        surf.inputs["IOR"].default_value = float(eta)
        surf.inputs["Color"].default_value = (1, 1, 1, 1)
        nt.links.new(surf.outputs[0], out.inputs["Surface"])
    mat.cycles.volume_sampling = "DISTANCE"
    return mat, (smax * per_unit, amax * per_unit)


def render_cycles(scene, spp: int = 1024, *, bsdf: str = "glass", max_bounces: int = CYCLES_MAX,
                  threads: int = 0, progress=None):
    """Plain Cycles render (translucency + reflection) of a RefScene: ``(image (H, W, 3), seconds)``.

    Supports a uniform environment and suns only (what the cross-check needs).
    """
    _setup_blender_user_dir()
    import bpy

    t0 = time.perf_counter()
    for light in scene.lights:
        if light.kind != "sun":
            raise NotImplementedError("the Cycles cross-check supports suns and a uniform environment only")
    if scene.material.heterogeneous:
        raise NotImplementedError("the Cycles cross-check is homogeneous only")
    W, H = scene.resolution
    s = scene.mm_per_unit
    sa, ss = scene.material.coefficients(n=1)
    out = np.zeros((H, W, 3))
    with tempfile.TemporaryDirectory(prefix="translucency-cycles-") as tmp:
        for c in range(3):
            bpy.ops.wm.read_factory_settings(use_empty=True)
            sc = bpy.context.scene
            # mesh, in object units (Blender units), object scale 1
            me = bpy.data.meshes.new("object")
            me.from_pydata(scene.V.tolist(), [], scene.F.tolist())
            me.update()
            for poly in me.polygons:
                poly.use_smooth = bool(scene.smooth_normals)
            ob = bpy.data.objects.new("object", me)
            sc.collection.objects.link(ob)
            mat, _ = volume_material(bpy, "translucent", float(ss[0, c]), float(sa[0, c]), s, surface=bsdf,
                                     eta=scene.material.eta)
            ob.data.materials.append(mat)
            # world
            world = bpy.data.worlds.new("world")
            world.use_nodes = True
            bg = world.node_tree.nodes.get("Background") or world.node_tree.nodes.new("ShaderNodeBackground")
            value = float(scene.environment.radiance[c]) if scene.environment is not None else 0.0
            bg.inputs["Color"].default_value = (value, value, value, 1)
            bg.inputs["Strength"].default_value = 1.0
            sc.world = world
            for k, light in enumerate(scene.lights):
                ld = bpy.data.lights.new(f"sun{k}", "SUN")
                ld.energy = float(light.rgb[c])  # W/m^2
                ld.angle = 0.0
                lo = bpy.data.objects.new(f"sun{k}", ld)
                d = light.unit_direction
                lo.rotation_mode = "QUATERNION"
                from mathutils import Vector

                lo.rotation_quaternion = Vector((0, 0, -1)).rotation_difference(Vector(d.tolist()))
                sc.collection.objects.link(lo)
            # camera
            cam = scene.camera
            if cam.kind != "orthographic":
                raise NotImplementedError("the Cycles cross-check uses the orthographic camera")
            r, u, f = cam.basis()
            cd = bpy.data.cameras.new("camera")
            cd.type = "ORTHO"
            cd.ortho_scale = float(cam.width)
            cd.sensor_fit = "HORIZONTAL"
            lo_, hi_ = scene.bbox
            diag = float(np.linalg.norm(hi_ - lo_))
            cd.clip_start = 1e-3 * diag
            cd.clip_end = 10.0 * diag
            co = bpy.data.objects.new("camera", cd)
            from mathutils import Matrix

            back = 2.0 * diag
            pos = np.asarray(cam.position) - back * f
            # Blender camera: looks along -Z, +Y up, +X right
            M = np.eye(4)
            M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = r, u, -f, pos
            co.matrix_world = Matrix(M.tolist())
            sc.collection.objects.link(co)
            sc.camera = co
            # render settings
            sc.render.engine = "CYCLES"
            cy = sc.cycles
            cy.device = "CPU"
            cy.samples = int(spp)
            cy.use_adaptive_sampling = False
            cy.use_denoising = False
            cy.max_bounces = max_bounces
            cy.volume_bounces = max_bounces
            cy.transmission_bounces = max_bounces
            cy.glossy_bounces = max_bounces
            cy.diffuse_bounces = max_bounces
            cy.transparent_max_bounces = max_bounces
            cy.min_light_bounces = max_bounces
            cy.min_transparent_bounces = max_bounces
            cy.sample_clamp_direct = 0.0
            cy.sample_clamp_indirect = 0.0
            cy.blur_glossy = 0.0
            cy.caustics_reflective = True
            cy.caustics_refractive = True
            cy.pixel_filter_type = "BOX"
            cy.filter_width = 1.0
            cy.seed = 17 + c
            if hasattr(cy, "use_guiding"):
                cy.use_guiding = False
            if threads:
                sc.render.threads_mode = "FIXED"
                sc.render.threads = threads
            sc.render.resolution_x, sc.render.resolution_y = W, H
            sc.render.resolution_percentage = 100
            sc.render.film_transparent = False
            sc.view_settings.view_transform = "Standard"
            sc.view_settings.look = "None"
            sc.view_settings.exposure = 0.0
            sc.view_settings.gamma = 1.0
            sc.render.image_settings.file_format = "OPEN_EXR"
            sc.render.image_settings.color_depth = "32"
            path = os.path.join(tmp, f"c{c}.exr")
            sc.render.filepath = path
            bpy.ops.render.render(write_still=True)
            img = bpy.data.images.load(path)
            px = np.empty(W * H * img.channels, dtype=np.float32)
            img.pixels.foreach_get(px)
            px = px.reshape(H, W, img.channels)[::-1]  # Blender stores bottom row first
            out[..., c] = px[..., c]
            bpy.data.images.remove(img)
            if progress is not None:
                progress(f"cycles channel {c}: {time.perf_counter() - t0:.1f} s")
    return out, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--mitsuba-spp", type=int, default=None, help="default: same as --spp")
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--material", default="marble", help="a preset name, or 'white' (albedo 1, the furnace)")
    ap.add_argument("--mm-per-unit", type=float, default=12.0, help="object units -> mm (unit sphere at 12)")
    ap.add_argument("--bsdf", choices=["glass", "refraction"], default="glass")
    ap.add_argument("--skip-capped", action="store_true", help="do not run the capped Mitsuba render")
    a = ap.parse_args(argv)

    _setup_blender_user_dir()
    import bpy  # noqa: F401  (before mitsuba, as in the test suite)

    from bench.reference import metrics
    from bench.reference.mitsuba_ref import render_reference
    from bench.reference.scene import sphere_env
    from translucency_addon.scene.materials import Material, Medium, material_from_preset

    if a.material == "white":
        mat = Material(Medium((0.0, 0.0, 0.0), (2.19, 2.62, 3.00), "white"), eta=1.3)
    else:
        mat = material_from_preset(a.material)
    sc = sphere_env(mat, image_res=a.res, spp=a.spp, mm_per_unit=a.mm_per_unit)
    say = lambda m: print("  ", m, file=sys.stderr, flush=True)  # noqa: E731
    cyc, t_c = render_cycles(sc, a.spp, bsdf=a.bsdf, progress=say)
    ref = render_reference(sc, spp=a.mitsuba_spp or a.spp, progress=say)
    runs = [("Mitsuba, uncapped", ref)]
    if not a.skip_capped:
        runs.append((f"Mitsuba, max_depth {CYCLES_MAX + 2}", render_reference(sc, spp=a.mitsuba_spp or a.spp,
                                                                          max_depth=CYCLES_MAX + 2, progress=say)))
    P = metrics.comparison_mask(ref.mask)
    H, W = ref.image.shape[:2]
    c2 = (slice(H // 2 - 1, H // 2 + 1), slice(W // 2 - 1, W // 2 + 1))
    print(f"sphere R=12 mm ({a.mm_per_unit} mm/unit), {a.material}, eta {mat.eta}, env 1, {a.res}x{a.res}; "
          f"Cycles {a.bsdf} BSDF {a.spp} spp/channel: {t_c:.1f} s")
    fmt = lambda v: "(" + ", ".join(f"{x:.4f}" for x in v) + ")"  # noqa: E731
    print(f"  Cycles ({a.bsdf}): mean over {P.sum()} px {fmt(cyc[P].mean(0))}, centre 2x2 {fmt(cyc[c2].mean((0, 1)))}")
    for label, res in runs:
        full = res.full
        se = np.sqrt((res.stderr[P] ** 2).sum(0)) / P.sum()
        print(f"  {label} ({res.spp} spp, {res.seconds:.1f} s): mean {fmt(full[P].mean(0))} +- {fmt(se)}, "
              f"centre 2x2 {fmt(full[c2].mean((0, 1)))}")
        rep = metrics.relative_rms(cyc, full, ref.mask, stderr=res.stderr)
        print(f"    Cycles vs {label}: {rep}; mean ratio Cycles/Mitsuba {fmt(cyc[P].mean(0) / full[P].mean(0))}")


if __name__ == "__main__":
    main()
