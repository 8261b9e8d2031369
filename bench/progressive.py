# SPDX-License-Identifier: GPL-3.0-or-later
"""Progressive viewport frames (issue 33, item 1): the first image after a light move, and how it refines.

    .venv/bin/python -m bench.progressive [--qualities preview final] [--budget-ms 33.3] [--out docs/bench_progressive.md]

The accuracy bench's headline scene (``bunny_marble_sky``: the 40 mm marble bunny under the sky,
Self-Occlusion on, tol 1e-4, bakes from ``bench/out/accuracy_bakes``), per quality: a converged frame,
then the sky turned by 5 degrees (``bench/accuracy_core.py``'s warm frame) or 90 degrees (a light dragged
across) solved two ways from it:

* *blocking*: ``frame.diffuse`` and the vertex radiance, as renders and the add-on without Progressive do;
* *progressive*: ``progressive.ProgressiveSolve`` over ``frame.diffuse_steps`` with the frame budget
  (default 1/30 s), as the add-on's viewport does: after each slice the solution so far and its vertex
  radiance (the image the overlay shows), until it converges.

Per slice: wall time since the move (the slices back to back, plus each image's vertex radiance, which the
viewport pays too), and the image's error against the blocking frame (relative RMS over the vertices).
The converged progressive frame equals the blocking one bit for bit (``tests/test_progressive.py``).
Two shared CPU cores, no GPU: compare within a row; absolute times only as a guide.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.bench_io import write_file  # noqa: E402
BAKES = ROOT / "bench" / "out" / "accuracy_bakes"
TARGET_MS = 40.0  # issue 33: first image after a light move, any quality


def run(quality: str, budget_s: float, degrees: float) -> dict:
    from bench import accuracy_scenes as scenes
    from bench.accuracy_core import Evaluator, environment_turned, view_dirs
    from translucency_addon import frame as frame_mod
    from translucency_addon.diffusion import solver as diffusion
    from translucency_addon.progressive import ProgressiveSolve

    sc = next(s for s in scenes.reference_scenes() if s.name == "bunny_marble_sky")
    bk, _ = Evaluator(bake_cache=BAKES, log=lambda *a: None).bake(sc, quality=quality)
    vd = view_dirs(sc)
    solver = diffusion.DiffusionSolver(bk, sc.material, None, diffusion.SolveOptions(solver="fast", tol=1e-4))
    passes = frame_mod.FramePasses(True, False, False, (True, True, True), (False, False, False))
    kw = {"tol": 1e-4, "shadows": True}
    start, _, _ = frame_mod.diffuse(solver, bk, (), sc.environment, passes, **kw)
    moved = environment_turned(sc, degrees)
    blocking = []
    for _ in range(2):  # the first run also sets up what both share (the sweep layout is cached per level)
        t0 = time.perf_counter()
        ref, _, _ = frame_mod.diffuse(solver, bk, (), moved, passes, warm_start=start, **kw)
        L_ref = solver.vertex_radiance(ref, vd)
        blocking.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    solver.incident((), moved)
    light_s = time.perf_counter() - t0
    job = ProgressiveSolve(frame_mod.diffuse_steps(solver, bk, (), moved, passes, warm_start=start, **kw), key=0)
    rows = []
    scale = float(np.sqrt(np.mean(L_ref ** 2)))
    t0 = time.perf_counter()
    while True:
        out, done = job.advance(budget_s)
        L = solver.vertex_radiance(out[0] if done else out, vd)
        now = time.perf_counter() - t0
        rows.append((now, float(np.sqrt(np.mean((L - L_ref) ** 2))) / scale))
        if done:
            break
    return {"quality": quality, "degrees": degrees, "nodes": int(bk.finest.n_nodes), "blocking_s": min(blocking), "light_s": light_s,
            "rows": rows, "sweeps": int(out[0].level_solves[-1].iterations), "same": bool(np.array_equal(L, L_ref))}


def _first_below(rows, err):
    return next((t for t, e in rows if e <= err), float("nan"))


def table(results: list, budget_ms: float) -> str:
    lines = ["| quality | sky turned | finest nodes | blocking warm frame ms | light pass ms | first image ms (error) | "
             "error < 5 % at ms | error < 1 % at ms | converged at ms (slices) | converged = blocking |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        t1, e1 = r["rows"][0]
        lines.append(f"| {r['quality']} | {r['degrees']:g} deg | {r['nodes']:,} | {1e3 * r['blocking_s']:,.0f} | {1e3 * r['light_s']:,.0f} | "
                     f"{1e3 * t1:,.0f} ({e1:.1%}) | {1e3 * _first_below(r['rows'], 0.05):,.0f} | "
                     f"{1e3 * _first_below(r['rows'], 0.01):,.0f} | {1e3 * r['rows'][-1][0]:,.0f} "
                     f"({len(r['rows'])}) | {'yes' if r['same'] else 'no'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--qualities", nargs="+", default=["preview", "final"])
    ap.add_argument("--budget-ms", type=float, default=1000.0 / 30.0)
    ap.add_argument("--degrees", type=float, nargs="+", default=[5.0, 90.0], help="how far the sky turns")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    results = [run(q, a.budget_ms / 1000.0, d) for q in a.qualities for d in a.degrees]
    worst = max(1e3 * r["rows"][0][0] for r in results)
    text = (f"# Progressive viewport frames (issue 33, item 1)\n\nWritten by `bench/progressive.py` in "
            f"{time.perf_counter() - t0:.0f} s: `.venv/bin/python -m bench.progressive --out "
            f"docs/bench_progressive.md`. Frame budget {a.budget_ms:.1f} ms. **2 shared CPU cores, no GPU**: "
            "compare within a row.\n\nThe 40 mm marble bunny under the sky (Self-Occlusion on), the sky turned "
            "by 5 or 90 degrees after a converged frame; the blocking frame against the add-on's progressive one "
            "(the solution so far after each slice, its error the relative RMS of the vertex radiance against "
            f"the blocking frame).\n\n{table(results, a.budget_ms)}\n\n**Target** (issue 33): first image after a "
            f"light move <= {TARGET_MS:.0f} ms at any quality: {worst:,.0f} ms at worst, "
            f"{'met' if worst <= TARGET_MS else '**missed**'}. The first slice pays for the light pass (shadow "
            "rays, sky visibility, the split: the light pass column), which is not sliced, and ends at the "
            "solve's start: the last frame's solution with this frame's light at the surface (its error is "
            "the first image's: the last frame's share of the change). The iteration's own set-up (at Final the "
            "true residual of the first block's CG in fp64: its product and two reorderings of 400 k x 3 "
            "values, and the coarse space's set-up) comes in the second slice. Later slices run at "
            "least one sweep and at least 4x what showing the last image cost (the iterate gathered from the "
            "sweeps' layout and carried to the vertices, ~20 ms at Final), up to 0.25 s: the viewport redraws "
            "4-30 times a second while the image refines, and the progressive frame converges in 1.1-1.4x "
            "the blocking frame's time (timings on these shared cores vary by ~20 % from run to run).\n")
    return write_file(text, a.out)


if __name__ == "__main__":
    sys.exit(main())
