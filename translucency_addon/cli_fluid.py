"""``python -m translucency_addon fluid``: particle frames in, per-cell phi and radiance out.

``POINTS.npy`` is (N, 3) -- one frame -- or (F, N, 3): F frames solved in
turn, each warm-started from the one before (particle i of one frame is
particle i of the next: the row index is the particle id).  NaN rows are
particles that do not exist in that frame; a frame whose every row is NaN
has no particle (radiance 0, with a warning).  A file with no particle, no
finite position in any frame, or a single particle is refused (exit 2):
there is nothing diffusion can render.  Files are read with
``allow_pickle=False``, and a file that is not a ``.npy`` is refused by name.
Outputs (written all or nothing at the end, with the umask's permissions):

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
import tokenize

import numpy as np

from .errors import ParticleError, RadiusError, TranslucencyError


NPY_MAGIC = b"\x93NUMPY"  # the first bytes of every .npy file (numpy.lib.format)
WHAT = "an (N, 3) or (F, N, 3) array of particle positions in object units, written by numpy.save"


def load_frames(path: str) -> tuple[np.ndarray, bool]:
    """(F, N, 3) float64 positions and whether the file held a single (N, 3) frame.

    Refused with one line naming the file and what it should hold: a file that
    is not a ``.npy`` (text, ``.npz``, a pickle: never unpickled), a non-numeric
    array, any other shape (the file's own shape is reported)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(NPY_MAGIC))
    except OSError as exc:
        raise ParticleError(f"cannot read the particle file {path}: {exc.strerror or exc}") from None
    if head != NPY_MAGIC:
        raise ParticleError(f"{path} is not a NumPy .npy file; it should hold {WHAT}")
    try:
        P = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, SyntaxError, tokenize.TokenError) as exc:
        # a damaged header reaches numpy's header parser: it raises what the tokenizer raises
        raise ParticleError(f"{path} is not a readable .npy array ({exc}); it should hold {WHAT}") from None
    shape = P.shape
    if P.ndim not in (2, 3) or P.shape[-1] != 3 or not np.issubdtype(P.dtype, np.number) \
            or np.issubdtype(P.dtype, np.complexfloating):
        raise ParticleError(f"{path} holds a {P.dtype} array of shape {shape}; it should hold {WHAT}")
    single = P.ndim == 2
    return (P[None] if single else P).astype(np.float64), single


def check_frames(path: str, frames: np.ndarray, single: bool, radius: float, mm_per_unit: float) -> np.ndarray:
    """The finite particles per frame, or :class:`ParticleError` when no frame has anything to render:
    no particles, no finite position in any frame, or a single particle (one ball with no neighbour, to
    which cell diffusion gives no light)."""
    n_frames, n = frames.shape[:2]
    shape = frames.shape[1:] if single else frames.shape
    if n_frames == 0 or n == 0:
        raise ParticleError(f"{path} holds no particles (shape {shape}): there is nothing to render")
    count = np.isfinite(frames).all(axis=2).sum(axis=1)
    if count.max() == 0:
        every = "" if single else f" in every one of its {n_frames:,} frames"
        raise ParticleError(f"{path}: all {n:,} particles have NaN or Inf positions{every} (NaN rows are absent "
                            "particles): there is nothing to render")
    if count.max() == 1:
        which = "a single particle" if n == 1 else f"at most one particle with a finite position per frame (of {n:,})"
        raise ParticleError(f"{path} holds {which}: one ball of radius {radius:g} units ({radius * mm_per_unit:.4g} "
                            f"mm) has no neighbour, and cell diffusion gives it no light; render a sphere mesh "
                            f"of that radius with 'bake' and 'solve', or give two or more particles closer than "
                            f"2 x --radius ({2 * radius:g} units)")
    return count


def run_fluid(a, material, lights, environment, field_spec=None) -> int:
    """Solve every frame of ``a.points`` (see the module docstring); returns the exit status.

    ``field_spec(points) -> FieldSpec``: the mixing field of a two-media material.  The caller has checked
    the arguments and that the outputs' folders are writable; every output is written at the end, all or
    nothing (:func:`~..cache.write_files`).
    """
    from .cache import write_files
    from .scene.fields import evaluate_field
    from .geometry.meshio import load_obj
    from .fluid.solver import FluidOptions, FluidSolver

    if a.surface_out and not a.surface:
        raise TranslucencyError("--surface-out needs --surface MESH.obj")
    frames, single = load_frames(a.points)
    count = check_frames(a.points, frames, single, a.radius, a.mm_per_unit)
    surface = load_obj(a.surface) if a.surface else None
    solver = FluidSolver(material, a.radius, a.mm_per_unit, FluidOptions(tol=a.tol))
    spec = None
    if material.heterogeneous:
        spec = field_spec(frames[np.isfinite(frames).all(axis=2)])
    ids = np.arange(frames.shape[1])
    outs, vertex, points_out, stats = [], [], [], []
    state = None
    from .frame import fluid_radiance, view_directions
    from .planner import plan_fluid

    view = ("PERSP", tuple(a.camera)) if getattr(a, "camera", None) is not None else None
    t0 = time.perf_counter()
    for k, pts in enumerate(frames):
        fv = None
        if spec is not None:
            fv = np.zeros(len(pts))
            ok = np.isfinite(pts).all(axis=1)
            fv[ok] = evaluate_field(spec, pts[ok])
        if count[k] == 0:  # no particle exists in this frame (an emitter before its first particle)
            res = _absent_frame(len(pts), None if surface is None else len(surface[0]))
        else:
            try:
                at = surface[0] if surface is not None else pts
                res = solver.solve(pts, ids=ids, field_values=fv, lights=lights, environment=environment,
                                   surface=surface, shadows=not a.no_shadows, warm_start=state,
                                   view_dirs=view_directions(view, at) if view is not None else None)
            except RadiusError as exc:
                raise ParticleError(f"{a.points}, frame {k}: " + exc.describe(
                    lambda x: f"{x:.4g} units", "use --radius {value} (the particle spacing)")) from None
            except ParticleError as exc:
                raise ParticleError(f"{a.points}, frame {k}: {exc}") from None
        state = res.state if res.state is not None else state
        outs.append(res)
        # what the add-on writes, through the same engine function: the planner's channels (plan_fluid)
        plan = None
        if count[k]:
            ok = np.isfinite(pts).all(axis=1)
            plan = plan_fluid(pts[ok], a.radius, a.mm_per_unit, material, list(lights), environment,
                              field_values=None if fv is None else fv[ok])
        n_out = len(surface[0]) if surface is not None else len(pts)
        written = fluid_radiance(res if plan is not None else None, plan, surface is None, n_out)
        (vertex if surface is not None else points_out).append(written)
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

    arrays = dict(phi=stack("phi").astype(np.float32), volume=stack("volume").astype(np.float32),
                  surface=stack("surface"), radiance=stack("cell_radiance").astype(np.float32))
    if surface is None:  # the radiance the add-on writes onto a point cloud that is its own source
        Lp = np.stack(points_out)
        arrays["point_radiance"] = (Lp[0] if single else Lp).astype(np.float32)
    writers = {a.output: lambda fh: np.savez(fh, **arrays)}
    if a.surface_out:
        L = np.stack(vertex)
        L = (L[0] if single else L).astype(np.float32)
        writers[a.surface_out] = lambda fh: np.save(fh, L)
    if a.stats:
        text = json.dumps({"frames": stats, "seconds_total": time.perf_counter() - t0}, indent=2)
        writers[a.stats] = lambda fh: fh.write(text.encode("utf-8"))
    write_files(writers)
    print(f"solved {len(frames)} frame(s) of {frames.shape[1]:,} particles in {time.perf_counter() - t0:.2f} s; "
          f"wrote {a.output}" + (f" and {a.surface_out}" if a.surface_out else ""))
    return 0


def _absent_frame(n: int, n_vertices: int | None):
    """The result of a frame in which none of the ``n`` particles exists (every row NaN): radiance 0."""
    from .fluid.solver import FluidResult

    z = np.zeros((n, 3))
    warning = f"none of the {n:,} particles exists in this frame (every row is NaN): radiance 0"
    stats = {"particles": n, "cells": 0, "surface_nodes": 0, "sweeps": 0, "warm_start": False,
             "seconds": {"total": 0.0}, "warnings": [warning]}
    return FluidResult(phi=z, volume=np.zeros(n), surface=np.zeros(n, dtype=bool), cell_radiance=z.copy(),
                       vertex_radiance=None if n_vertices is None else np.zeros((n_vertices, 3)),
                       point_radiance=None, state=None, stats=stats, warnings=[warning])
