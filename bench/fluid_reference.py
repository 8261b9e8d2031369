"""A particle fluid against the independent path tracer (issue 14): Mitsuba 3 vs our radiance on its surface.

    .venv/bin/python bench/fluid_reference.py [--spp 2048] [--refresh]

The fluid: particles on a cubic lattice (jittered by 10 % of the spacing)
filling an ellipsoid of semi-axes 12 x 9 x 7 mm, radius = the spacing, skim
milk (eta 1.3), lit by the accuracy report's SH sky lobe (the stand-in for a
sun a path tracer can render behind a smooth dielectric), seen
orthographically along -z at 32 x 32 pixels.  Its surface mesh -- what a user
renders -- is the ellipsoid (an icosphere of 5,120 facets scaled to it).

* **reference**: Mitsuba 3 renders the mesh filled with the homogeneous medium
  (``bench/reference/mitsuba_ref.py``: volpath, Russian roulette off, one grey
  render per channel, the surface reflection subtracted), cached in
  ``bench/data/reference/`` like the accuracy report's references (rendered
  once; ``--refresh`` renders again);
* **ours**: ``FluidSolver`` on the particles at two spacings (1 mm and
  0.75 mm), ``vertex_radiance`` toward the camera on the same mesh,
  rasterised by ``bench/reference/raster.py``; and, for scale, the QuadGraph
  path (``bake_mesh`` Preview of the mesh, ``DiffusionSolver``) on the same
  mesh and light.

The relative RMS error over the object's pixels (``bench/reference/metrics.py``)
goes to ``bench/data/fluid_reference.json`` and to the "Particle fluids"
subsection of ``docs/accuracy.md`` (:func:`markdown_section`, which
``bench/accuracy_text.py`` also appends when it rewrites the report).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RESULT = ROOT / "bench" / "data" / "fluid_reference.json"
REF_CACHE = ROOT / "bench" / "data" / "reference"
SEMI_AXES = (12.0, 9.0, 7.0)  # mm
SPACINGS = (1.0, 0.75)  # mm
HEADING = "## Particle fluids (Voronoi-fluid cells, issue 14)\n"


def fluid_particles(spacing: float, seed: int = 0) -> np.ndarray:
    """Lattice points whose cells lie inside the ellipsoid, jittered by 10 % of the spacing."""
    a = np.asarray(SEMI_AXES)
    m = int(np.ceil(a.max() / spacing)) + 1
    g = np.stack(np.meshgrid(*[np.arange(-m, m + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) * spacing
    inside = np.linalg.norm(g / (a - 0.5 * spacing), axis=1) < 1.0
    g = g[inside].astype(np.float64)
    return g + np.random.default_rng(seed).uniform(-0.1 * spacing, 0.1 * spacing, g.shape)


def scene():
    from bench.accuracy_scenes import SKY_DIR
    from bench.reference.scene import Camera, RefScene, sky_environment
    from translucency_addon.geometry import primitives
    from translucency_addon.scene.materials import material_from_preset

    V, F = primitives.icosphere(1.0, 4)
    V = V * np.asarray(SEMI_AXES)
    cam = Camera.orthographic((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=2.2 * SEMI_AXES[0])
    return RefScene(V, F, 1.0, material_from_preset("skimmilk"), cam, lights=[],
                    environment=sky_environment(SKY_DIR, lobe=2, irradiance=np.pi), resolution=(32, 32),
                    spp=2048, name="fluid_ellipsoid_skimmilk_sky")


def ours(sc):
    """Our images of the scene: the fluid at each spacing and the QuadGraph Preview bake."""
    from bench.accuracy_core import SUPERSAMPLE, view_dirs
    from bench.reference.raster import rasterize
    from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
    from translucency_addon.diffusion.solver import DiffusionSolver
    from translucency_addon.fluid import FluidSolver, suggest_radius

    vd = view_dirs(sc)
    out = []
    for s in SPACINGS:
        P = fluid_particles(s)
        t = time.perf_counter()
        res = FluidSolver(sc.material, suggest_radius(P), sc.mm_per_unit).solve(
            P, environment=sc.environment, surface=(sc.V, sc.F), view_dirs=vd)
        sec = time.perf_counter() - t
        ras = rasterize(sc.V, sc.F, res.vertex_radiance, sc.camera, sc.resolution, supersample=SUPERSAMPLE)
        out.append({"label": f"fluid, spacing {s:g} mm", "particles": int(len(P)), "cells": res.stats["cells"],
                    "surface_nodes": res.stats["surface_nodes"], "seconds": sec, "image": ras.image, "mask": ras.mask,
                    "warnings": res.warnings})
    t = time.perf_counter()
    bake = bake_mesh(sc.V, sc.F, BakeSettings(quality="preview", mm_per_unit=sc.mm_per_unit))
    solver = DiffusionSolver(bake, sc.material)
    L = solver.vertex_radiance(solver.solve([], sc.environment), vd)
    sec = time.perf_counter() - t
    ras = rasterize(sc.V, sc.F, L, sc.camera, sc.resolution, supersample=SUPERSAMPLE)
    lv = bake.levels[-1]
    out.append({"label": "QuadGraph Preview bake of the mesh", "particles": 0, "cells": int(lv.n_inner),
                "surface_nodes": int(lv.n_surface), "seconds": sec, "image": ras.image, "mask": ras.mask,
                "warnings": []})
    return out


def run(spp: int, refresh: bool) -> dict:
    from bench.reference.metrics import relative_rms
    from bench.reference.mitsuba_ref import cached_reference, scene_key

    sc = scene()
    sc.spp = spp
    key_path = REF_CACHE / f"{sc.name}-{scene_key(sc)}.npz"
    if refresh and key_path.exists():
        key_path.unlink()
    t = time.perf_counter()
    ref = cached_reference(sc, REF_CACHE, progress=lambda m: print(m, file=sys.stderr))
    rendered = time.perf_counter() - t
    rows = []
    for o in ours(sc):
        e = relative_rms(o["image"], ref.image, o["mask"], ref.mask, stderr=ref.stderr)
        bias = (o["image"][o["mask"] & ref.mask].mean(axis=0) / ref.image[o["mask"] & ref.mask].mean(axis=0) - 1.0)
        rows.append({k: v for k, v in o.items() if k not in ("image", "mask")} | {
            "rel_rms": e.rel_rms, "rel_rms_rgb": list(e.rel_rms_rgb), "noise_floor": e.noise_floor,
            "debiased": float(np.sqrt(max(e.rel_rms**2 - e.noise_floor**2, 0.0))), "bias_rgb": bias.tolist(),
            "pixels": e.pixels})
    return {"scene": sc.name, "cache": str(key_path.relative_to(ROOT)), "spp": int(ref.spp),
            "reference_seconds": float(ref.seconds), "loaded_in": rendered,
            "reference_mean": ref.image[ref.mask].mean(axis=0).tolist(), "rows": rows}


def markdown_section(data: dict | None = None) -> str:
    """The "Particle fluids" subsection of docs/accuracy.md from the stored result ('' if none)."""
    if data is None:
        if not RESULT.exists():
            return ""
        data = json.loads(RESULT.read_text())
    lines = [HEADING.rstrip("\n"), "",
             f"`.venv/bin/python bench/fluid_reference.py` (the reference is cached in `{data['cache']}`; "
             f"`--refresh` renders it again, {data['reference_seconds']:.0f} s here). Particles on a cubic lattice "
             f"jittered by 10 % fill an ellipsoid of {' x '.join(f'{a:g}' for a in SEMI_AXES)} mm semi-axes, radius = "
             "the spacing, skim milk, the SH sky lobe of the scenes above, 32 x 32 pixels orthographic; the path "
             f"tracer renders the ellipsoid mesh (5,120 facets) filled with the medium at {data['spp']:,} spp per "
             "channel; ours is `FluidSolver(...).solve(particles, surface=mesh, view_dirs=...)` on the same mesh.", "",
             "| our side | particles | cells / surface cells | frame s (cold) | (b) vs path tracer | (b) debiased | "
             "R, G, B | mean brightness R, G, B |", "|---|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['label']} | {r['particles']:,} | {r['cells']:,} / {r['surface_nodes']:,} | "
                     f"{r['seconds']:.2f} | {100 * r['rel_rms']:.1f} % | {100 * r['debiased']:.1f} % | "
                     + ", ".join(f"{100 * v:.1f} %" for v in r["rel_rms_rgb"]) + " | "
                     + ", ".join(f"{100 * v:+.1f} %" for v in r["bias_rgb"]) + " |")
    floor = data["rows"][0]["noise_floor"]
    lines += ["", f"The reference's noise floor is {100 * floor:.2f} %. The QuadGraph row is the mesh pipeline on "
              "the same surface (its bake is included in its time): the gap between it and the fluid rows is what "
              "the particle discretisation costs; the rest is the diffusion model's own error on this scene "
              "(compare `sphere_skimmilk_sky` above).", "",
              "Checked by `tests/test_fluid_solve.py` against the closed-form sphere (12 mm, uniform light, mean "
              "radiance on a sphere mesh; jittered lattices of 739, 1,791 and 6,403 particles): marble -1.3 %, "
              "-0.8 %, -0.4 % and skim milk -2.4 %, -1.4 %, -0.8 % in the worst channel, falling with the particle "
              "count.  Flicker: particles re-jittered by 10 % of their spacing every frame in a static blob change "
              "the per-vertex radiance by at most 0.9 % of the peak under uniform light and 6.4 % under a sun "
              "(skim milk, blue; the test's bounds are 1 % and 8 %).  Cell geometry is exact: lattice volumes and "
              "face areas to 1e-9 (`tests/test_fluid_cells.py`).", ""]
    return "\n".join(lines)


def update_accuracy_doc(section: str, path: Path = ROOT / "docs" / "accuracy.md") -> None:
    """Replace (or append) only the fluid section of docs/accuracy.md (kept by bench/accuracy.py's rewrite)."""
    from bench.accuracy_text import replace_section

    path.write_text(replace_section(path.read_text(), HEADING, section[len(HEADING):]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=2048, help="samples per pixel per channel of the reference")
    ap.add_argument("--refresh", action="store_true", help="render the reference again")
    a = ap.parse_args(argv)
    data = run(a.spp, a.refresh)
    RESULT.write_text(json.dumps(data, indent=1) + "\n")
    section = markdown_section(data)
    update_accuracy_doc(section)
    print(section)
    return 0


if __name__ == "__main__":
    sys.exit(main())
