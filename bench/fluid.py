"""Particle-fluid benchmark (issue 14): Voronoi-fluid cells, light pass, warm solve and output per frame.

    .venv/bin/python bench/fluid.py [--sizes 4096 16384 65536 262144] [--frames 3] [--out docs/bench_fluid.md]

A ball of particles (a cubic lattice of spacing 1 unit = 0.5 mm, jittered
afresh by 10 % of the spacing every frame around its rest positions: the
temporal-stability case of the tests), radius = ``suggest_radius`` (the
spacing), skim milk, a uniform environment plus a sun with shadow rays, the
radiance carried onto an icosphere around the ball with about as many
vertices as there are surface cells.  Frame 0 starts cold; ``--frames`` more
frames are warm-started from the one before (``FluidSolver.solve(...,
warm_start=previous.state)``).  Each size runs in its own process (its peak
memory is measured there).  Per stage, the median over the warm frames:

* **cells**: input checks, neighbour pairs (``cKDTree``), exact faces and
  cells, the contract graph (surface nodes, smoothed normals);
* **light pass**: the ball occluder and eq. 3 with shadow rays;
* **warm solve**: assembly and the Chebyshev solve (with its guard) from the
  previous frame's phi, to a relative residual of 1e-4;
* **output**: the surface map and the corrected eq. 4/7 at the vertices.

Growth exponents ``log(t2/t1) / log(N2/N1)`` between consecutive sizes say how
close to linear each stage stays.  The machine has 2 CPU cores shared with
other work and no GPU: compare ratios within the table, not absolute times.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SPACING_MM = 0.5
STAGES = ("cells", "light pass", "warm solve", "output")
TARGET_N, TARGET_MS = 16384, 50.0  # issue 14: cells + warm solve + output at 16k particles on 2 CPU cores
PAPER = "Kang & Kim 2013 (GTX 680): 15,625 particles, 10 ms neighbours + 32 ms volumes and areas + 2 ms diffusion"


NOTES = """**Reading the table.**

* *Cells* grow linearly overall (the last row of the exponents; single steps scatter with the machine's
  load). They are exact (`translucency_addon/fluid/cells.py`): every candidate face (all particle pairs
  closer than 2R, about 16 per particle of which 7-8 keep a face) is a disk clipped by the bisecting
  planes of up to 16 other neighbours, computed in numpy as O(m^2) interval intersections per face. That
  is where 80 %+ of the frame goes. The paper's sampling (64 + 36 samples per cell and face) would cost the
  same order in numpy and be several percent off per cell, jumping as particles move.
* *Warm solve*: the time per sweep is linear in N; the sweep count grows with the ball's diameter in cells
  (Chebyshev needs about l/h sweeps), so the total grows like N^(4/3) here, where the ball grows with N at a
  fixed spacing. The warm start saves little in this benchmark because every particle is re-jittered by
  10 % of the spacing each frame (the temporal-stability case): the surface rows change by 10-20 %. With
  smooth motion (2 % of the spacing per frame) the warm start saves more than 30 % of the sweeps
  (`tests/test_fluid_solve.py::test_warm_start_by_id_saves_sweeps_and_keeps_the_answer`).
* **Target missed by about two orders of magnitude** on these 2 shared CPU cores. The cell geometry is
  one independent, branch-light job per face (a loop over at most ~32 lines in registers), the shape of
  a GPU compute kernel; the paper ran its (less exact) version on a GTX 680 in 42 ms. A GLSL twin of
  `disk_faces.clipped_disk` in `gpu_shaders/` (not written: that layer was being refactored during this
  work) is the way to the target; the solve already has its GPU path, but `gpu_shaders/pack.py` packs 4
  links per node and a fluid cell has 15-25.
"""


def ball(n_target: int, seed: int = 0):
    """Rest positions of about n_target particles on a unit lattice inside a ball."""
    r = (3.0 * n_target / (4.0 * np.pi)) ** (1.0 / 3.0)
    m = int(np.ceil(r)) + 1
    g = np.stack(np.meshgrid(*[np.arange(-m, m + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float64)
    return g[np.linalg.norm(g, axis=1) < r], r


def run_one(n: int, frames: int) -> dict:
    from translucency_addon import primitives
    from translucency_addon.fluid import FluidSolver, suggest_radius
    from translucency_addon.lights import Environment, Light
    from translucency_addon.materials import material_from_preset

    rest, r = ball(n)
    R = suggest_radius(rest)
    subdiv = int(np.clip(np.ceil(np.log(0.78 * 4.0 * np.pi * r * r / 10.0) / np.log(4.0)), 3, 7))  # ~ surface cells
    V, F = primitives.icosphere(r + 0.5 * R, subdiv)
    fs = FluidSolver(material_from_preset("skimmilk"), R, SPACING_MM)
    lights = [Light("sun", irradiance=1000.0, direction=(0.3, -0.5, -0.8))]
    env = Environment((1.0, 1.0, 1.0))
    rng = np.random.default_rng(1)
    rows, state = [], None
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for k in range(frames + 1):
        P = rest + rng.uniform(-0.1, 0.1, rest.shape)
        t = time.perf_counter()
        res = fs.solve(P, lights=lights, environment=env, surface=(V, F), warm_start=state)
        wall = time.perf_counter() - t
        state = res.state
        rows.append({"seconds": res.stats["seconds"], "sweeps": res.stats["sweeps"], "wall": wall,
                     "residual": max(res.stats["relative_residual"]), "warm": res.stats["warm_start"]})
    st = res.stats
    return {"n": int(len(rest)), "radius": R, "cells": st["cells"], "surface_nodes": st["surface_nodes"],
            "faces_per_cell": st["faces_per_cell"], "vertices": int(len(V)), "frames": rows,
            "peak_rss_mb": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - 0 * rss0) / 1024.0,
            "load": os.getloadavg()}


def summarise(one: dict) -> dict:
    warm = one["frames"][1:] or one["frames"]
    out = {}
    for key in ("cells", "light pass", "warm solve", "output", "total"):
        out[key] = float(np.median([_stages(f["seconds"])[key] for f in warm])) * 1e3
    for key in ("particles", "cells_neighbours", "cells_faces", "cells_cells", "graph", "occluder", "map",
                "assemble", "solve", "light", "output"):
        out["sub:" + key] = float(np.median([f["seconds"].get(key, 0.0) for f in warm])) * 1e3
    out["sweeps_cold"] = one["frames"][0]["sweeps"]
    out["sweeps_warm"] = float(np.median([f["sweeps"] for f in warm]))
    out["target"] = out["cells"] + out["warm solve"] + out["output"]
    return out


def _stages(sec: dict) -> dict:
    """The four stages of a frame from FluidSolver's seconds."""
    return {
        "cells": sec["particles"] + sec["cells"] + sec["graph"],
        "light pass": sec["occluder"] + sec["light"],
        "warm solve": sec["assemble"] + sec["solve"],
        "output": sec["map"] + sec["output"],
        "total": sec["total"],
    }


def table(results: list) -> str:
    lines = ["| particles | cells / surface | faces per cell | mesh vertices | cells ms | light pass ms | warm solve ms | "
             "output ms | cells + warm solve + output ms | sweeps cold / warm | warm solve ms per sweep | "
             "peak memory MB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    sums = [summarise(r) for r in results]
    for r, s in zip(results, sums):
        s["per_sweep"] = s["warm solve"] / max(s["sweeps_warm"], 1.0)
        lines.append(f"| {r['n']:,} | {r['cells']:,} / {r['surface_nodes']:,} | {r['faces_per_cell']:.1f} | "
                     f"{r['vertices']:,} | {s['cells']:,.0f} | {s['light pass']:,.0f} | {s['warm solve']:,.0f} | "
                     f"{s['output']:,.0f} | {s['target']:,.0f} | {s['sweeps_cold']} / {s['sweeps_warm']:.0f} | "
                     f"{s['per_sweep']:.2f} | {r['peak_rss_mb']:,.0f} |")
    keys = STAGES + ("per_sweep",)
    lines += ["", "Growth exponent of each stage, log(t2/t1) / log(N2/N1) (1 = linear; the output follows the mesh's "
              "vertex count, not N):", "",
              "| from -> to | cells | light pass | warm solve | output | warm solve per sweep |", "|---|---|---|---|---|---|"]
    pairs = list(zip(zip(results, sums), zip(results[1:], sums[1:])))
    if len(results) > 2:
        pairs.append(((results[0], sums[0]), (results[-1], sums[-1])))
    for (r1, s1), (r2, s2) in pairs:
        ex = [np.log(s2[k] / s1[k]) / np.log(r2["n"] / r1["n"]) for k in keys]
        lines.append(f"| {r1['n']:,} -> {r2['n']:,} | " + " | ".join(f"{e:.2f}" for e in ex) + " |")
    return "\n".join(lines), sums


def profile(results, sums) -> str:
    k = min(range(len(results)), key=lambda i: abs(results[i]["n"] - TARGET_N))
    r, s = results[k], sums[k]
    parts = [("input checks", "sub:particles"), ("neighbour pairs (cKDTree)", "sub:cells_neighbours"),
             ("exact faces (disk clipping)", "sub:cells_faces"), ("cell sums", "sub:cells_cells"),
             ("contract graph + smoothed normals", "sub:graph"), ("occluder voxels", "sub:occluder"),
             ("light pass (eq. 3, shadow rays)", "sub:light"), ("assembly", "sub:assemble"),
             ("Chebyshev solve + guard", "sub:solve"), ("surface map weights", "sub:map"),
             ("output (eq. 4/7 at vertices)", "sub:output")]
    tot = sum(s[key] for _, key in parts)
    lines = [f"Where the time goes at {r['n']:,} particles (median of the warm frames):", "",
             "| part | ms | share |", "|---|---|---|"]
    for name, key in parts:
        lines.append(f"| {name} | {s[key]:,.1f} | {s[key] / tot:.0%} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4096, 16384, 65536, 262144])
    ap.add_argument("--frames", type=int, default=3, help="warm frames after the cold one")
    ap.add_argument("--out", default=None)
    ap.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one is not None:
        print(json.dumps(run_one(a.one, a.frames)))
        return 0
    t0 = time.perf_counter()
    load0 = os.getloadavg()
    results = []
    for n in a.sizes:
        frames = a.frames if n <= 65536 else max(1, a.frames - 1)
        out = subprocess.run([sys.executable, __file__, "--one", str(n), "--frames", str(frames)],
                             capture_output=True, text=True, check=True)
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        s = summarise(results[-1])
        print(f"{results[-1]['n']:,} particles: cells {s['cells']:.0f} ms, light {s['light pass']:.0f} ms, "
              f"warm solve {s['warm solve']:.0f} ms, output {s['output']:.0f} ms", file=sys.stderr)
    t, sums = table(results)
    k = min(range(len(results)), key=lambda i: abs(results[i]["n"] - TARGET_N))
    got = sums[k]["target"]
    verdict = "met" if got <= TARGET_MS else "**missed**"
    load1 = os.getloadavg()
    text = (f"# Particle-fluid benchmark (Voronoi-fluid cells, Kang & Kim 2013)\n\n"
            f"Written by `bench/fluid.py` in {time.perf_counter() - t0:.0f} s. Do not edit by hand: "
            f"`.venv/bin/python bench/fluid.py --out docs/bench_fluid.md`.\n\n"
            f"**2 CPU cores shared with other work (load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the "
            f"end), no GPU** -- none was available to this work, so there are no GPU rows. Compare ratios within "
            f"the table, not absolute times.\n\n"
            f"Scene: a ball of particles (lattice spacing {SPACING_MM} mm jittered by 10 % every frame), radius = "
            f"the spacing, skim milk, uniform environment + sun with shadow rays, radiance onto an icosphere. "
            f"Median over the warm frames (frame 0 is cold); tolerance 1e-4.\n\n{t}\n\n"
            f"**Target** (issue 14): cells + warm solve + output <= {TARGET_MS:.0f} ms per frame at "
            f"{TARGET_N:,} particles on 2 CPU cores: {got:,.0f} ms, {verdict}. {PAPER}.\n\n"
            f"{profile(results, sums)}\n\n{NOTES}\n")
    print(text)
    if a.out:
        Path(a.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
