# SPDX-License-Identifier: GPL-3.0-or-later
"""The World as the engine's environment (issue 19): cost of large HDRIs, and the add-on against Cycles.

    nice -n 10 .venv/bin/python -m bench.world [--large 16384] [--spp 256] [--res 32] [--no-cycles]

1. **Large HDRIs.**  A synthetic float32 RGBA map of the given width (16384 x 8192 = 2 GiB, what
   ``Image.pixels.foreach_get`` hands over for a 16k HDRI) is reduced by
   ``environment_map.downsample`` to 2048 x 1024, then the sun is extracted and the rest projected:
   wall time and the peak of numpy's allocations on top of the input (``tracemalloc``).
2. **Against Cycles.**  A sphere of marble (R = 5 mm, the add-on's mm-per-unit override) lit only by the
   shipped HDRI ``tests/data/sun_sky_cc0.exr`` (its sun 20 W/m^2, 88 % of its light), seen orthographically
   from above (the sun 35 degrees up at +x): the add-on bakes, solves and writes the Translucency pass in an
   F12 Cycles render; Cycles renders the same sphere as a Volume Scatter + Volume Absorption medium
   (one grey render per colour channel, densities per Blender unit, box filter, bounce limits at 1024,
   as ``bench/reference/cycles_ref.py``).  The boundary is **index-matched** (IOR 1, no surface shader):
   behind a smooth Glass surface a unidirectional path tracer cannot sample a sun or a 1.5 degree HDRI sun
   (measured with Mitsuba 3 here: even a 30 degree disk left 24 % noise per pixel that hardly fell from 256 to
   2048 spp), while through a matched boundary
   Cycles' world importance sampling reaches it from every scattering event.  The add-on runs with IOR 1
   too.  The table compares the mean over the sphere's pixels (2 px inside its rim), its sunlit and its
   shaded halves, with Cycles' standard error.

The table is written into ``docs/accuracy.md`` under its own heading (a kept section:
``bench/accuracy_text.KEPT_SECTIONS``), so ``bench/accuracy.py`` leaves it alone.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
HEADING = "## HDRI world (issue 19): the add-on against Cycles\n"
HDRI = ROOT / "tests" / "data" / "sun_sky_cc0.exr"
MM_PER_UNIT = 5.0


def large(width: int):
    """(seconds to reduce, peak extra MiB, seconds to extract the sun and project) of a width x width/2 RGBA map."""
    from translucency_addon.scene import environment_map as em

    h = width // 2
    img = np.empty((h, width, 4), np.float32)
    for r in range(0, h, 512):  # a sky gradient, written in bands
        img[r:r + 512] = np.linspace(0.2, 1.0, width, dtype=np.float32)[None, :, None]
    # a 0.5 degree sun of 20 W/m^2, 40 degrees up, drawn in the window of pixels around it
    el, az, half = math.radians(40.0), math.radians(-60.0), math.radians(0.25)
    sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    u, v = em.direction_to_uv(sun[None])
    i0, j0, k = int(v[0] * h), int(u[0] * width), int(math.ceil(2 * half / math.pi * h)) + 2
    rows = np.arange(i0 - k, i0 + k)
    cols = np.arange(j0 - 2 * k, j0 + 2 * k)
    e = math.pi * ((rows + 0.5) / h - 0.5)
    a = math.pi * (1.0 - 2.0 * (cols + 0.5) / width)
    d = np.stack(np.broadcast_arrays(np.cos(e)[:, None] * np.cos(a)[None, :], np.cos(e)[:, None] * np.sin(a)[None, :],
                                     np.sin(e)[:, None]), axis=-1)
    disk = d @ sun >= math.cos(half)
    img[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1][disk] = 20.0 / (2 * math.pi * (1 - math.cos(half)))
    tracemalloc.start()
    t0 = time.perf_counter()
    small = em.downsample(img, 2048)
    t1 = time.perf_counter()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    found, rest, why = em.extract_sun(small)
    em.project_equirect(rest)
    t2 = time.perf_counter()
    got = (f"sun found {math.degrees(math.acos(min(1.0, float(np.dot(found.direction, sun))))):.2f} deg off, "
           f"{float(np.dot(found.irradiance, [0.2126, 0.7152, 0.0722])):.1f} of 20 W/m^2" if found else why)
    return img.nbytes / 2**20, t1 - t0, peak / 2**20, t2 - t1, small.shape, got


def irradiance_check(n_normals: int = 600):
    """Irradiance on a plane of every orientation from the shipped HDRI: brute force over its pixels against
    what the engine receives (order-2 SH + the extracted sun), the same SH with the sun left in, and the
    map's mean (a uniform world).  Returns rows ``(label, rel. RMS, worst, sunlit worst, shaded worst)``."""
    from tools.make_hdri import pixels
    from translucency_addon.scene import environment_map as em
    from translucency_addon.scene.sh import fibonacci_directions, transmitted_flux_from_sh

    L = pixels().astype(np.float64)
    h, w = L.shape[:2]
    d = em.equirect_directions(h, w).reshape(-1, 3)
    wt = np.repeat(em.equirect_solid_angles(h, w), w)
    Lw = L.reshape(-1, 3) * wt[:, None]
    n = fibonacci_directions(n_normals)
    truth = np.zeros((len(n), 3))
    for a in range(0, len(n), 50):
        truth[a:a + 50] = np.maximum(n[a:a + 50] @ d.T, 0.0) @ Lw
    sun, rest, _ = em.extract_sun(L)
    s = np.asarray(sun.direction)
    ours = transmitted_flux_from_sh(em.project_equirect(rest), n, 1.0) + \
        np.maximum(n @ s, 0.0)[:, None] * np.asarray(sun.irradiance)[None, :]
    smeared = transmitted_flux_from_sh(em.project_equirect(L), n, 1.0)
    uniform = np.broadcast_to(np.pi * np.sum(Lw, axis=0) / (4 * np.pi), truth.shape)
    lit, shade = n @ s > 0.2, n @ s < -0.2
    scale = truth.mean()
    rows = []
    for label, est in (("order-2 SH + the extracted sun (the add-on)", ours),
                       ("order-2 SH with the sun left in", smeared), ("the map's mean (a uniform world)", uniform)):
        err = (est - truth).mean(axis=1)
        rows.append((label, float(np.sqrt(np.mean(err ** 2)) / scale), float(np.abs(err).max() / scale),
                     float(np.abs(err[lit]).max() / scale), float(np.abs(err[shade]).max() / scale)))
    return rows, sun


def hdri_mean() -> np.ndarray:
    """The shipped HDRI's mean radiance per channel (solid-angle weighted), W/(m^2 sr)."""
    from tools.make_hdri import pixels
    from translucency_addon.scene import environment_map as em

    L = pixels().astype(np.float64)
    wt = em.equirect_solid_angles(*L.shape[:2])
    return np.sum(L * wt[:, None, None], axis=(0, 1)) / (4 * np.pi)


def hdri_sun():
    """The sun the add-on extracts from the shipped HDRI (world space)."""
    from tools.make_hdri import pixels
    from translucency_addon.scene import environment_map as em

    return em.extract_sun(pixels())[0]


def _scene(kind="hdri"):
    import bpy

    from bench.reference.cycles_ref import empty_node_tree

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, segments=48, ring_count=24)
    obj = bpy.context.object
    bpy.ops.object.shade_smooth()
    cd = bpy.data.cameras.new("camera")
    cd.type = 'ORTHO'
    cd.ortho_scale = 2.2
    cam = bpy.data.objects.new("camera", cd)
    cam.location = (0.0, 0.0, 5.0)
    sc.collection.objects.link(cam)
    sc.camera = cam
    world = bpy.data.worlds.new("HDRI")
    tree = empty_node_tree(world)
    bg = tree.nodes.new("ShaderNodeBackground")
    out = tree.nodes.new("ShaderNodeOutputWorld")
    if kind == "uniform":
        bg.inputs["Color"].default_value = (*hdri_mean(), 1.0)
    elif kind == "sun":  # the HDRI's sun as a Blender Sun lamp of the same size, in a black world
        from mathutils import Vector

        sun = hdri_sun()
        E = np.asarray(sun.irradiance)
        bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        ld = bpy.data.lights.new("sun", 'SUN')
        ld.energy = float(E.max())
        ld.color = tuple(float(x) for x in E / E.max())
        ld.angle = sun.angle
        lo = bpy.data.objects.new("sun", ld)
        lo.rotation_mode = 'QUATERNION'
        lo.rotation_quaternion = Vector((0, 0, -1)).rotation_difference(Vector([-x for x in sun.direction]))
        sc.collection.objects.link(lo)
    else:
        env = tree.nodes.new("ShaderNodeTexEnvironment")
        env.image = bpy.data.images.load(str(HDRI))
        tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    tree.links.new(bg.outputs[0], out.inputs["Surface"])
    sc.world = world
    r = sc.render
    r.engine = 'CYCLES'
    sc.cycles.device = 'CPU'
    sc.cycles.use_denoising = False
    sc.cycles.pixel_filter_type = 'BOX'
    sc.cycles.filter_width = 1.0
    sc.view_settings.view_transform = 'Standard'
    r.image_settings.file_format = 'OPEN_EXR'
    r.image_settings.color_depth = '32'
    return sc, obj


def _read(path, W, H):
    import bpy

    img = bpy.data.images.load(path)
    px = np.empty(W * H * img.channels, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(H, W, -1)[::-1]


def addon_pass(res: int, tmp: str, kind="hdri"):
    """The add-on's Translucency pass (F12, Cycles), (res, res, 3), and what the World became."""
    import bpy

    sys.path.insert(0, str(ROOT / "tests"))
    import conftest

    addon = conftest.load_addon()
    from tools.exr import exr_pass
    from translucency.ops import render_pass, world

    sc, obj = _scene(kind)
    addon.register()
    try:
        s = obj.translucency
        s.enabled = True
        s.material_preset = 'MARBLE'
        s.eta = 1.0
        s.use_mm_per_unit_override = True
        s.mm_per_unit = MM_PER_UNIT
        s.quality = 'PREVIEW'
        bpy.context.view_layer.objects.active = obj
        t0 = time.perf_counter()
        assert bpy.ops.translucency.bake() == {'FINISHED'}, s.status.bake_status
        t_bake = time.perf_counter() - t0
        t0 = time.perf_counter()
        assert bpy.ops.translucency.solve() == {'FINISHED'}
        t_solve = time.perf_counter() - t0
        note = world.status_line()
        bpy.ops.translucency.add_to_material()
        sc.render.resolution_x = sc.render.resolution_y = res
        sc.cycles.samples = 4
        render_pass.configure_output(sc.render.image_settings, 'OPEN_EXR_MULTILAYER')
        path = os.path.join(tmp, "addon.exr")
        sc.render.filepath = path
        bpy.ops.render.render(write_still=True)
        px = exr_pass(Path(path), "Translucency")[..., :3]
        return px, note, t_bake, t_solve
    finally:
        addon.unregister()


def cycles_volume(res: int, spp: int, tmp: str, progress=print, kind="hdri"):
    """Cycles' volume render of the same sphere (index-matched), (res, res, 3), its standard error, seconds."""
    import bpy

    from bench.reference.cycles_ref import volume_material
    from translucency_addon.scene.materials import material_from_preset

    sa, ss = material_from_preset("marble").coefficients(n=1)
    out = np.zeros((res, res, 3))
    se = np.zeros((res, res, 3))
    t0 = time.perf_counter()
    for c in range(3):
        sc, obj = _scene(kind)
        mat, _ = volume_material(bpy, "volume", float(ss[0, c]), float(sa[0, c]), MM_PER_UNIT, surface=None)
        obj.data.materials.append(mat)
        cy = sc.cycles
        for attr in ("max_bounces", "volume_bounces", "transmission_bounces", "glossy_bounces", "diffuse_bounces",
                     "transparent_max_bounces", "min_light_bounces", "min_transparent_bounces"):
            setattr(cy, attr, 1024)
        cy.sample_clamp_direct = cy.sample_clamp_indirect = 0.0
        cy.use_adaptive_sampling = False
        if hasattr(cy, "use_guiding"):
            cy.use_guiding = False
        sc.render.film_transparent = True  # the world's own pixels are not compared
        sc.render.resolution_x = sc.render.resolution_y = res
        halves = []
        for k in range(2):  # two independent halves of the samples: the standard error per pixel
            cy.samples = spp // 2
            cy.seed = 101 + 7 * c + k
            path = os.path.join(tmp, f"cyc{c}{k}.exr")
            sc.render.filepath = path
            bpy.ops.render.render(write_still=True)
            halves.append(_read(path, res, res)[..., c])
        out[..., c] = 0.5 * (halves[0] + halves[1])
        se[..., c] = 0.5 * np.abs(halves[0] - halves[1])
        progress(f"  cycles channel {c}: {time.perf_counter() - t0:.0f} s")
    return out, se, time.perf_counter() - t0


def masks(res: int):
    yy, xx = np.mgrid[0:res, 0:res] + 0.5
    x = (xx - res / 2) / (res / 2) * 1.1
    y = (res / 2 - yy) / (res / 2) * 1.1
    inside = np.hypot(x, y) < 1.0 - 2 * 2.2 / res
    return inside, inside & (x > 0.15), inside & (x < -0.15)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--large", type=int, nargs="*", default=[8192, 16384])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--no-cycles", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "docs" / "accuracy.md"))
    a = ap.parse_args(argv)
    lines = [HEADING, "\n", "Written by `bench/world.py` (`nice -n 10 .venv/bin/python -m bench.world`); "
             "CPU, 2 cores shared with other jobs.\n", "\n",
             "**Large HDRIs** (synthetic float32 RGBA maps: a sky gradient and a 0.5 degree sun of 20 W/m^2; "
             "reduced to 2048 x 1024 before anything else):\n\n",
             "| map | its buffer | reduce | peak extra memory | sun + SH of the reduced map |\n",
             "|---|---|---|---|---|\n"]
    for w in a.large:
        mib, t_red, peak, t_rest, shape, found = large(w)
        lines.append(f"| {w} x {w // 2} | {mib:.0f} MiB | {t_red:.2f} s | {peak:.0f} MiB | {t_rest:.2f} s "
                     f"({shape[1]} x {shape[0]}; {found}) |\n")
        print(lines[-1], end="", flush=True)
    rows, sun = irradiance_check()
    lines.append("\n**What the World becomes.** Irradiance on a plane of 600 orientations under the shipped HDRI "
                 "`tests/data/sun_sky_cc0.exr` (its sun 1.5 degrees across, 20 W/m^2), brute force over its "
                 "524,288 pixels against what the engine receives, unoccluded, no Fresnel (errors relative to the "
                 f"mean irradiance; sunlit/shaded: the planes facing within 78 degrees of the sun or away from it; "
                 f"the sun found: {sun.angle_degrees:.2f} degrees across, "
                 f"{float(np.dot(sun.irradiance, [0.2126, 0.7152, 0.0722])):.2f} W/m^2):\n\n"
                 "| environment | RMS error | worst | worst sunlit | worst shaded |\n|---|---|---|---|---|\n")
    for label, rms, worst, wl, ws in rows:
        lines.append(f"| {label} | {100 * rms:.1f} % | {100 * worst:.1f} % | {100 * wl:.1f} % | {100 * ws:.1f} % |\n")
    print("".join(lines[-4:]), flush=True)
    lines.append("\nBlender itself holds the loaded image (the same size again) and `Image.pixels.foreach_get` "
                 "needs the buffer above once per change of the World; every later frame reuses the cached SH.\n")
    if not a.no_cycles:
        import conftest  # noqa: F401  (tests/ on the path below: a temporary Blender user folder before bpy)
    text = "".join(lines)
    if not a.no_cycles:
        inside, lit, shade = masks(a.res)
        fmt = lambda v: ", ".join(f"{x:.4f}" for x in v)  # noqa: E731
        rows, notes = [], {}
        worlds = (("hdri", "the HDRI"), ("sun", "its sun alone, as a Sun lamp"), ("uniform", "its mean, uniform"))
        for kind, world in worlds:
            with tempfile.TemporaryDirectory(prefix="translucency-world-") as tmp:
                ours, note, t_bake, t_solve = addon_pass(a.res, tmp, kind)
                cyc, se, t_cyc = cycles_volume(a.res, a.spp, tmp, kind=kind)
            notes[kind] = (note, t_bake, t_solve, t_cyc)
            regions = ((("whole sphere", inside),) if kind == "uniform" else
                       (("whole sphere", inside), ("sunlit half (x > 0)", lit), ("shaded half (x < 0)", shade)))
            for label, m in regions:
                o, c = ours[m].mean(0), cyc[m].mean(0)
                e = np.sqrt((se[m] ** 2).sum(0)) / m.sum()
                rows.append(f"| {world} | {label} ({m.sum()} px) | {fmt(o)} | "
                            + ", ".join(f"{x:.4f} ± {y:.4f}" for x, y in zip(c, e)) + " | "
                            + ", ".join(f"{100 * (x / y - 1):+.1f} %" for x, y in zip(o, c)) + " |\n")
                print(rows[-1], end="", flush=True)
        note, t_bake, t_solve, t_cyc = notes["hdri"]
        mean = hdri_mean()
        text += ("\n**Against Cycles.** Marble sphere, R = 5 mm, IOR 1 (index-matched), lit only by the shipped "
                 "HDRI `tests/data/sun_sky_cc0.exr` (generated, CC0: `tools/make_hdri.py`), and, in the same run, "
                 f"by a Sun lamp and by a uniform world of the HDRI's mean radiance ({fmt(mean)}), orthographic "
                 "view from above, "
                 f"{a.res} x {a.res} px. The add-on (Preview quality): {note}; bake {t_bake:.1f} s, solve "
                 f"{t_solve:.2f} s. Cycles: Volume Scatter + Absorption, {a.spp} spp per channel, {t_cyc:.0f} s "
                 f"(the Sun lamp {notes['sun'][3]:.0f} s, the uniform world {notes['uniform'][3]:.0f} s). The same run "
                 "renders the HDRI's extracted sun alone as a Blender Sun lamp (same irradiance, direction and "
                 "angle) in a black world, and a uniform world of the HDRI's mean radiance: the World's conversion "
                 "is checked above to 0.1 %, so what differs from Cycles under the HDRI is the diffusion model "
                 "under a sun, which the Sun-lamp row shows alone.\n\n"
                 "| world | region | add-on (R, G, B) | Cycles (R, G, B) ± s.e. | add-on / Cycles - 1 |\n"
                 "|---|---|---|---|---|\n" + "".join(rows))
        print(text)
    from bench.accuracy_text import replace_section

    out = Path(a.out)
    body = text[len(HEADING):]
    out.write_text(replace_section(out.read_text() if out.exists() else "", HEADING, body))
    print(f"wrote {out}")


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT / "tests"))
    main()
