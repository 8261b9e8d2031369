"""Would smoothed aggregation cut the converged frame's sweeps? (issue 33, item 2: "find out why PyAMG
took 34-38 s per channel before ruling it out").

    python -m bench.amg_probe [--qualities preview final] [--tol 1e-4] [--out docs/bench_solve.md]

Needs PyAMG (``pip install pyamg``; a bench-only dependency, not bundled in the extension).  For the
marble bunny (150 mm) under one sun, at each quality: the finest level's system of one channel
(``LevelSystem``, the conservative scheme: ``diag x - off x = b``) as a scipy CSR, then

* its facts: size, non-zeros per row, symmetry (the FV scheme's links are symmetric), diagonal dominance;
* PyAMG's smoothed aggregation with the symmetric strength measure, as ``pyamg.smoothed_aggregation_solver``
  builds it by default and with the settings a graph Laplacian of this kind wants, each: set-up seconds,
  levels, operator and grid complexity, then conjugate gradients preconditioned by one V-cycle to the
  frame's tolerance, cold (x0 = 0) and warm (the solution of the sun 5 degrees away), iterations and
  seconds;
* our solve of the same level (Chebyshev with Jacobi, fp32 sweeps), cold from the coarse levels' eq. 10
  start as a frame runs it, and warm, sweeps and seconds, same process, same load.

The relative residual is ``|b - A x| / |b|`` for both.  Ratios count, not seconds (two shared cores).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

HEADING = "## Smoothed aggregation on the finest level (issue 33, item 2)\n"


def csr_of(system, c: int) -> sp.csr_matrix:
    """The channel-``c`` matrix of ``diag x - sum_j off_ij x_j`` as CSR (object units as assembled)."""
    nbr, off = system.nbr, system.off[:, :, c]
    n, k = nbr.shape
    rows = np.repeat(np.arange(n), k)
    cols = nbr.ravel()
    keep = cols >= 0
    A = sp.csr_matrix((-off.ravel()[keep], (rows[keep], cols[keep])), shape=(n, n))
    return (A + sp.diags(system.diag[:, c])).tocsr()


def pcg_amg(ml, b, x0, tol):
    res = []
    t = time.perf_counter()
    x = ml.solve(b, x0=x0, tol=tol, accel="cg", residuals=res, maxiter=500)
    sec = time.perf_counter() - t
    rel = float(np.linalg.norm(b - ml.levels[0].A @ x) / np.linalg.norm(b))
    return {"iterations": len(res) - 1, "seconds": sec, "residual": rel}, x


def run(quality: str, tol: float) -> dict:
    import pyamg

    from data import mesh_path
    from translucency_addon.diffusion.solver import DiffusionSolver, SolveOptions
    from translucency_addon.geometry.meshio import load_obj
    from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh
    from translucency_addon.scene.lights import Light
    from translucency_addon.scene.materials import material_from_preset

    V, F = load_obj(mesh_path("stanford-bunny"))
    bake = bake_mesh(V, F, BakeSettings(quality=quality, mm_per_unit=1000.0))
    solver = DiffusionSolver(bake, material_from_preset("marble"), options=SolveOptions(solver="fast", tol=tol))
    d0 = np.array([0.5, -1.0, -0.6])
    rot = np.deg2rad(5.0)
    d1 = np.array([[np.cos(rot), -np.sin(rot), 0], [np.sin(rot), np.cos(rot), 0], [0, 0, 1]]) @ d0
    sun0, sun1 = ([Light("sun", irradiance=1000.0, direction=d)] for d in (d0, d1))
    # ours: a cold frame (coarse levels, then the finest warm-started by eq. 10), then a warm one
    r0 = solver.solve(sun0)
    t = time.perf_counter()
    r1 = solver.solve(sun1, warm_start=r0)
    warm_sec = time.perf_counter() - t
    fin = len(bake.levels) - 1
    system = solver.systems[fin]
    ours = {"cold_sweeps": r0.level_solves[-1].iterations, "cold_seconds": r0.level_solves[-1].seconds,
            "warm_sweeps": r1.level_solves[-1].iterations, "warm_frame_seconds": warm_sec,
            "warm_seconds": r1.level_solves[-1].seconds}
    c = 0  # red: the longest diffusion length, the slowest channel
    A = csr_of(system, c)
    b0 = system.rhs(r0.q[fin])[:, c]
    b1 = system.rhs(r1.q[fin])[:, c]
    x_ours0 = r0.phi[fin][:, c]
    facts = {"n": A.shape[0], "nnz_per_row": A.nnz / A.shape[0],
             "asymmetry": float(abs(A - A.T).max() / abs(A).max()),
             "min_dominance": float(np.min(A.diagonal() - (abs(A).sum(axis=1).A1 - abs(A.diagonal())))
                                    / np.max(A.diagonal())),
             "ours_residual": float(np.linalg.norm(b0 - A @ x_ours0) / np.linalg.norm(b0))}
    variants = {
        "PyAMG's defaults": {},
        "defaults, one weighted-Jacobi pre- and post-smoothing step (vectorised, as our sweeps)": dict(
            presmoother=("jacobi", {"omega": 2.0 / 3.0}), postsmoother=("jacobi", {"omega": 2.0 / 3.0})),
        "strength 0.25, Jacobi prolongation smoother, max_coarse 500": dict(
            strength=("symmetric", {"theta": 0.25}), smooth=("jacobi", {"omega": 4.0 / 3.0}), max_coarse=500),
    }
    rows = []
    for name, kw in variants.items():
        t = time.perf_counter()
        ml = pyamg.smoothed_aggregation_solver(A, symmetry="symmetric", **kw)
        setup = time.perf_counter() - t
        cold, x0 = pcg_amg(ml, b0, np.zeros_like(b0), tol)
        warm, _ = pcg_amg(ml, b1, x0, tol)
        rows.append({"variant": name, "setup": setup, "levels": len(ml.levels),
                     "operator_complexity": ml.operator_complexity(), "grid_complexity": ml.grid_complexity(),
                     "cold": cold, "warm": warm})
    return {"quality": quality, "tol": tol, "facts": facts, "ours": ours, "amg": rows,
            "pyamg": pyamg.__version__}


def markdown(results: list, command: str) -> str:
    r0 = results[0]
    lines = [HEADING, f"From one run of `{command}` (PyAMG {r0['pyamg']}; two shared CPU cores, no GPU).  The "
             "marble bunny, one sun; the finest level's red channel (the slowest: the longest diffusion length). "
             f"Tolerance {r0['tol']:g} (relative residual).  *warm*: the sun 5 degrees away, started from the "
             "last solution, as a light move is.  Ours solves the three channels at once; PyAMG one.\n",
             "| quality | solve of the finest level | set-up (s) | levels | operator / grid complexity | cold: "
             "iterations, s | warm: iterations, s |", "|---|---|---|---|---|---|---|"]
    reads = []
    for r in results:
        f, o = r["facts"], r["ours"]
        q = f"{r['quality'].title()}: {f['n']:,} nodes, {f['nnz_per_row']:.1f} non-zeros per row"
        lines.append(f"| {q} | ours: Chebyshev + Jacobi, fp32 sweeps, **three channels** | spectral bounds, per "
                     f"material | QuadGraph levels | | {o['cold_sweeps']} sweeps, {o['cold_seconds']:.2f} | "
                     f"{o['warm_sweeps']} sweeps, {o['warm_seconds']:.2f} |")
        for a in r["amg"]:
            lines.append(f"| | PyAMG SA + CG, **one channel**: {a['variant']} | {a['setup']:.2f} | {a['levels']} | "
                         f"{a['operator_complexity']:.2f} / {a['grid_complexity']:.2f} | {a['cold']['iterations']}, "
                         f"{a['cold']['seconds']:.2f} | {a['warm']['iterations']}, {a['warm']['seconds']:.2f} |")
        best = min(r["amg"], key=lambda a: a["warm"]["seconds"])
        reads.append(f"at {r['quality'].title()} ({f['n']:,} nodes; symmetric to {f['asymmetry']:.0e}) three "
                     f"channels of the best AMG would take {3 * best['warm']['seconds']:.2f} s per light move "
                     f"against our {o['warm_seconds']:.2f} s, plus {3 * best['setup']:.1f} s of set-up per material "
                     f"({best['warm']['iterations']} iterations of {1e3 * best['warm']['seconds'] / max(best['warm']['iterations'], 1):.0f} ms "
                     f"for one channel, against {o['warm_sweeps']} sweeps of "
                     f"{1e3 * o['warm_seconds'] / max(o['warm_sweeps'], 1):.1f} ms for three)")
    lines += ["", "Read: " + "; ".join(reads) + ".  Smoothed aggregation does what it promises -- a handful of "
              "iterations whatever the size -- and its set-up is about a second per channel here, not the "
              "34-38 s of the last try (not reproduced: that try's settings are not in the repository).  But "
              "on these levels one V-cycle costs as much as dozens of our fused fp32 sweeps, so at this size it "
              "does not win on the CPU; the frame keeps Chebyshev at every quality.  Chebyshev's sweeps grow "
              "with the level's diffusion length in node spacings (the scaling table below), AMG's iterations "
              "do not, so the crossing lies at a finer level than Final's."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--qualities", nargs="+", default=["preview", "final"])
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    try:
        import pyamg  # noqa: F401
    except ImportError:
        print("bench.amg_probe needs PyAMG: pip install pyamg (a bench-only dependency)", file=sys.stderr)
        return 2
    results = [run(q, a.tol) for q in a.qualities]
    command = "python -m bench.amg_probe" + (f" --out {a.out}" if a.out else "")
    text = markdown(results, command)
    print(text)
    if a.out:
        from bench.accuracy_text import replace_section

        out = Path(a.out)
        out.write_text(replace_section(out.read_text() if out.exists() else "", HEADING, text[len(HEADING):]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
