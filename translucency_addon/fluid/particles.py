"""Particle input of a fluid frame: checks, clean-up and the radius (Kang & Kim 2013 sec. 4.1, 5.1).

Everything a particle source can hand us goes through :func:`prepare_particles`
first.  What it does with bad input (each case has a test):

* **no particles**: an empty set -- zero radiance is the right answer (an
  emitter before its first frame);
* **NaN or Inf positions**: those particles are left out, with a warning
  naming how many; if none is finite, :class:`ParticleError`;
* **coincident particles** (closer than 1e-9 radii): they share one cell
  (a bisecting plane needs two distinct points), with a warning;
* **radius** zero, negative or not finite: :class:`ParticleError`; **larger
  than the fluid** (than the particles' extent) or more than
  ``MAX_RADIUS_SPACING`` times the particle spacing: :class:`RadiusError`
  (a :class:`ParticleError`) naming the spacing, the radius to use (what
  :func:`suggest_radius` chooses), which callers say in their own units;
* **all particles in a plane** (or on a line): :class:`ParticleError` -- a
  single layer of balls has no inside for diffusion;
* **more particles than memory allows**: :class:`ParticleError` with the
  estimate and the budget, before anything large is allocated.

Isolated particles (no neighbour within 2R) and a single particle are not
errors: :mod:`.cellgraph` leaves such cells out with a warning (zero radiance).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ParticleError, RadiusError
from ..geometry.extent import extent as column_extent
from ..geometry.meshio import DEFAULT_MEMORY_BUDGET_BYTES

MAX_RADIUS_SPACING = 4.0  # radius / spacing beyond which cells would have hundreds of neighbours
BYTES_PER_PARTICLE = 8_000  # peak bytes per particle over a frame (pairs, faces, graph, system): 7.4 kB measured at 262k (bench_fluid.md)
DUPLICATE = 1e-9  # particles closer than this many radii share a cell
PLANAR = 1e-6  # thickness / extent below which the particles lie in a plane
SPACING_NEIGHBOURS = 12  # neighbours counted for the spacing (density) estimate


@dataclass
class ParticleSet:
    """The particles that get cells, and how they map back to the input."""

    points: np.ndarray  # (n, 3) float64, finite, distinct
    radius: float
    source: np.ndarray  # (n,) index of each kept particle in the input
    owner: np.ndarray  # (N_in,) kept particle each input particle maps to, -1 if left out
    ids: np.ndarray | None = None  # (n,) int64 particle ids (warm start), None if not given or not unique
    field_values: np.ndarray | None = None  # (n,) mixing field values, None for a homogeneous material
    spacing: float = 0.0  # particle_spacing() of the points (0 for fewer than 2)
    warnings: list = field(default_factory=list)
    tree: object = None  # the points' cKDTree (built for the checks; the cells reuse it)

    @property
    def n(self) -> int:
        return len(self.points)


def particle_spacing(points: np.ndarray, tree=None, samples: int = 4000) -> float:
    """The mean distance between neighbouring particles, ``(volume per particle)^(1/3)``.

    From the distance r_k to the k-th nearest particle (k = 12, fewer when
    there are fewer particles) the local density is ``k / (4/3 pi r_k^3)``;
    the spacing is the median of ``r_k (4 pi / (3 k))^(1/3)`` (0.996 on a
    cubic lattice of spacing 1, 1.001 jittered by 10 %; particles on the
    boundary, with half their neighbours missing, move the median little).  The median is taken over
    ``samples`` particles at most (drawn with a fixed seed).
    """
    P = np.asarray(points, dtype=np.float64)
    if len(P) < 2:
        return 0.0
    k = min(SPACING_NEIGHBOURS, len(P) - 1)
    if tree is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(P)
    sample = P if len(P) <= samples else P[np.random.default_rng(0).choice(len(P), samples, replace=False)]
    d, _ = tree.query(sample, k=k + 1)
    return float(np.median(d[:, k]) * (4.0 * np.pi / (3.0 * k)) ** (1.0 / 3.0))


def suggest_radius(points) -> float:
    """A particle radius that makes the fluid's inside solid: the particle spacing (:func:`particle_spacing`).

    On a cubic lattice the balls close every gap from ``sqrt(3)/2`` spacings
    on; at one spacing a lattice jittered by 10 % of its spacing has no
    interior voids left (``tests/test_fluid_cells.py``).
    """
    return particle_spacing(points)


def check_radius(radius) -> float:
    """The particle radius as a float, or :class:`ParticleError`: a finite number > 0 of object units."""
    from ..scene.materials import check_positive

    return check_positive(radius, "the particle radius (object units)", ParticleError)


def estimate_bytes(n: int) -> int:
    return int(BYTES_PER_PARTICLE * n)


def prepare_particles(points, radius, ids=None, field_values=None,
                      memory_budget: int = DEFAULT_MEMORY_BUDGET_BYTES) -> ParticleSet:
    """Check and clean a frame's particles (see the module docstring for every case)."""
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ParticleError(f"particle positions must be an (N, 3) array, got shape {P.shape}")
    R = check_radius(radius)
    n_in = len(P)
    need = estimate_bytes(n_in)
    if need > memory_budget:
        raise ParticleError(f"{n_in:,} particles need about {need / 2**30:.1f} GiB for their cells "
                            f"(budget {memory_budget / 2**30:.1f} GiB); use fewer particles")
    P = P.astype(np.float64, copy=False)
    warnings = []
    finite = np.isfinite(P).all(axis=1)
    if n_in and not finite.any():
        raise ParticleError(f"all {n_in:,} particles have NaN or Inf positions: the particle data is broken")
    if not finite.all():
        warnings.append(f"{int((~finite).sum()):,} of {n_in:,} particles have NaN or Inf positions and were "
                        "left out (zero radiance)")
    src = np.nonzero(finite)[0]
    owner = np.full(n_in, -1, dtype=np.int64)
    owner[src] = np.arange(len(src))
    Q = P[src]
    spacing, tree = 0.0, None
    if len(Q):
        from scipy.spatial import cKDTree

        # unbalanced (median of the extent, not of the points): built in 1.6 against 2.7 ms at 16k particles,
        # its queries here and by the cells, the graph and the occluder as fast (measured)
        tree = cKDTree(Q, balanced_tree=False)
        dup = tree.query_pairs(DUPLICATE * R, output_type="ndarray")
        if len(dup):
            keep_of = np.arange(len(Q))
            for _ in range(64):  # chains of coincident particles collapse onto their lowest index
                nxt = keep_of.copy()
                np.minimum.at(nxt, dup[:, 1], keep_of[dup[:, 0]])
                np.minimum.at(nxt, dup[:, 0], keep_of[dup[:, 1]])
                if np.array_equal(nxt, keep_of):
                    break
                keep_of = nxt
            uniq, new = np.unique(keep_of, return_inverse=True)
            warnings.append(f"{len(Q) - len(uniq):,} particles coincide with another (closer than "
                            f"{DUPLICATE:g} radii) and share its cell")
            owner[src] = new
            src = src[uniq]
            Q = Q[uniq]
            tree = cKDTree(Q, balanced_tree=False)
        # for the radius checks only: the median over 1,000 particles is within a few tenths of a per cent of
        # the spacing, and costs a quarter of 4,000's query (10 ms a frame at 16k particles)
        spacing = particle_spacing(Q, tree, samples=1000)
        _check_shape(Q, R, spacing)
    id_arr = _check_ids(ids, n_in, src, warnings)
    fv = None
    if field_values is not None:
        f = np.asarray(field_values, dtype=np.float64).reshape(-1)
        if len(f) != n_in:
            raise ParticleError(f"field values: {len(f):,} for {n_in:,} particles")
        fv = f[src]
    return ParticleSet(points=Q, radius=R, source=src, owner=owner, ids=id_arr, field_values=fv, spacing=spacing,
                       warnings=warnings, tree=tree)


def _check_shape(Q, R, spacing):
    """Radius against the fluid's extent and spacing; all particles in a plane."""
    if len(Q) < 2:
        return
    extent = float(column_extent(Q).max())
    if R >= extent:
        raise RadiusError("fluid", R, spacing, extent)
    if spacing > 0 and R > MAX_RADIUS_SPACING * spacing:
        raise RadiusError("spacing", R, spacing, extent)
    c = Q - Q.mean(axis=0)
    if len(Q) >= 3:
        # the singular values of c from its 3 x 3 scatter matrix (the svd of c itself cost ~2 ms a frame at
        # 16k); its smallest eigenvalue is exact to ~1e-16 of the largest, so the ratio resolves 1e-8
        lam = np.linalg.eigvalsh(c.T @ c)
        s = np.sqrt(np.maximum(lam[::-1], 0.0))
        thick = s[-1] / max(s[0], 1e-300)
        if thick < PLANAR:
            raise ParticleError(f"all {len(Q):,} particles lie in one plane (thickness/extent {thick:.1e}): a single "
                                f"layer of balls has no inside for the diffusion to fill; the fluid must be at "
                                f"least two particles thick")


def _check_ids(ids, n_in, src, warnings):
    if ids is None:
        return None
    a = np.asarray(ids).reshape(-1)
    if len(a) != n_in:
        raise ParticleError(f"particle ids: {len(a):,} for {n_in:,} particles")
    if not np.issubdtype(a.dtype, np.integer):
        raise ParticleError(f"particle ids must be integers, got {a.dtype}")
    a = a[src].astype(np.int64)
    if len(np.unique(a)) != len(a):
        warnings.append("particle ids repeat: the warm start matches particles by position instead")
        return None
    return a
