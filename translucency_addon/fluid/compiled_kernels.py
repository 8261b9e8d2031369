"""The numba kernels of :mod:`.compiled_faces` (see its docstring for what they compute and why).

Imported only by :func:`.compiled_faces._kernel`, inside a guard: importing this module needs numba.  The
kernels are module-level functions, not closures, so numba's on-disk cache (``cache=True``) finds them
again in a new process: a closure over another compiled function got a new cache entry, and a compile of
about 1.5 s, in every process.
"""

from __future__ import annotations

import numba
import numpy as np

BLOCK = 256  # faces per task: the vertex buffers are allocated once per block


@numba.njit(cache=True, nogil=True)
def sector(ax, ay, bx, by):
    """The signed angle from (ax, ay) to (bx, by)."""
    return np.arctan2(ax * by - ay * bx, ax * bx + ay * by)


@numba.njit(cache=True, nogil=True)
def clip(i, j, f, P, n, e1, e2, h, rho, start, nbr, ux, uy, vx, vy) -> int:
    """The region of face f as a counter-clockwise polygon in (ux, uy); its vertex count (0: empty)."""
    s = 2.0 * rho  # the square around the disk, counter-clockwise in (e1, e2)
    ux[0], uy[0], ux[1], uy[1], ux[2], uy[2], ux[3], uy[3] = -s, -s, s, -s, s, s, -s, s
    m = 4
    pix, piy, piz = P[i, 0], P[i, 1], P[i, 2]
    e1x, e1y, e1z = e1[0, f], e1[1, f], e1[2, f]
    e2x, e2y, e2z = e2[0, f], e2[1, f], e2[2, f]
    hx, hy, hz = h * n[0, f], h * n[1, f], h * n[2, f]
    rho2 = rho * rho
    for t in range(start[i], start[i + 1]):
        k = nbr[t]
        if k == j:
            continue
        dx, dy, dz = P[k, 0] - pix, P[k, 1] - piy, P[k, 2] - piz
        a = e1x * dx + e1y * dy + e1z * dz
        b = e2x * dx + e2y * dy + e2z * dz
        dd = dx * dx + dy * dy + dz * dz
        c = 0.5 * dd - (hx * dx + hy * dy + hz * dz)
        ell2 = a * a + b * b
        if ell2 <= 1e-24 * dd:  # k on the axis: all or nothing
            if c < 0.0:
                return 0
            continue
        if c * c >= rho2 * ell2:  # the line misses the disk (|c| / ell >= rho)
            if c > 0.0:
                continue  # the whole disk is on i's side
            return 0  # k takes the whole disk
        q = 0  # keep a u + b v <= c (Sutherland-Hodgman: the region is convex)
        sn = a * ux[0] + b * uy[0] - c
        for p in range(m):
            px, py, sp = ux[p], uy[p], sn
            nxt = p + 1 if p + 1 < m else 0
            nx_, ny_ = ux[nxt], uy[nxt]
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


@numba.njit(cache=True, nogil=True)
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
        if disc <= 0.0:  # no crossing: the sector from A to B alone (P1 = P2 = A + e, the rest exactly 0)
            phi = sector(ax, ay, ax + ex, ay + ey)
            sa += 0.5 * r2 * phi
            so += phi * cone
            continue
        lo, hi = 1.0, 1.0  # a crossing outside the edge: the sector alone, as above
        sq = np.sqrt(disc)
        t1 = min(max((-qb - sq) / (2.0 * qa), 0.0), 1.0)
        t2 = min(max((-qb + sq) / (2.0 * qa), 0.0), 1.0)
        if t1 < t2:
            lo, hi = t1, t2
        p1x, p1y = ax + lo * ex, ay + lo * ey
        p2x, p2y = ax + hi * ex, ay + hi * ey
        phi = (sector(ax, ay, p1x, p1y) if lo > 0.0 else 0.0) + sector(p2x, p2y, bx, by)  # A inside: no first sector
        cr = p1x * p2y - p1y * p2x
        sa += 0.5 * r2 * phi + 0.5 * cr
        if lo == hi:  # P1 = P2: no triangle, its arctangent exactly 0
            so += phi * cone
            continue
        r1 = np.sqrt(h * h + p1x * p1x + p1y * p1y)
        r2_ = np.sqrt(h * h + p2x * p2x + p2y * p2y)
        den = h * r1 * r2_ + h * h * (r1 + r2_) + h * (h * h + p1x * p2x + p1y * p2y)
        so += phi * cone + 2.0 * np.arctan2(h * cr, den)
    return sa, so


@numba.njit(cache=True, nogil=True, parallel=True)
def faces(P, R, fi, fj, n, e1, e2, h, rho, start, nbr, area, omega):
    """Area and solid angle of every face into ``area``/``omega``: :func:`clip`, then :func:`in_disk`."""
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


@numba.njit(cache=True, nogil=True)
def ball_voxels(points, lo, h, R, strides, off, flat_off, oh2, solid):
    """The voxels of :meth:`.occluder.BallOccluder._voxelise`, one particle's stencil at a time (the same
    sums: ``|o h + f|^2 = |o h|^2 + 2 h o.f + |f|^2``, f the particle's offset to its voxel's centre)."""
    r2 = R * R
    for p in range(points.shape[0]):
        bx = np.floor((points[p, 0] - lo[0]) / h)
        by = np.floor((points[p, 1] - lo[1]) / h)
        bz = np.floor((points[p, 2] - lo[2]) / h)
        fx = (bx + 0.5) * h + lo[0] - points[p, 0]
        fy = (by + 0.5) * h + lo[1] - points[p, 1]
        fz = (bz + 0.5) * h + lo[2] - points[p, 2]
        ff = fx * fx + fy * fy + fz * fz
        base = int(bx) * strides[0] + int(by) * strides[1] + int(bz) * strides[2]
        for o in range(off.shape[0]):
            if oh2[o] + (2.0 * h) * (fx * off[o, 0] + fy * off[o, 1] + fz * off[o, 2]) + ff <= r2:
                solid[base + flat_off[o]] = True
