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


def _one(args, queue):
    import resource

    from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
    from data import mesh_path
    from translucency_addon.geometry.meshio import load_obj

    name, quality = args
    V, F = load_obj(mesh_path(name))
    b = bake_mesh(V, F, BakeSettings(quality=quality, mm_per_unit=MM_PER_UNIT.get(name, 1.0)))
    st = b.stats
    queue.put({
        "mesh": name, "quality": quality, "triangles": int(len(F)),
        "resampled": st["resampled_triangles"], "levels": [(lv.n_surface, lv.n_inner) for lv in b.levels],
        "tets_finest": b.finest.n_inner, "timings": st["timings"], "seconds": st["seconds"],
        "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "graph_mib": b.graph_bytes() / 2**20,
        "quality_median": b.finest.stats["tet_quality_median"], "quality_min": b.finest.stats["tet_quality_min"],
    })


def run(name, quality):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_one, args=((name, quality), q))
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", nargs="+", default=["spot", "fandisk", "rocker-arm", "stanford-bunny"])
    ap.add_argument("--qualities", nargs="+", default=["draft", "preview", "final"])
    ap.add_argument("--out", default=None, help="also write the table (markdown) here")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
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
        Path(a.out).write_text("# Bake benchmark\n\n`" + " ".join(["bench/bake.py"] + (argv or sys.argv[1:])) + "`\n\n" + t + "\n")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
