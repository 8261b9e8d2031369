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
  intersection.  Its fan triangle (origin, X0, X1) has the signed area
  ``-c (tau1 - tau0) / 2`` and, seen from the particle at height h above the
  origin, the signed solid angle of Van Oosterom & Strackee (1983);
* the **arcs** are the parts of the circle no line excludes.  Line t
  excludes the angles within ``alpha = arccos(-c/r)`` of its normal's angle;
  an allowed stretch starts at an exclusion's end that no other exclusion
  covers and runs to the nearest exclusion start, so the total allowed angle
  Theta is a min over (m, m) angle gaps.  An arc of angle Theta adds
  ``r^2 Theta / 2`` to the area and ``(1 - h/R) Theta`` to the solid angle
  (a sector of the disk seen from its axis; ``h^2 + r^2 = R^2``).

Degenerate input -- a regular lattice, where several lines coincide and
vertices fall exactly on the circle -- is handled by tie-breaks: of two
coincident lines with the same orientation only the first keeps its segment,
and of two exclusions ending at the same angle only the first opens an arc.

Written by hand because no library in the engine's dependencies clips disks
exactly (scipy's qhull Voronoi diagram was 7-30x slower than the whole frame
budget on 16k particles, see ``cells.py``), and it runs vectorised over all
faces with the same number of lines at once.
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi
PARALLEL = 1e-10  # |sin| below which two lines count as parallel
COINCIDENT = 1e-10  # distance (in units of the disk radius) below which parallel lines coincide
SAME_ANGLE = 1e-12  # radians: exclusion ends closer than this are the same end


def clipped_disk(r: np.ndarray, h: np.ndarray, R: float, normal: np.ndarray, offset: np.ndarray):
    """Area and solid angle (seen from height ``h`` on the axis) of disks clipped by half-planes.

    ``r, h``: (F,) disk radii and apex heights, ``h^2 + r^2 = R^2``;
    ``normal`` (F, m, 2) unit line normals and ``offset`` (F, m) with
    ``|offset| < r``: the region is ``{x: |x| <= r, normal . x + offset <= 0}``.
    Returns ``(area (F,), solid_angle (F,))``, both >= 0.
    """
    r = np.asarray(r, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    F = r.shape[0]
    m = offset.shape[1] if offset.ndim == 2 else 0
    if m == 0:  # an uncut disk
        return np.pi * r * r, TWO_PI * (1.0 - h / R)
    n = np.asarray(normal, dtype=np.float64)
    c = np.asarray(offset, dtype=np.float64)
    seg_area, seg_omega = _segments(r, h, n, c)
    theta = _allowed_arc(r, n, c)
    area = seg_area + 0.5 * r * r * theta
    omega = seg_omega + (1.0 - h / R) * theta
    assert area.shape == (F,)
    return np.maximum(area, 0.0), np.maximum(omega, 0.0)


def _segments(r, h, n, c):
    """Signed fan area and solid angle of every line's boundary segment, summed per face."""
    m = c.shape[1]
    w = np.sqrt(np.maximum(r[:, None] ** 2 - c * c, 0.0))  # (F, m) half-chord
    d = np.stack([-n[..., 1], n[..., 0]], axis=-1)  # (F, m, 2) direction, inside on the left
    nT = np.swapaxes(n, 1, 2)
    den = np.matmul(d, nT)  # (F, t, s): d_t . n_s
    cos = np.matmul(n, nT)  # n_t . n_s
    # Constraint of line s on the segment x0_t + tau d_t of line t (x0 = -c n): val + tau den <= 0.
    val = c[:, None, :] - c[:, :, None] * cos
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -val / den
    # Parallel pairs (the diagonal t = s among them) bound nothing here; below they may kill a segment.
    hi = np.minimum(w, np.where(den > PARALLEL, bound, np.inf).min(axis=2))
    lo = np.maximum(-w, np.where(den < -PARALLEL, bound, -np.inf).max(axis=2))
    live = hi > lo
    par = np.abs(den) <= PARALLEL
    par[:, np.arange(m), np.arange(m)] = False
    if par.any():  # only lattices and other exact ties get here
        tol = COINCIDENT * r[:, None, None]
        first = np.arange(m)[None, None, :] < np.arange(m)[None, :, None]  # s < t
        killed = par & ((val > tol) | ((np.abs(val) <= tol) & (cos > 0) & first))
        live &= ~killed.any(axis=2)
    span = np.where(live, hi - lo, 0.0)
    lo = np.where(live, lo, 0.0)
    hi = lo + span
    area = (-0.5 * c * span).sum(axis=1)
    # Fan triangle (origin, X0, X1), X = x0 + tau d with |x0| = |c| and x0 . d = 0, seen from height h.
    hh = h[:, None]
    h2 = hh * hh
    c2 = c * c + h2
    b = np.sqrt(c2 + lo * lo)
    e = np.sqrt(c2 + hi * hi)
    vos = hh * (b * e + hh * (b + e) + c2 + lo * hi)  # |A||B||C| + (A.B)|C| + (A.C)|B| + (B.C)|A|
    omega = (2.0 * np.arctan2(-hh * c * span, vos)).sum(axis=1)
    return area, omega


def _allowed_arc(r, n, c):
    """Total angle of the circle |x| = r that no line excludes (the arcs of the region's boundary).

    Line t excludes the arc of half-width ``alpha = arccos(-c/r)`` around its
    normal's angle.  The union of the exclusions is measured by the usual
    sweep -- sort the arcs by start, keep the running maximum of their ends --
    on the circle cut open at the first start; what runs past 2 pi wraps over
    the beginning and covers only the gaps found there.  Touching or
    repeated arcs (lattices) need no special case.
    """
    phi = np.arctan2(n[..., 1], n[..., 0])  # [-pi, pi]
    alpha = np.arccos(np.clip(-c / r[:, None], -1.0, 1.0))  # [0, pi]
    start = phi - alpha  # [-2 pi, pi]
    start = np.where(start < 0.0, start + TWO_PI, start)
    order = np.argsort(start, axis=1)
    u = np.take_along_axis(start, order, 1)
    u = u - u[:, :1]  # the first start at 0
    e = u + 2.0 * np.take_along_axis(alpha, order, 1)
    reach = np.maximum.accumulate(e, axis=1)
    prev = np.concatenate([np.zeros((len(u), 1)), reach[:, :-1]], axis=1)  # covered up to, before arc t
    lo = np.maximum(u, prev)
    inside = np.maximum(np.minimum(e, TWO_PI) - lo, 0.0).sum(axis=1)  # the union within [0, 2 pi)
    wrap = reach[:, -1:] - TWO_PI  # the union past 2 pi covers [0, wrap] again
    gaps = np.maximum(np.minimum(u, wrap) - prev, 0.0).sum(axis=1)
    return np.maximum(TWO_PI - inside - gaps, 0.0)
