"""The numba kernels of :mod:`.compiled_faces` (see its docstring for what they compute and why).

Imported only by :func:`.compiled_faces._kernel`, inside a guard: importing this module needs numba.  The
kernels are module-level functions, not closures, so numba's on-disk cache (``cache=True``) finds them
again in a new process: a closure over another compiled function got a new cache entry, and a compile of
about 1.5 s, in every process.  numba's ``error_model="numpy"``: a division by zero gives inf or nan as in
numpy instead of raising, so no division carries a zero test (the faces 4-5 % faster, the same cells bit for
bit, measured at 16k particles).
"""

from __future__ import annotations

import numba
import numpy as np

BLOCK = 256  # faces per task: the vertex buffers are allocated once per block


@numba.njit(cache=True, error_model="numpy", nogil=True)
def sector(ax, ay, bx, by):
    """The signed angle from (ax, ay) to (bx, by)."""
    return np.arctan2(ax * by - ay * bx, ax * bx + ay * by)


@numba.njit(cache=True, error_model="numpy", nogil=True)
def clip(j, nx, ny, nz, e1x, e1y, e1z, e2x, e2y, e2z, h, rho, lo, hi, nbr, dx, dy, dz, dd, ux, uy, vx, vy) -> int:
    """The region of face (i, j) as a counter-clockwise polygon in (ux, uy); its vertex count (0: empty).
    ``n`` is the face's unit normal (i -> j), ``e1, e2`` its in-plane basis (:func:`plane_basis`).

    ``nbr[lo:hi]`` is i's neighbour list, ``dx, dy, dz`` each neighbour's offset from p_i and ``dd`` its
    square (:func:`offsets`).  A line is first tested with its normal component only: with
    ``t = n . (p_k - p_i)``, ``c = |p_k - p_i|^2 / 2 - h t`` and ``a^2 + b^2 = |p_k - p_i|^2 - t^2``, so
    the lines that miss the disk (most of them) never need their in-plane coordinates (a, b).  "The disk"
    shrinks as the region does: the region is convex, so it lies within its farthest vertex's distance of
    the centre, and a line farther than that (or than rho) cannot change the region's part in the disk,
    which is all :func:`in_disk` reads.  And a point x of that part lies within ``sqrt(h^2 + reach^2)`` of
    p_i, so only a k with ``|p_k - p_i| < 2 |x - p_i|`` can be nearer to it: the list is sorted by
    distance, and the loop ends at the first k beyond twice that.  Measured at 16k jittered particles:
    the line tests alone were half of the kernel's time.
    """
    s = 2.0 * rho  # the square around the disk, counter-clockwise in (e1, e2)
    ux[0], uy[0], ux[1], uy[1], ux[2], uy[2], ux[3], uy[3] = -s, -s, s, -s, s, s, -s, s
    m = 4
    reach2 = rho * rho  # the region's part in the disk lies within this of the centre: min(rho, |vertex|)^2
    for t in range(lo, hi):
        if nbr[t] == j:
            continue
        px, py, pz, d2 = dx[t], dy[t], dz[t], dd[t]
        if d2 >= 4.0 * (h * h + reach2):  # this k and every later one (the list is sorted) is too far to cut
            break
        tn = nx * px + ny * py + nz * pz
        c = 0.5 * d2 - h * tn
        ell2 = d2 - tn * tn
        if ell2 <= 1e-24 * d2:  # k on the axis: all or nothing
            if c < 0.0:
                return 0
            continue
        if c * c >= reach2 * ell2:  # the line misses what is left of the disk (|c| / ell >= the reach)
            if c > 0.0:
                continue  # all of it is on i's side
            return 0  # k takes all of it
        a = e1x * px + e1y * py + e1z * pz
        b = e2x * px + e2y * py + e2z * pz
        q = 0  # keep a u + b v <= c (Sutherland-Hodgman: the region is convex)
        sn = a * ux[0] + b * uy[0] - c
        for p in range(m):
            qx, qy, sp = ux[p], uy[p], sn
            nxt = p + 1 if p + 1 < m else 0
            nx_, ny_ = ux[nxt], uy[nxt]
            sn = a * nx_ + b * ny_ - c
            if sp <= 0.0:
                vx[q], vy[q] = qx, qy
                q += 1
            if (sp < 0.0 < sn) or (sn < 0.0 < sp):
                w = sp / (sp - sn)
                vx[q], vy[q] = qx + w * (nx_ - qx), qy + w * (ny_ - qy)
                q += 1
        if q < 3:
            return 0
        far2 = 0.0
        for p in range(q):
            ux[p], uy[p] = vx[p], vy[p]
            far2 = max(far2, vx[p] * vx[p] + vy[p] * vy[p])
        m = q
        reach2 = min(reach2, far2)
    return m


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def offsets(P, start, nbr, dx, dy, dz, dd):
    """Each neighbour's offset from its list's particle, ``p_k - p_i``, and its square: computed once per
    list entry instead of once per face that reads the list (about 13 faces per particle)."""
    for i in numba.prange(start.shape[0] - 1):
        for t in range(start[i], start[i + 1]):
            k = nbr[t]
            x, y, z = P[k, 0] - P[i, 0], P[k, 1] - P[i, 1], P[k, 2] - P[i, 2]
            dx[t], dy[t], dz[t], dd[t] = x, y, z, x * x + y * y + z * z


@numba.njit(cache=True, error_model="numpy", nogil=True)
def in_disk(m, ux, uy, h, rho, R):
    """Area and solid angle (from the particle at height h) of the polygon's part inside the disk.

    The straight triangles' solid angles are summed as one argument: each is ``2 atan2(y_k, x_k)``, so
    their sum is twice the argument of the product of the ``x_k + i y_k``, which one ``atan2`` gives at the
    end.  That is exact because the half-angles' sum lies in (-pi, pi): the triangles of either sign form a
    fan from the disk's centre that never overlaps itself and stays inside the disk, which subtends
    2 pi (1 - h/R) < 2 pi from the particle, so their sum is within that of zero.  The product is rescaled
    at every step (by ``|x| + |y|``) so it neither overflows nor underflows.  A sector of zero angle (an edge
    that ends inside the disk) is skipped.  An interior face, whose polygon lies inside its disk, then costs
    one ``atan2`` instead of two per edge: the kernel's most expensive call.
    """
    r2 = rho * rho
    cone = 1.0 - h / R
    sa, so = 0.0, 0.0
    zr, zi = 1.0, 0.0  # the product of the straight triangles' (den + i h cross), rescaled
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
        phi = 0.0  # A inside (lo = 0): no first sector; B inside (hi = 1): no last one
        if lo > 0.0:
            phi += sector(ax, ay, p1x, p1y)
        if hi < 1.0:
            phi += sector(p2x, p2y, bx, by)
        cr = p1x * p2y - p1y * p2x
        sa += 0.5 * r2 * phi + 0.5 * cr
        so += phi * cone
        if lo == hi:  # P1 = P2: no triangle, its arctangent exactly 0
            continue
        r1 = np.sqrt(h * h + p1x * p1x + p1y * p1y)
        r2_ = np.sqrt(h * h + p2x * p2x + p2y * p2y)
        den = h * r1 * r2_ + h * h * (r1 + r2_) + h * (h * h + p1x * p2x + p1y * p2y)
        yi = h * cr
        zr, zi = zr * den - zi * yi, zr * yi + zi * den
        s = abs(zr) + abs(zi)
        if s > 0.0:
            zr, zi = zr / s, zi / s
    return sa, so + 2.0 * np.arctan2(zi, zr)


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def faces(P, R, fi, fj, n, d, start, nbr, area, omega):
    """Area and solid angle of every face into ``area``/``omega``: :func:`clip`, then :func:`in_disk`.  Each
    face's frame -- h = d/2, the disk's radius ``rho = sqrt(R^2 - h^2)``, the in-plane basis -- is computed
    here from its distance and normal (``cells._faces``'s numpy twin stores them: nine more arrays per
    candidate face, 250 MB at 262k particles, whose first touch cost 0.1-0.7 s a frame there)."""
    E = fi.shape[0]
    cap = 8  # a clipped square gains at most one vertex per line: 4 + the lines of a face, and one spare
    for i in range(start.shape[0] - 1):
        cap = max(cap, start[i + 1] - start[i] + 6)
    T = nbr.shape[0]
    dx, dy, dz, dd = np.empty(T), np.empty(T), np.empty(T), np.empty(T)
    offsets(P, start, nbr, dx, dy, dz, dd)
    for blk in numba.prange((E + BLOCK - 1) // BLOCK):
        ux, uy, vx, vy = np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap)
        for f in range(blk * BLOCK, min(E, (blk + 1) * BLOCK)):
            h = 0.5 * d[f]
            rho = np.sqrt(max(R * R - h * h, 0.0))
            if not rho > 0.0:
                continue
            i = fi[f]
            nx, ny, nz = n[0, f], n[1, f], n[2, f]
            e1x, e1y, e1z, e2x, e2y, e2z = plane_basis(nx, ny, nz)
            m = clip(fj[f], nx, ny, nz, e1x, e1y, e1z, e2x, e2y, e2z, h, rho, start[i], start[i + 1], nbr, dx, dy,
                     dz, dd, ux, uy, vx, vy)
            if m:
                area[f], omega[f] = in_disk(m, ux, uy, h, rho, R)


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
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


@numba.njit(cache=True, error_model="numpy", nogil=True, inline="always")
def plane_basis(nx, ny, nz):
    """The in-plane basis of ``cells._plane_basis`` for the unit normal n: e1 = n x the axis where |n| is
    smallest (the first of equals), normalised; e2 = n x e1."""
    ax, ay, az = abs(nx), abs(ny), abs(nz)
    if ax <= ay and ax <= az:  # n x (1, 0, 0)
        ux, uy, uz = 0.0, nz, -ny
    elif ay <= az:  # n x (0, 1, 0)
        ux, uy, uz = -nz, 0.0, nx
    else:  # n x (0, 0, 1)
        ux, uy, uz = ny, -nx, 0.0
    un = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / un, uy / un, uz / un
    return ux, uy, uz, ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux


@numba.njit(cache=True, error_model="numpy", nogil=True)
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


@numba.njit(cache=True, error_model="numpy", nogil=True)
def _cell_ranges(u, g0, dims, ukeys, ustart, lo, hi) -> int:
    """The row ranges of the occupied cells among the 27 around cell u (whose first particle's cell
    coordinates are ``g0``), in ascending key, into ``lo``/``hi``; returns how many."""
    m = 0
    for oz in range(-1, 2):
        z = g0[2] + oz
        if z < 0 or z >= dims[2]:
            continue
        for oy in range(-1, 2):
            y = g0[1] + oy
            if y < 0 or y >= dims[1]:
                continue
            for ox in range(-1, 2):
                x = g0[0] + ox
                if x < 0 or x >= dims[0]:
                    continue
                key = (z * dims[1] + y) * dims[0] + x
                v = np.searchsorted(ukeys, key)
                if v < ukeys.shape[0] and ukeys[v] == key:
                    lo[m], hi[m] = ustart[v], ustart[v + 1]
                    m += 1
    return m


@numba.njit(cache=True, error_model="numpy", nogil=True)
def _scan(i, P, two_r, m, lo, hi, nbr, dist, at) -> int:
    """The particles within 2R of particle i (not i) in the row ranges ``lo[:m]``/``hi[:m]``, in ascending
    index: written to ``nbr[at:]``/``dist[at:]`` where ``at >= 0``; returns how many there are."""
    c = 0
    px, py, pz = P[i, 0], P[i, 1], P[i, 2]
    for r in range(m):
        for k in range(lo[r], hi[r]):
            dx, dy, dz = P[k, 0] - px, P[k, 1] - py, P[k, 2] - pz
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            if d < two_r and k != i:
                if at >= 0:
                    nbr[at + c], dist[at + c] = k, d
                c += 1
    return c


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def neighbour_lists(P, R, g, dims, ukeys, ustart, start):
    """Every particle's neighbours closer than 2R, as CSR rows (``start``, filled here) in ascending index,
    with their distances: per occupied cell of size 2R, its 27 cells' row ranges (one binary search each),
    then two passes over its particles (count, then fill)."""
    N = P.shape[0]
    U = ukeys.shape[0]
    two_r = 2.0 * R
    count = np.zeros(N, dtype=np.int64)
    empty_i, empty_f = np.zeros(0, dtype=np.int64), np.zeros(0)
    for u in numba.prange(U):
        lo, hi = np.empty(27, dtype=np.int64), np.empty(27, dtype=np.int64)
        m = _cell_ranges(u, g[ustart[u]], dims, ukeys, ustart, lo, hi)
        for i in range(ustart[u], ustart[u + 1]):
            count[i] = _scan(i, P, two_r, m, lo, hi, empty_i, empty_f, -1)
    start[0] = 0
    for i in range(N):
        start[i + 1] = start[i] + count[i]
    nbr = np.empty(start[N], dtype=np.int64)
    dist = np.empty(start[N])
    for u in numba.prange(U):
        lo, hi = np.empty(27, dtype=np.int64), np.empty(27, dtype=np.int64)
        m = _cell_ranges(u, g[ustart[u]], dims, ukeys, ustart, lo, hi)
        for i in range(ustart[u], ustart[u + 1]):
            _scan(i, P, two_r, m, lo, hi, nbr, dist, start[i])
    return nbr, dist


@numba.njit(cache=True, error_model="numpy", nogil=True)
def directed_links(a, b, n, src, dst, link, first):
    """Both directions of every face (a[f], b[f]) as links sorted by (source, destination), with the face
    of each (:func:`.cellgraph.build_graph`'s argsort of ``src n + dst``, the same order: no two links share
    a key): a counting sort by source, then each row (~15 links) sorted by destination in place."""
    E = len(a)
    for i in range(n + 1):
        first[i] = 0
    for f in range(E):
        first[a[f] + 1] += 1
        first[b[f] + 1] += 1
    for i in range(n):
        first[i + 1] += first[i]
    pos = first[:n].copy()
    for f in range(E):
        p = pos[a[f]]
        dst[p], link[p] = b[f], f
        pos[a[f]] = p + 1
        p = pos[b[f]]
        dst[p], link[p] = a[f], f
        pos[b[f]] = p + 1
    for i in range(n):
        lo, hi = first[i], first[i + 1]
        for e in range(lo, hi):
            src[e] = i
        for e in range(lo + 1, hi):  # insertion sort of the row by destination, the faces carried along
            d, f = dst[e], link[e]
            k = e - 1
            while k >= lo and dst[k] > d:
                dst[k + 1], link[k + 1] = dst[k], link[k]
                k -= 1
            dst[k + 1], link[k + 1] = d, f


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def fill_slots(first, dst, link, face_distance, face_area, nbr, d, A):
    """Row r's links into its slots 0, 1, ...: neighbour, link length and face area (the graph's layout)."""
    for r in numba.prange(len(first) - 1):
        lo = first[r]
        for s in range(first[r + 1] - lo):
            e = lo + s
            f = link[e]
            nbr[r, s] = dst[e]
            d[r, s] = face_distance[f]
            A[r, s] = face_area[f]


@numba.njit(cache=True, error_model="numpy", nogil=True)
def cell_sums(fi, fj, area, omega, fd, n, sum_omega, cone, vec):
    """Per cell, over its faces (i < j, both ends): the solid angles the faces take from its sphere, their
    cones' volumes ``d S / 6`` and its faces' vector area, minus for i (the normal points i -> j) and plus
    for j (:func:`.cells.build_cells`'s bincounts, one pass)."""
    sum_omega[:] = 0.0
    cone[:] = 0.0
    vec[:] = 0.0
    for f in range(len(fi)):
        i, j = fi[f], fj[f]
        sum_omega[i] += omega[f]
        sum_omega[j] += omega[f]
        c = 0.5 * fd[f] * area[f] / 3.0
        cone[i] += c
        cone[j] += c
        for a in range(3):
            v = area[f] * n[a, f]
            vec[i, a] -= v
            vec[j, a] += v


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def count_upper(start, nbr, count):
    """Per particle i, how many of its neighbours j have j > i (its faces i < j)."""
    for i in numba.prange(start.shape[0] - 1):
        c = 0
        for t in range(start[i], start[i + 1]):
            if nbr[t] > i:
                c += 1
        count[i] = c


@numba.njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def upper_faces(P, start, nbr, first, fi, fj, d, n):
    """The candidate faces i < j from the neighbour lists (rows ascending, so sorted by (i, j)), written from
    ``first[i]`` on, with their distances and unit normals (``cells._face_frames``'s arithmetic)."""
    for i in numba.prange(start.shape[0] - 1):
        f = first[i]
        for t in range(start[i], start[i + 1]):
            j = nbr[t]
            if j > i:
                fi[f], fj[f] = i, j
                dx, dy, dz = P[j, 0] - P[i, 0], P[j, 1] - P[i, 1], P[j, 2] - P[i, 2]
                dd = np.sqrt(dx * dx + dy * dy + dz * dz)
                d[f] = dd
                n[0, f], n[1, f], n[2, f] = dx / dd, dy / dd, dz / dd
                f += 1
