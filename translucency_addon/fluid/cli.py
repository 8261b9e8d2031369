"""``python -m translucency_addon fluid``: particle frames in, per-cell phi and radiance out.

``POINTS.npy`` is (N, 3) -- one frame -- or (F, N, 3): F frames solved in
turn, each warm-started from the one before (particle i of one frame is
particle i of the next: the row index is the particle id).  NaN rows are
particles that do not exist in that frame.  Files are read with
``allow_pickle=False``.  Outputs:

* ``-o PHI.npz``: ``phi`` (.., N, 3), ``volume`` (.., N), ``surface`` (.., N)
  bool and ``radiance`` (.., N, 3) -- the outgoing radiance along the normal
  at surface cells -- per cell, with a leading frame axis for (F, N, 3) input;
* ``--surface-out L.npy``: per-vertex RGB radiance on ``--surface MESH.obj``;
* ``--stats STATS.json``: per frame the cell count, build / light / solve /
  output seconds, sweeps, residual, warm start and warnings.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from ..errors import ParticleError, TranslucencyError


def load_frames(path: str) -> tuple[np.ndarray, bool]:
    """(F, N, 3) float64 positions and whether the file held a single (N, 3) frame."""
    try:
        P = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ParticleError(f"cannot read particle positions from {path}: {exc}") from None
    single = P.ndim == 2
    if single:
        P = P[None]
    if P.ndim != 3 or P.shape[2] != 3 or not np.issubdtype(P.dtype, np.number):
        raise ParticleError(f"{path}: expected an (N, 3) or (F, N, 3) numeric array, got {P.dtype} {P.shape}")
    return P.astype(np.float64), single


def run_fluid(a, material, lights, environment, field_spec=None) -> int:
    """Solve every frame of ``a.points`` (see the module docstring); returns the exit status.

    ``field_spec(points) -> FieldSpec``: the mixing field of a two-media material.
    """
    from ..fields import evaluate_field
    from ..meshio import load_obj
    from .solver import FluidOptions, FluidSolver

    frames, single = load_frames(a.points)
    if a.surface_out and not a.surface:
        raise TranslucencyError("--surface-out needs --surface MESH.obj")
    surface = load_obj(a.surface) if a.surface else None
    solver = FluidSolver(material, a.radius, a.mm_per_unit, FluidOptions(tol=a.tol))
    spec = None
    if material.heterogeneous:
        spec = field_spec(frames[np.isfinite(frames).all(axis=2)])
    ids = np.arange(frames.shape[1])
    outs, vertex, stats = [], [], []
    state = None
    t0 = time.perf_counter()
    for k, pts in enumerate(frames):
        fv = None
        if spec is not None:
            fv = np.zeros(len(pts))
            ok = np.isfinite(pts).all(axis=1)
            fv[ok] = evaluate_field(spec, pts[ok])
        res = solver.solve(pts, ids=ids, field_values=fv, lights=lights, environment=environment,
                           surface=surface, shadows=not a.no_shadows, warm_start=state)
        state = res.state if res.state is not None else state
        outs.append(res)
        if surface is not None:
            vertex.append(res.vertex_radiance)
        st = {"frame": k, **res.stats}
        stats.append(st)
        s = st["seconds"]
        print(f"frame {k}: {st.get('cells', 0):,} cells ({st.get('surface_nodes', 0):,} on the surface), "
              f"{st['sweeps']} sweeps{' (warm)' if st['warm_start'] else ''}, cells {s.get('cells', 0) * 1e3:.0f} ms, "
              f"solve {s.get('solve', 0) * 1e3:.0f} ms, total {s['total'] * 1e3:.0f} ms", file=sys.stderr)
        for w in res.warnings:
            print(f"  warning: {w}", file=sys.stderr)

    def stack(name):
        arr = np.stack([getattr(r, name) for r in outs])
        return arr[0] if single else arr

    np.savez(a.output, phi=stack("phi").astype(np.float32), volume=stack("volume").astype(np.float32),
             surface=stack("surface"), radiance=stack("cell_radiance").astype(np.float32))
    if a.surface_out:
        L = np.stack(vertex)
        np.save(a.surface_out, (L[0] if single else L).astype(np.float32))
    if a.stats:
        with open(a.stats, "w", encoding="utf-8") as fh:
            json.dump({"frames": stats, "seconds_total": time.perf_counter() - t0}, fh, indent=2)
    print(f"solved {len(frames)} frame(s) of {frames.shape[1]:,} particles in {time.perf_counter() - t0:.2f} s; "
          f"wrote {a.output}" + (f" and {a.surface_out}" if a.surface_out else ""))
    return 0
