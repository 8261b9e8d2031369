r"""The faces of the Voronoi-fluid cells in compiled code (numba), one face per thread: the fast path.

Same quantities as :func:`.cells._face_geometry` (the numpy path, kept as the fallback where numba is
not installed): for every pair i < j closer than 2R, the area ``S_ij`` of the disk of radius
``rho = sqrt(R^2 - d^2/4)`` on their bisecting plane that is nearer to i and j than to any other
particle, and the solid angle ``Omega_ij`` it subtends from p_i (Kang & Kim 2013 sec. 4.1, 5.1).

Per face, in the plane's basis (e1, e2) with the disk centre at the origin:

1. the cutting lines.  A particle k takes the points x of the plane with ``|x - p_k| < |x - p_i|``,
   the half-plane ``a u + b v > c`` with ``(a, b) = (e1, e2) . (p_k - p_i)`` and
   ``c = |p_k - p_i|^2 / 2 - (d/2) n . (p_k - p_i)``.  A point of the disk lies within R of p_i, so
   only particles within 2R of i cut it: the cell's neighbour list holds every line.  A line farther
   than rho from the centre on the far side bounds nothing; one as far on the near side takes the
   whole disk (the face is empty);
2. the region: a square of half-side 2 rho (the disk inside it) clipped by the lines that cross the
   disk (Sutherland-Hodgman: the region is convex, so one pass per line);
3. the region's intersection with the disk, from its edges (A -> B, counter-clockwise): per edge the
   triangle (0, A, B) cut by the disk is a circular sector from A to where AB enters the disk, the
   straight triangle (0, P1, P2) inside it, and a sector from where AB leaves to B (the classic
   polygon-circle intersection).  A sector of angle phi has area ``rho^2 phi / 2`` and subtends
   ``phi (1 - h/R)`` from p_i at height h = d/2 (a cone of half-angle acos(h/R)); the straight
   triangle subtends ``2 atan2(h (P1 x P2), h r1 r2 + h^2 (r1 + r2) + h (h^2 + P1.P2))``
   (Van Oosterom and Strackee 1983, apex at p_i, r_k = sqrt(h^2 + |P_k|^2)).

Why hand-written: no well-kept library computes Voronoi cells cut by balls.  Measured at 17k
jittered particles on 2 cores: scipy's Qhull Delaunay alone takes 0.67 s (with the per-face closed
forms above, vectorised in numpy, 1.37 s: the numpy path takes 0.95 s), freud's voro++ 0.53 s at
8k for the plain Voronoi cells (no ball, no faces' polygons, and no wheel for Python 3.11).  numba
compiles this loop once per machine (``cache=True``; about 2 s the first time).  The extension's zips bundle
numba and llvmlite where PyPI has them (not for macOS x86-64: there, and wherever numba is missing or fails to
compile, :func:`.cells.cell_path` takes the numpy path and says why).

Exact up to rounding, like the numpy path: lattice ties (four particles on one circle) need no rule
here, since each face is clipped by all its lines in one place and coincident lines clip twice to the
same edge.  ``tests/test_fluid_cells.py`` runs the closed forms and lattices on both paths and holds
them to each other.
"""

from __future__ import annotations

import time

import numpy as np

BLOCK = 256  # faces per task: the vertex buffers are allocated once per block

_KERNEL = {}  # the compiled kernel, built at the first call ({"fn": ...} or {"error": "why not"})


def available() -> str:
    """'' when the compiled path can run, else why not (numba missing, or its compile failed)."""
    _kernel()
    return _KERNEL.get("error", "")


def version() -> str:
    try:
        import numba
    except ImportError:
        return ""
    return str(numba.__version__)


def face_geometry(P, R, fi, fj, normal, e1, e2, h, rho, nbr_start, nbr, nbr_distance):
    """Area and solid angle of each face (i, j) = (``fi[f]``, ``fj[f]``); see the module docstring.

    ``normal, e1, e2``: (3, E) unit normal (i -> j) and in-plane basis (e1 x e2 = n); ``h``: d/2,
    ``rho``: the disk's radius; ``nbr[nbr_start[i]:nbr_start[i + 1]]``: every particle within 2R of
    i, at ``nbr_distance`` from it (each list is sorted by it here: the nearest particles empty a face
    soonest).  Returns ``(area, omega)``, (E,) each.
    """
    fn = _kernel().get("fn")
    if fn is None:
        raise RuntimeError(f"the compiled cell faces are not available: {_KERNEL['error']}")
    E = len(fi)
    area, omega = np.zeros(E), np.zeros(E)
    if E:
        first = not fn.signatures  # this process compiles the kernel now, or loads it from numba's cache
        t0 = time.perf_counter()
        start, nbr = nbr_start.astype(np.int64), nbr.astype(np.int64)
        _KERNEL["sort"](start, nbr, np.array(nbr_distance, dtype=np.float64))
        fn(np.ascontiguousarray(P, dtype=np.float64), float(R), fi.astype(np.int64), fj.astype(np.int64),
           np.ascontiguousarray(normal), np.ascontiguousarray(e1), np.ascontiguousarray(e2),
           np.ascontiguousarray(h, dtype=np.float64), np.ascontiguousarray(rho, dtype=np.float64), start, nbr, area,
           omega)  # one signature: C-contiguous float64/int64 (numba compiles once per signature)
        if first:
            _KERNEL["first_call_s"] = time.perf_counter() - t0
    return area, omega


def face_frames(P, i, j) -> tuple:
    """``(d, n, e1, e2, mid)`` of the faces i -> j, as ``cells._faces`` computes them in numpy (one pass
    instead of some thirty array operations and their temporaries); vectors (3, E)."""
    if "frames" not in _kernel():
        raise RuntimeError(f"the compiled cell faces are not available: {_KERNEL['error']}")
    E = len(i)
    d = np.empty(E)
    n, e1, e2, mid = (np.empty((3, E)) for _ in range(4))
    if E:
        _KERNEL["frames"](np.ascontiguousarray(P, dtype=np.float64), np.ascontiguousarray(i, dtype=np.int64),
                          np.ascontiguousarray(j, dtype=np.int64), d, n, e1, e2, mid)
    return d, n, e1, e2, mid


def first_call_seconds() -> float:
    """What this process's first call took (the kernel compiled, or loaded from numba's cache, and run);
    0 before it."""
    return float(_KERNEL.get("first_call_s", 0.0))


def _kernel() -> dict:
    if _KERNEL:
        return _KERNEL
    try:
        import numba
    except ImportError:
        _KERNEL["error"] = "numba is not installed"
        return _KERNEL
    try:
        _KERNEL["fn"], _KERNEL["sort"], _KERNEL["frames"] = _compile(numba)
    except Exception as ex:  # noqa: BLE001 - any compile failure means the numpy path, with its reason
        _KERNEL["error"] = f"numba {numba.__version__} could not compile the kernel ({type(ex).__name__}: {ex})"
    return _KERNEL


def _compile(numba):
    njit = numba.njit(cache=True, nogil=True)

    @njit
    def sector(ax, ay, bx, by):
        return np.arctan2(ax * by - ay * bx, ax * bx + ay * by)

    @njit
    def clip(i, j, f, P, n, e1, e2, h, rho, start, nbr, ux, uy, vx, vy) -> int:
        """The region of face f as a counter-clockwise polygon in (ux, uy); its vertex count (0: empty)."""
        s = 2.0 * rho  # the square around the disk, counter-clockwise in (e1, e2)
        ux[0], uy[0], ux[1], uy[1], ux[2], uy[2], ux[3], uy[3] = -s, -s, s, -s, s, s, -s, s
        m = 4
        for t in range(start[i], start[i + 1]):
            k = nbr[t]
            if k == j:
                continue
            dx, dy, dz = P[k, 0] - P[i, 0], P[k, 1] - P[i, 1], P[k, 2] - P[i, 2]
            a = e1[0, f] * dx + e1[1, f] * dy + e1[2, f] * dz
            b = e2[0, f] * dx + e2[1, f] * dy + e2[2, f] * dz
            c = 0.5 * (dx * dx + dy * dy + dz * dz) - h * (n[0, f] * dx + n[1, f] * dy + n[2, f] * dz)
            ell2 = a * a + b * b
            if ell2 <= 1e-24 * (dx * dx + dy * dy + dz * dz):  # k on the axis: all or nothing
                if c < 0.0:
                    return 0
                continue
            if c * c >= rho * rho * ell2:  # the line misses the disk (|c| / ell >= rho)
                if c > 0.0:
                    continue  # the whole disk is on i's side
                return 0  # k takes the whole disk
            q = 0  # keep a u + b v <= c (Sutherland-Hodgman: the region is convex)
            for p in range(m):
                px, py = ux[p], uy[p]
                nx_, ny_ = ux[(p + 1) % m], uy[(p + 1) % m]
                sp = a * px + b * py - c
                sn = a * nx_ + b * ny_ - c
                if sp <= 0.0:
                    vx[q], vy[q] = px, py
                    q += 1
                if (sp < 0.0 < sn) or (sn < 0.0 < sp):
                    w = sp / (sp - sn)
                    vx[q], vy[q] = px + w * (nx_ - px), py + w * (ny_ - py)
                    q += 1
            if q < 3:
                return 0
            for p in range(q):
                ux[p], uy[p] = vx[p], vy[p]
            m = q
        return m

    @njit
    def in_disk(m, ux, uy, h, rho, R):
        """Area and solid angle (from the particle at height h) of the polygon's part inside the disk."""
        r2 = rho * rho
        cone = 1.0 - h / R
        sa, so = 0.0, 0.0
        for p in range(m):
            ax, ay = ux[p], uy[p]
            bx, by = ux[(p + 1) % m], uy[(p + 1) % m]
            ex, ey = bx - ax, by - ay
            qa = ex * ex + ey * ey
            if qa == 0.0:
                continue
            qb = 2.0 * (ax * ex + ay * ey)
            qc = ax * ax + ay * ay - r2
            disc = qb * qb - 4.0 * qa * qc
            lo, hi = 1.0, 1.0  # no crossing: the sector from A to B alone
            if disc > 0.0:
                sq = np.sqrt(disc)
                t1 = min(max((-qb - sq) / (2.0 * qa), 0.0), 1.0)
                t2 = min(max((-qb + sq) / (2.0 * qa), 0.0), 1.0)
                if t1 < t2:
                    lo, hi = t1, t2
            p1x, p1y = ax + lo * ex, ay + lo * ey
            p2x, p2y = ax + hi * ex, ay + hi * ey
            phi = sector(ax, ay, p1x, p1y) + sector(p2x, p2y, bx, by)
            cr = p1x * p2y - p1y * p2x
            sa += 0.5 * r2 * phi + 0.5 * cr
            r1 = np.sqrt(h * h + p1x * p1x + p1y * p1y)
            r2_ = np.sqrt(h * h + p2x * p2x + p2y * p2y)
            den = h * r1 * r2_ + h * h * (r1 + r2_) + h * (h * h + p1x * p2x + p1y * p2y)
            so += phi * cone + 2.0 * np.arctan2(h * cr, den)
        return sa, so

    @numba.njit(cache=True, nogil=True, parallel=True)
    def faces(P, R, fi, fj, n, e1, e2, h, rho, start, nbr, area, omega):
        E = fi.shape[0]
        cap = 8  # a clipped square gains at most one vertex per line: 4 + the lines of a face, and one spare
        for i in range(start.shape[0] - 1):
            cap = max(cap, start[i + 1] - start[i] + 6)
        for blk in numba.prange((E + BLOCK - 1) // BLOCK):
            ux, uy, vx, vy = np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap)
            for f in range(blk * BLOCK, min(E, (blk + 1) * BLOCK)):
                if not rho[f] > 0.0:
                    continue
                m = clip(fi[f], fj[f], f, P, n, e1, e2, h[f], rho[f], start, nbr, ux, uy, vx, vy)
                if m:
                    area[f], omega[f] = in_disk(m, ux, uy, h[f], rho[f], R)

    @numba.njit(cache=True, nogil=True, parallel=True)
    def sort_rows(start, nbr, dist):
        """Each particle's neighbours by distance (insertion sort: a few dozen per row)."""
        for i in numba.prange(start.shape[0] - 1):
            for t in range(start[i] + 1, start[i + 1]):
                k, dk = nbr[t], dist[t]
                u = t - 1
                while u >= start[i] and dist[u] > dk:
                    nbr[u + 1], dist[u + 1] = nbr[u], dist[u]
                    u -= 1
                nbr[u + 1], dist[u + 1] = k, dk

    @numba.njit(cache=True, nogil=True, parallel=True)
    def frames(P, i, j, d, n, e1, e2, mid):
        """Per face i -> j: distance, unit normal, the in-plane basis of ``cells._plane_basis`` (e1 = n x the
        axis where |n| is smallest, normalised; e2 = n x e1) and the disk centre."""
        for f in numba.prange(i.shape[0]):
            a, b = i[f], j[f]
            dx, dy, dz = P[b, 0] - P[a, 0], P[b, 1] - P[a, 1], P[b, 2] - P[a, 2]
            dd = np.sqrt(dx * dx + dy * dy + dz * dz)
            nx, ny, nz = dx / dd, dy / dd, dz / dd
            ax, ay, az = abs(nx), abs(ny), abs(nz)
            if ax <= ay and ax <= az:  # n x (1, 0, 0)
                ux, uy, uz = 0.0, nz, -ny
            elif ay <= az:  # n x (0, 1, 0)
                ux, uy, uz = -nz, 0.0, nx
            else:  # n x (0, 0, 1)
                ux, uy, uz = ny, -nx, 0.0
            un = np.sqrt(ux * ux + uy * uy + uz * uz)
            ux, uy, uz = ux / un, uy / un, uz / un
            d[f] = dd
            n[0, f], n[1, f], n[2, f] = nx, ny, nz
            e1[0, f], e1[1, f], e1[2, f] = ux, uy, uz
            e2[0, f], e2[1, f], e2[2, f] = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux
            mid[0, f], mid[1, f], mid[2, f] = 0.5 * (P[a, 0] + P[b, 0]), 0.5 * (P[a, 1] + P[b, 1]), \
                0.5 * (P[a, 2] + P[b, 2])

    return faces, sort_rows, frames
