"""Voxel Number Map benchmark (Mochida et al.): precompute, memory and frame time, and how they grow.

    python -m bench.voxel_number_map [--out docs/bench_voxel_number_map.md] [--quick] [--gpu]

1. The paper's scenes (``bench/inner_parts_scenes.py``): a cube with a spherical cavity (2,180
   vertices) and a bottle of wine (9,926 vertices, two LUTs: glass and wine).  Precompute per stage,
   LUT and run-time kernel memory, the per-material preparation, and the frame time: a sun and a
   sky; "frame" = lights changed (shadow rays cached per light pose), "light moved" = new shadow
   rays.  Targets on 2 CPU cores: cube <= 10 ms, bottle <= 40 ms per frame, bottle precompute
   <= 30 s.  The paper's GPU figures (405 and 238 FPS) are the anchor for the GLSL kernel.
2. Growth with the surface-voxel count n (the cube with its cavity at other targets): the LUT is
   quadratic; beyond ``MAX_SURFACE_VOXELS`` (4,096) a bake is refused (rows show the memory it
   would need).
3. ``--gpu``: the GLSL kernel through Blender's ``gpu`` module.  Without a real GPU this is llvmpipe
   (Mesa's software rasteriser on the same CPU cores): those times say nothing about a GPU.

Times are medians of repeated frames (wall clock) with the best frame beside them; other jobs share
the 2 cores (the packed kernel, 22 MiB for the cube, is read from memory every frame, so a loaded
machine slows the transport step most), so the load average is printed and ratios within one run are
what carry over.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench.bench_io import write_file  # noqa: E402

from bench import inner_parts_scenes as scenes  # noqa: E402
from translucency_addon.scene.lights import Light  # noqa: E402
from translucency_addon.voxel_number_map import (MAX_SURFACE_VOXELS, VNMSettings,  # noqa: E402
                                                 VoxelNumberMapEvaluator, bake_voxel_number_map, kernel_bytes,
                                                 lut_bytes)

PAPER_FPS = {"cube_cavity_ss": 405, "bottle": 238}
MIB = 2.0**20


def table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def load() -> str:
    return f"{os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else "n/a"


def lights_for(k: int):
    """A sun and a world light; ``k`` turns the sun (a new light pose: new shadow rays)."""
    from bench.reference.scene import sky_environment

    a = np.deg2rad(20.0 * k)
    d = np.array([-np.cos(a), -0.3, -0.5 - 0.2 * np.sin(a)])
    return [Light("sun", irradiance=800.0, direction=tuple(d))], sky_environment(scenes.sky_to_light(), lobe=2)


def frame_times(ev, reps: int):
    """(median frame ms with cached shadows, median ms when the light moved, per-stage medians)."""
    lights, env = lights_for(0)
    view = ("ORTHO", (0.3, -1.0, 0.4))
    ev.radiance(lights, env, view)
    cached, stages = [], {"lights": [], "transport": [], "output": []}
    for _ in range(reps):
        t = time.perf_counter()
        ev.radiance(lights, env, view)
        cached.append(time.perf_counter() - t)
        for k in stages:
            stages[k].append(ev.seconds[k])
    moved = []
    for k in range(1, 1 + max(3, reps // 4)):
        lights, _ = lights_for(k)
        t = time.perf_counter()
        ev.radiance(lights, env, view)
        moved.append(time.perf_counter() - t)
    st = {k: 1e3 * np.median(v) for k, v in stages.items()}
    st["best"] = 1e3 * min(cached)
    return 1e3 * np.median(cached), 1e3 * np.median(moved), st


def scene_rows(reps: int, quick: bool):
    rows, stage_rows = [], []
    for name in ("cube_cavity_ss", "bottle"):
        comp, mm = scenes.SCENES[name]()
        settings = VNMSettings(quality=scenes.quality_for(name))
        t0 = time.perf_counter()
        vnm = bake_voxel_number_map(comp, settings, mm_per_unit=mm)
        bake_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        ev = VoxelNumberMapEvaluator(vnm, comp.material)
        prep_s = time.perf_counter() - t0
        frame, moved, st = frame_times(ev, reps)
        t = vnm.stats["time"]
        fps = PAPER_FPS.get(name)
        rows.append([name, f"{scenes.n_vertices(comp):,}", f"{vnm.n:,}", vnm.n_components,
                     f"{vnm.lut_bytes / MIB:.1f}", f"{ev.kernel.nbytes / MIB:.1f}", f"{bake_s:.1f}", f"{prep_s:.1f}",
                     f"{frame:.1f} / {st['best']:.1f}", f"{moved:.1f}", f"{1e3 / frame:.0f}",
                     f"{fps} ({1e3 / fps:.1f} ms)"])
        stage_rows.append([name] + [f"{t.get(k, 0.0):.2f}" for k in ("resolution", "voxelise", "surface", "lut",
                                                                      "visibility")]
                          + [f"{st['lights']:.2f}", f"{st['transport']:.2f}", f"{st['output']:.2f}"])
    return rows, stage_rows


def growth_rows(targets, reps: int):
    comp, mm = scenes.cube_cavity("single-scattering")
    rows = []
    for target in targets:
        if target > MAX_SURFACE_VOXELS:
            rows.append([f"~{target:,}", f"{lut_bytes(target, 1) / MIB:.0f}", f"{kernel_bytes(target) / MIB:.0f}",
                         "refused (budget)", "", "", ""])
            continue
        t0 = time.perf_counter()
        vnm = bake_voxel_number_map(comp, VNMSettings(surface_voxels=target), mm_per_unit=mm)
        bake_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        ev = VoxelNumberMapEvaluator(vnm, comp.material)
        prep_s = time.perf_counter() - t0
        frame, _, st = frame_times(ev, reps)
        rows.append([f"{vnm.n:,}", f"{vnm.lut_bytes / MIB:.1f}", f"{ev.kernel.nbytes / MIB:.1f}", f"{bake_s:.1f}",
                     f"{prep_s:.2f}", f"{frame:.1f} / {st['best']:.1f}", f"{st['transport']:.2f}"])
    return rows


def gpu_rows(targets):
    """The GLSL kernel (prefer="GPU") against BLAS on the same maps; needs bpy."""
    import bpy  # noqa: F401  (Blender as a module: the gpu module's home)

    import gpu_shaders
    from gpu_shaders import voxel_number_map as gv

    renderer = gpu_shaders.init_headless()
    comp, mm = scenes.cube_cavity("single-scattering")
    rows = []
    for target in targets:
        vnm = bake_voxel_number_map(comp, VNMSettings(surface_voxels=target, env_directions=16), mm_per_unit=mm)
        tr, _, _ = gv.make_transmission(vnm, prefer="GPU")
        ev = VoxelNumberMapEvaluator(vnm, comp.material, transmission=tr)
        x = np.random.default_rng(0).random((vnm.n, 3))
        ref = ev.kernel.product(x)
        tr.product(x)
        ts = []
        for _ in range(3):
            t = time.perf_counter()
            got = tr.product(x)
            ts.append(time.perf_counter() - t)
        tc = []
        for _ in range(10):
            t = time.perf_counter()
            ev.kernel.product(x)
            tc.append(time.perf_counter() - t)
        err = float(np.abs(got - ref).max() / np.abs(ref).max())
        rows.append([f"{vnm.n:,}", f"{1e3 * min(ts):.1f}", f"{1e3 * np.median(tc):.2f}", f"{err:.1e}"])
        tr.free()
    return renderer, rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="write the tables as markdown to this file")
    ap.add_argument("--quick", action="store_true", help="fewer frames and sizes (a smoke run)")
    ap.add_argument("--gpu", action="store_true", help="also time the GLSL kernel through bpy's gpu module")
    a = ap.parse_args(argv)
    reps = 5 if a.quick else 25
    lines = ["# Voxel Number Map benchmark", "",
             f"`python -m bench.voxel_number_map{' --quick' if a.quick else ''}{' --gpu' if a.gpu else ''}`; "
             f"{os.cpu_count()} CPUs, load average at the start {load()}.  **No GPU was available in this session**: "
             "every time below is a CPU time (numpy + BLAS on 2 shared cores).  The paper's GPU figures (405 FPS "
             "for its cube, 238 FPS for its bottle with two LUTs) are the anchor for the GLSL kernel "
             "(`gpu_shaders/voxel_number_map.glsl`) once it runs on a real GPU.", ""]
    rows, stage_rows = scene_rows(reps, a.quick)
    lines += ["## The paper's scenes", "",
              "Frame = one sun (shadow rays cached per light pose) and a sky (SH world, 64 baked directions), "
              "orthographic view, radiance at every outer-mesh vertex.  Light moved = the sun turned: new shadow "
              "rays for every surface voxel.  Prepare = once per material (the packed kernel, the near-entry "
              "tables and the world's weights).  Targets: cube <= 10 ms and bottle <= 40 ms per frame, bottle "
              "precompute <= 30 s.", "",
              table(["scene", "vertices", "surface voxels", "media (LUTs)", "LUT MiB (fp16)", "kernel MiB (fp32)",
                     "precompute s", "prepare s", "frame ms (median / best)", "light moved ms", "FPS (CPU, median)",
                     "paper FPS (GPU)"], rows),
              "", "Per stage (s for the bake, ms for a frame):", "",
              table(["scene", "resolution", "voxelise", "surface", "LUT", "sky visibility", "frame: lights",
                     "frame: transport", "frame: output"], stage_rows), ""]
    targets = [250, 500, 1000, 2000] if a.quick else [250, 500, 1000, 2000, 3000, 4000, 6000, 8000, 16000]
    lines += ["## Growth with the surface-voxel count", "",
              "The cube with its cavity at several targets (one medium).  The LUT holds n (n + 1)/2 pairs (fp16 "
              "lengths per medium + one blocked bit), the run-time kernel the same pairs in float32 for three "
              f"channels; the budget ends at {MAX_SURFACE_VOXELS:,} surface voxels (34 MiB of LUT for two media, "
              "100 MiB of kernel): larger maps are refused with these numbers, or coarsened when the resolution "
              "is 'auto'.", "",
              table(["surface voxels", "LUT MiB", "kernel MiB", "precompute s", "prepare s",
                     "frame ms (median / best)", "transport ms"], growth_rows(targets, max(5, reps // 2))), ""]
    if a.gpu:
        renderer, rows = gpu_rows([250, 500, 1000] if a.quick else [250, 500, 1000, 2000])
        lines += ["## The GLSL kernel", "",
                  f"Renderer: **{renderer}**.  "
                  + ("**This is a software rasteriser on the CPU: these times are not GPU times**; the error "
                     "column carries over." if "llvmpipe" in renderer.lower() else ""), "",
                  table(["surface voxels", "kernel ms (GLSL)", "BLAS ms (same x)", "max rel. error"], rows), ""]
    lines += [f"Load average at the end {load()}.", ""]
    text = "\n".join(lines)
    write_file(text, a.out)


if __name__ == "__main__":
    main()
