r"""Exact area and solid angle of a disk clipped by half-planes: one Voronoi-fluid face.

A face of a Voronoi-fluid cell (Kang & Kim 2013 sec. 4.1) lies on the
bisecting plane of two particles i and j at distance d.  Clipped by the two
particles' balls of radius R it is the disk of radius ``r = sqrt(R^2 - h^2)``,
``h = d/2``, around the midpoint; every other particle k whose bisecting plane
with i crosses that disk cuts it by a straight line.  In the face's own 2D
frame (origin at the midpoint) each such line is ``n . x + c <= 0`` (inside),
with ``|n| = 1`` and ``|c| < r``.

The region's boundary is made of one segment per line and of arcs of the
circle, so both integrals follow from Green's theorem as a fan from the
origin, exactly, without ordering the polygon's vertices:

* the **segment** of line t is ``x0 + tau d``, ``x0 = -c n``, ``d = rot90(n)``
  (inside on the left: counter-clockwise), for the ``tau`` in the disk
  (``|tau| <= sqrt(r^2 - c^2)``) that every other line allows -- a 1D interval
  intersection (:func:`segment_bounds`).  Its fan triangle (origin, X0, X1)
  has the signed area ``-c (tau1 - tau0) / 2`` and, seen from the particle at
  height h above the origin, the signed solid angle of Van Oosterom &
  Strackee (1983) (:func:`fan`);
* the **arcs** are the parts of the circle no line excludes.  Line t
  excludes the angles within ``alpha = arccos(-c/r)`` of its normal's angle;
  the union of these exclusions is measured by a sort-and-sweep
  (:func:`allowed_arc`).  An arc of angle Theta adds ``r^2 Theta / 2`` to the
  area and ``(1 - h/R) Theta`` to the solid angle (a sector of the disk seen
  from its axis; ``h^2 + r^2 = R^2``).

Degenerate input -- a regular lattice, where several lines coincide and
vertices fall exactly on the circle -- is handled by tie-breaks: of two
coincident lines with the same orientation only the first keeps its segment,
and of two exclusions ending at the same angle only the first opens an arc.

:mod:`.cells` calls :func:`segment_bounds` for only part of a face's lines
(each Voronoi edge once, in one of its three faces) and the other two
functions on the segments it then shares; :func:`clipped_disk` is the whole
computation for faces given by all their lines.

Written by hand because no library in the engine's dependencies clips disks
exactly (scipy's qhull ``Voronoi`` alone costs as much CPU as the whole cell
build, see ``cells.py``, and would still need the disk cut), and it runs
vectorised over all faces with the same number of lines at once.
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi
PARALLEL = 1e-10  # |sin| below which two lines count as parallel
COINCIDENT = 1e-10  # distance (in units of the disk radius) below which parallel lines coincide
SAME_ANGLE = 1e-12  # radians: exclusion ends closer than this are the same end


def clipped_disk(r: np.ndarray, h: np.ndarray, R: float, nx: np.ndarray, ny: np.ndarray, c: np.ndarray):
    """Area and solid angle (seen from height ``h`` on the axis) of disks clipped by half-planes.

    ``r, h``: (F,) disk radii and apex heights, ``h^2 + r^2 = R^2``; lines
    ``(nx, ny)`` (m, F) unit normals and ``c`` (m, F) offsets with ``|c| < r``:
    the region is ``{x: |x| <= r, nx x + ny y + c <= 0 for every line}``.
    The face axis is last so that every reduction over lines runs along the
    first axis, vectorised over faces (numpy's reductions over a short last
    axis cost 10-25x more).  Returns ``(area (F,), solid_angle (F,))``, >= 0.
    """
    r = np.asarray(r, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    if c.shape[0] == 0:  # an uncut disk
        return np.pi * r * r, TWO_PI * (1.0 - h / R)
    lo, hi, _ = segment_bounds(r, nx, ny, c)
    seg_area, seg_omega = fan(h, c, lo, hi)
    theta = allowed_arc(r, nx, ny, c)
    area = seg_area.sum(axis=0) + 0.5 * r * r * theta
    omega = seg_omega.sum(axis=0) + (1.0 - h / R) * theta
    return np.maximum(area, 0.0), np.maximum(omega, 0.0)


def segment_bounds(r, nx, ny, c, first: int = 0):
    """The segment ``[lo, hi]`` of lines ``first..m-1`` that all m lines of the face allow.

    Arrays (s, t, F): line s constrains the segment ``x0_t + tau d_t`` of
    line t (``x0 = -c n``, ``d = (-ny, nx)``) by ``val + tau den <= 0``.
    Returns ``lo, hi, live`` (m - first, F); ``lo = hi = 0`` where the segment
    is empty (``live`` False).  Of coincident lines with the same orientation
    the one earlier in the face's order keeps its segment.
    """
    m = c.shape[0]
    tx, ty, tc = nx[first:], ny[first:], c[first:]
    mt = tc.shape[0]
    w = np.sqrt(np.maximum(r * r - tc * tc, 0.0))  # (t, F) half-chord
    cos = nx[:, None] * tx[None]  # (s, t, F): n_s . n_t
    cos += ny[:, None] * ty[None]
    den = nx[:, None] * ty[None]  # n_s . d_t
    den -= ny[:, None] * tx[None]
    val = c[:, None] - tc[None] * cos
    up, dn = _bounds(val, den)
    hi = np.fmin(w, -up)  # tau <= -val/den where den > 0
    lo = np.fmax(-w, -dn)  # tau >= -val/den where den < 0
    live = hi > lo
    par = np.abs(den) <= PARALLEL
    own = np.arange(mt) + first  # line t's own row s
    par[own, np.arange(mt)] = False
    if par.any():  # only lattices and other exact ties get here: parallel pairs bound nothing ...
        f = np.nonzero(par.any(axis=(0, 1)))[0]
        pf, vf, df = par[..., f], val[..., f], den[..., f]
        q = vf / np.where(np.abs(df) <= PARALLEL, 1.0, df)
        hi[:, f] = np.minimum(w[:, f], -np.where(df > PARALLEL, q, -np.inf).max(axis=0))
        lo[:, f] = np.maximum(-w[:, f], -np.where(df < -PARALLEL, q, np.inf).min(axis=0))
        # ... but a parallel line outside (val > 0) empties the segment, and of two coincident lines with the
        # same orientation only the first keeps it.
        tol = COINCIDENT * r[f]
        earlier = (np.arange(m)[:, None] < own[None, :])[..., None]  # s before t
        killed = pf & ((vf > tol) | ((np.abs(vf) <= tol) & (cos[..., f] > 0) & earlier))
        live[:, f] = (hi[:, f] > lo[:, f]) & ~killed.any(axis=0)
    lo = np.where(live, lo, 0.0)
    hi = np.where(live, hi, 0.0)
    return lo, hi, live


def fan(h, c, lo, hi):
    """Signed area and solid angle of the fan triangles (origin, X(lo), X(hi)) of segments on lines ``c``.

    ``X(tau) = x0 + tau d`` with ``|x0| = |c|`` and ``x0 . d = 0``, seen from
    height ``h`` above the origin (Van Oosterom & Strackee 1983:
    ``tan(Omega/2) = h (X0 x X1) / (|A||B||C| + (A.B)|C| + (A.C)|B| + (B.C)|A|)``).
    Elementwise; ``h`` broadcasts against the segments.
    """
    span = hi - lo
    area = -0.5 * c * span
    h2 = h * h
    c2 = c * c + h2
    b = np.sqrt(c2 + lo * lo)
    e = np.sqrt(c2 + hi * hi)
    vos = h * (b * e + h * (b + e) + c2 + lo * hi)
    omega = 2.0 * np.arctan2(-h * c * span, vos)
    return area, omega


def _bounds(val, den):
    """``max_s val/den`` over den > 0 and ``min_s val/den`` over den < 0, per (t, F).

    Written with 0/0 = NaN for the excluded pairs and NaN-ignoring reductions:
    numpy's masked division (``where=``) and ``np.where`` cost 5-20x a plain
    division here (measured).  Near-parallel pairs (|den| tiny) are redone by
    the caller.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        pos = den > 0.0
        up = np.fmax.reduce((val * pos) / (den * pos), axis=0)
        neg = den < 0.0
        dn = np.fmin.reduce((val * neg) / (den * neg), axis=0)
    return up, dn


def allowed_arc(r, nx, ny, c):
    """Total angle of the circle |x| = r that no line excludes (the arcs of the region's boundary).

    Line t excludes the arc of half-width ``alpha = arccos(-c/r)`` around its
    normal's angle.  The union of the exclusions is measured by the usual
    sweep -- sort the arcs by start, keep the running maximum of their ends --
    on the circle cut open at the first start; what runs past 2 pi wraps over
    the beginning and covers only the gaps found there.  Touching or
    repeated arcs (lattices) need no special case.
    """
    phi = np.arctan2(ny, nx)  # (m, F) in [-pi, pi]
    alpha = np.arccos(np.clip(-c / r, -1.0, 1.0))  # [0, pi]
    start = phi - alpha  # [-2 pi, pi]
    start = np.where(start < 0.0, start + TWO_PI, start)
    order = np.argsort(start, axis=0)
    u = np.take_along_axis(start, order, 0)
    u = u - u[:1]  # the first start at 0
    e = u + 2.0 * np.take_along_axis(alpha, order, 0)
    reach = np.maximum.accumulate(e, axis=0)
    prev = np.concatenate([np.zeros((1, u.shape[1])), reach[:-1]], axis=0)  # covered up to, before arc t
    lo = np.maximum(u, prev)
    inside = np.maximum(np.minimum(e, TWO_PI) - lo, 0.0).sum(axis=0)  # the union within [0, 2 pi)
    wrap = reach[-1:] - TWO_PI  # the union past 2 pi covers [0, wrap] again
    gaps = np.maximum(np.minimum(u, wrap) - prev, 0.0).sum(axis=0)
    return np.maximum(TWO_PI - inside - gaps, 0.0)
