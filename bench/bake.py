"""Bake benchmark (issue 3): per mesh and quality, sizes, seconds per stage, peak memory.

    .venv/bin/python bench/bake.py [--meshes spot fandisk rocker-arm stanford-bunny]
                                   [--qualities draft preview final] [--out docs/bench_bake.md]

Each bake runs in a fresh subprocess so its peak resident memory (ru_maxrss)
is its own.  Targets on the 2-core machine: the bunny bakes in <= 30 s at
Preview and <= 120 s at Final, and its finest Final level has >= 20k surface
and >= 50k inner nodes.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# Object units to millimetres so each mesh is a few cm to 15 cm across.
MM_PER_UNIT = {"spot": 50.0, "fandisk": 20.0, "rocker-arm": 1.0, "stanford-bunny": 1000.0}


SKY_HEADING = "## Self-Occlusion at Final: the compiled ray walk against the numpy walk (issue 33)\n"
SKY_DIRECTIONS = 64


def _one(args, queue):
    import os
    import resource

    name, quality, sky, numpy_rays = (tuple(args) + (0, False))[:4]
    if numpy_rays:
        os.environ["TRANSLUCENCY_NUMPY_RAYS"] = "1"
    from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
    from data import mesh_path
    from translucency_addon.geometry.meshio import load_obj

    V, F = load_obj(mesh_path(name))
    b = bake_mesh(V, F, BakeSettings(quality=quality, mm_per_unit=MM_PER_UNIT.get(name, 1.0), sky_directions=sky))
    st = b.stats
    queue.put({
        "mesh": name, "quality": quality, "triangles": int(len(F)),
        "resampled": st["resampled_triangles"], "levels": [(lv.n_surface, lv.n_inner) for lv in b.levels],
        "tets_finest": b.finest.n_inner, "timings": st["timings"], "seconds": st["seconds"],
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "graph_mib": b.graph_bytes() / 2**20,
        "quality_median": b.finest.stats["tet_quality_median"], "quality_min": b.finest.stats["tet_quality_min"],
    })


def run(name, quality, sky: int = 0, numpy_rays: bool = False):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_one, args=((name, quality, sky, numpy_rays), q))
    p.start()
    out = q.get()
    p.join()
    return out


def table(rows) -> str:
    stages = ["validate", "resample", "tetrahedralize", "levels", "quadgraph", "transfer"]
    head = ("| mesh | quality | tris in | tris resampled | N_s / N_i per level (coarse to fine) | "
            + " | ".join(f"{s} s" for s in stages) + " | total s | peak MiB | graph MiB | tet quality median/min |")
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [head, sep]
    for r in rows:
        lv = ", ".join(f"{s:,}/{i:,}" for s, i in r["levels"])
        lines.append(
            f"| {r['mesh']} | {r['quality']} | {r['triangles']:,} | {', '.join(map(str, r['resampled']))} | {lv} | "
            + " | ".join(f"{r['timings'].get(s, 0):.2f}" for s in stages)
            + f" | {r['seconds']:.1f} | {r['peak_mib']:.0f} | {r['graph_mib']:.1f} | "
            f"{r['quality_median']:.2f}/{r['quality_min']:.1e} |")
    return "\n".join(lines)


def sky_compare(meshes, out) -> int:
    """Final bakes with Self-Occlusion (sky visibility, 64 directions), each mesh with the compiled ray walk
    and with the numpy walk (``TRANSLUCENCY_NUMPY_RAYS=1``), alternating, each bake its own process; the
    section of ``out``."""
    from bench.bench_io import write_section

    rows = []
    for m in meshes:
        fast, slow = run(m, "final", SKY_DIRECTIONS), run(m, "final", SKY_DIRECTIONS, numpy_rays=True)
        rows.append((m, fast, slow))
        print(m, fast["timings"], slow["timings"], flush=True)
    lines = [SKY_HEADING, f"`.venv/bin/python bench/bake.py --sky-compare --meshes {' '.join(meshes)} --out "
             f"{out or 'FILE'}`: Final, Self-Occlusion with {SKY_DIRECTIONS} directions (every surface node of "
             "every level casts a ray into each direction of its hemisphere, closest hit), the same bake with "
             "both ray walks, each in its own process (2 shared CPU cores: compare within a row). The "
             "compiled walk is `translucency_addon/geometry/compiled_raycast.py` (numba); the numpy walk is "
             "what a zip without numba (macOS x86-64) runs.", "",
             "| mesh | surface nodes, all levels | sky visibility s: compiled / numpy | speed-up | "
             "transfer s (the planner's thickness rays) | whole bake s: compiled / numpy |", "|---|---|---|---|---|---|"]
    for m, f, sl in rows:
        n_s = sum(s for s, _ in f["levels"])
        sky_f, sky_s = f["timings"].get("sky visibility", 0.0), sl["timings"].get("sky visibility", 0.0)
        lines.append(f"| {m} | {n_s:,} | {sky_f:.1f} / {sky_s:.1f} | {sky_s / max(sky_f, 1e-9):.0f}x | "
                     f"{f['timings'].get('transfer', 0.0):.2f} / {sl['timings'].get('transfer', 0.0):.2f} | "
                     f"{f['seconds']:.1f} / {sl['seconds']:.1f} |")
    return write_section("\n".join(lines) + "\n", SKY_HEADING, out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sky-compare", action="store_true",
                    help="only Final bakes with Self-Occlusion, compiled against numpy ray walk, as a section of --out")
    ap.add_argument("--meshes", nargs="+", default=["spot", "fandisk", "rocker-arm", "stanford-bunny"])
    ap.add_argument("--qualities", nargs="+", default=["draft", "preview", "final"])
    ap.add_argument("--out", default=None, help="also write the table (markdown) here")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.sky_compare:
        return sky_compare(a.meshes, a.out)
    rows = []
    for m in a.meshes:
        for qual in a.qualities:
            r = run(m, qual)
            rows.append(r)
            print(f"{m:15s} {qual:8s} {r['seconds']:6.1f} s  finest N_s={r['levels'][-1][0]:,} N_i={r['levels'][-1][1]:,}",
                  flush=True)
    t = table(rows)
    print()
    print(t)
    bunny = {r["quality"]: r for r in rows if r["mesh"] == "stanford-bunny"}
    if bunny:
        print()
        for qual, limit in (("preview", 30), ("final", 120)):
            if qual in bunny:
                r = bunny[qual]
                ok = r["seconds"] <= limit
                print(f"target: bunny {qual} bake {r['seconds']:.1f} s <= {limit} s: {'met' if ok else 'MISSED'}")
        if "final" in bunny:
            s, i = bunny["final"]["levels"][-1]
            print(f"target: bunny final finest N_s {s:,} >= 20,000 and N_i {i:,} >= 50,000: "
                  f"{'met' if s >= 20000 and i >= 50000 else 'MISSED'}")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        from bench.accuracy_text import section_span

        old = Path(a.out).read_text() if Path(a.out).exists() else ""
        span = section_span(old, SKY_HEADING) if SKY_HEADING in old else None
        kept = old[span[0]:span[1]] if span else ""  # the Self-Occlusion section (--sky-compare) stays
        Path(a.out).write_text("# Bake benchmark\n\n`" + " ".join(["bench/bake.py"] + (argv or sys.argv[1:])) + "`\n\n" + t
                               + "\n" + ("\n" + kept if kept else ""))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
