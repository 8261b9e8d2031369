"""CPU solve benchmark (issue 4): the paper's Jacobi against our Chebyshev, and the frame time.

    .venv/bin/python bench/solve.py [--qualities preview final] [--tol 1e-3] [--out docs/bench_solve.md]

For the bunny (150 mm, marble, one sun light) at each quality:

* sweeps and seconds to a relative residual of ``--tol`` on every level, with
  the multi-resolution warm start, for the paper's scheme + Jacobi (eqs. 5-9)
  and for ours (finite volumes + Chebyshev); the ratio of finest-level sweeps;
* the CPU time of one full RGB solve warm-started from the previous frame
  with the sun moved by 5 degrees (the frame-to-frame case), with the light
  pass (shadow rays) timed separately.

All numbers come from one run on one machine; compare ratios, not absolute times.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh  # noqa: E402
from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions  # noqa: E402
from translucency_addon.scene.lights import Light  # noqa: E402
from translucency_addon.scene.materials import material_from_preset  # noqa: E402
from data import mesh_path  # noqa: E402
from translucency_addon.geometry.meshio import load_obj  # noqa: E402



def rotate_z(v, deg):
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return R @ v


def bench_quality(V, F, quality, tol, frames=5, paper_cap=200_000):
    bake = bake_mesh(V, F, BakeSettings(quality=quality, mm_per_unit=1000.0))
    marble = material_from_preset("marble")
    d0 = np.array([0.5, -1.0, -0.6])
    sun = [Light("sun", irradiance=1000.0, direction=d0)]
    row = {"quality": quality, "levels": [(lv.n_surface, lv.n_inner) for lv in bake.levels]}
    fast = DiffusionSolver(bake, marble, options=SolveOptions(solver="fast", tol=tol))
    q = fast.incident(sun)
    for name, solver in (("paper", "paper"), ("ours", "fast")):
        s = fast if solver == "fast" else DiffusionSolver(
            bake, marble, options=SolveOptions(solver="paper", tol=tol, max_iterations=paper_cap))
        t = time.perf_counter()
        r = s.solve(q=q)
        row[name] = {
            "sweeps": [ls.iterations for ls in r.level_solves],
            "seconds": time.perf_counter() - t,
            "residual": float(r.residual.max()),
            "diverged": any(ls.diverged for ls in r.level_solves),
        }
    # frame-to-frame: warm start, light moved by 5 degrees each frame
    prev = fast.solve(q=q)
    light_s, solve_s, sweeps = [], [], []
    d = d0
    for _ in range(frames):
        d = rotate_z(d, 5.0)
        lights = [Light("sun", irradiance=1000.0, direction=d)]
        t0 = time.perf_counter()
        qf = fast.incident(lights, levels=[len(bake.levels) - 1])
        t1 = time.perf_counter()
        r = fast.solve(q=qf, warm_start=prev)
        t2 = time.perf_counter()
        fast.vertex_radiance(r)
        prev = r
        light_s.append(t1 - t0)
        solve_s.append(t2 - t1)
        sweeps.append(r.level_solves[-1].iterations)
    row["frame"] = {"light_ms": 1e3 * float(np.median(light_s)), "solve_ms": 1e3 * float(np.median(solve_s)),
                    "sweeps": float(np.median(sweeps))}
    return row


def table(rows, tol) -> str:
    lines = [
        "| quality | N_s/N_i finest | paper sweeps per level | paper s | ours sweeps per level | ours s | "
        "finest sweep ratio | frame: sweeps | frame: solve ms | frame: light pass ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p, o, f = r["paper"], r["ours"], r["frame"]
        ratio = p["sweeps"][-1] / max(o["sweeps"][-1], 1)
        pnote = " (diverged)" if p["diverged"] else ("" if p["residual"] <= tol else f" (stopped at {p['residual']:.1e})")
        s, i = r["levels"][-1]
        lines.append(
            f"| {r['quality']} | {s:,}/{i:,} | {p['sweeps']}{pnote} | {p['seconds']:.1f} | {o['sweeps']} | "
            f"{o['seconds']:.2f} | {ratio:.0f}x | {f['sweeps']:.0f} | {f['solve_ms']:.0f} | {f['light_ms']:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--qualities", nargs="+", default=["preview", "final"])
    ap.add_argument("--tol", type=float, default=1e-3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    V, F = load_obj(mesh_path("stanford-bunny"))
    rows = []
    for qual in a.qualities:
        rows.append(bench_quality(V, F, qual, a.tol))
        print(f"{qual}: done", flush=True)
    t = table(rows, a.tol)
    print(t)
    for r in rows:
        if r["quality"] == "preview":
            ms = r["frame"]["solve_ms"]
            print(f"target: preview warm-started RGB solve {ms:.0f} ms <= 150 ms: {'met' if ms <= 150 else 'MISSED'}")
        ratio = r["paper"]["sweeps"][-1] / max(r["ours"]["sweeps"][-1], 1)
        print(f"target: {r['quality']} >= 10x fewer sweeps than the paper: {ratio:.0f}x {'met' if ratio >= 10 else 'MISSED'}")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        p = Path(a.out)
        rest = ""  # the sections bench/frame.py appends (a frame with Self-Occlusion, how cost grows) stay
        if p.exists() and "\n## " in p.read_text():
            rest = "\n## " + p.read_text().split("\n## ", 1)[1]
        p.write_text(f"# Solve benchmark (bunny, marble, one sun; tol {a.tol:g})\n\n" + t + "\n" + rest)


if __name__ == "__main__":
    main()
