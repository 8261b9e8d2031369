"""Ray casts through :class:`.raycast.TriangleBVH` in compiled code (numba): one ray per thread.

The numpy traversal in :meth:`.raycast.TriangleBVH.intersect` walks all rays a tree level at a time
(~13 us per ray on these machines: most of a Final bake's sky visibility, a cold frame's shadow rays
against a 1.3 M-triangle mesh); this is the same walk for one ray at a time: the same boxes, the same
near-child-first order, the same Moller-Trumbore arithmetic (:func:`.raycast.ray_triangle`, written
out) and the same rule for a leaf (its slots against the best distance so far, the first of equal
distances), so it returns the same hits, with distances and barycentrics equal to rounding (LLVM may
fuse a multiply and an add: 1e-14 relative, ``tests/test_raycast.py``).  Measured: 200k random rays
through a bumpy sphere of 82k triangles, 0.22 s against 2.5 s for the numpy walk (12x, 2 shared cores).  Imported only by :mod:`.raycast` inside a guard (importing it
needs numba); where numba is missing the numpy traversal runs, and says nothing: the results are the same.
Hand-written because no library in the bundle traverses this tree (the tree is ours, kept in the cache).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, parallel=True)
def intersect(o, d, inv, tmin, tmax, any_hit, lo, hi, nonempty, first_leaf, split_axis, second_is_plus, v0, e1,
              e2, valid, leaf_tris, depth, best_t, best_tri, best_u, best_v):
    """Closest (or, with ``any_hit``, first found) hit of each ray ``o + t d``, ``tmin < t < tmax[r]``, written
    into ``best_*`` (``best_tri`` -1 and ``best_t`` tmax where a ray misses)."""
    for r in numba.prange(o.shape[0]):
        stack = np.empty(depth + 2, np.int64)
        stack[0] = 0
        sp = 1
        bt = tmax[r]
        btri = -1
        bu = 0.0
        bv = 0.0
        ox, oy, oz = o[r, 0], o[r, 1], o[r, 2]
        dx, dy, dz = d[r, 0], d[r, 1], d[r, 2]
        ix, iy, iz = inv[r, 0], inv[r, 1], inv[r, 2]
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if not nonempty[node]:
                continue
            a1 = (lo[node, 0] - ox) * ix
            a2 = (hi[node, 0] - ox) * ix
            tn, tf = min(a1, a2), max(a1, a2)
            a1 = (lo[node, 1] - oy) * iy
            a2 = (hi[node, 1] - oy) * iy
            tn, tf = max(tn, min(a1, a2)), min(tf, max(a1, a2))
            a1 = (lo[node, 2] - oz) * iz
            a2 = (hi[node, 2] - oz) * iz
            tn, tf = max(tn, min(a1, a2)), min(tf, max(a1, a2))
            if not (tf >= max(tn, tmin) and tn <= bt):
                continue
            if node >= first_leaf:
                lf = node - first_leaf
                k_best = -1
                t_best = np.inf
                u_best = 0.0
                v_best = 0.0
                for k in range(v0.shape[1]):
                    if not valid[lf, k]:
                        continue
                    ex, ey, ez = e1[lf, k, 0], e1[lf, k, 1], e1[lf, k, 2]
                    fx, fy, fz = e2[lf, k, 0], e2[lf, k, 1], e2[lf, k, 2]
                    px = dy * fz - dz * fy
                    py = dz * fx - dx * fz
                    pz = dx * fy - dy * fx
                    det = ex * px + ey * py + ez * pz
                    if not abs(det) > 1e-300:
                        continue
                    inv_det = 1.0 / det
                    sx, sy, sz = ox - v0[lf, k, 0], oy - v0[lf, k, 1], oz - v0[lf, k, 2]
                    u = (sx * px + sy * py + sz * pz) * inv_det
                    qx = sy * ez - sz * ey
                    qy = sz * ex - sx * ez
                    qz = sx * ey - sy * ex
                    v = (dx * qx + dy * qy + dz * qz) * inv_det
                    t = (fx * qx + fy * qy + fz * qz) * inv_det
                    if u >= 0.0 and v >= 0.0 and u + v <= 1.0 and t > tmin and t < bt and t < t_best:
                        k_best, t_best, u_best, v_best = k, t, u, v
                if k_best >= 0:
                    bt, btri, bu, bv = t_best, leaf_tris[lf, k_best], u_best, v_best
                    if any_hit:
                        break
            else:
                ax = split_axis[node]
                near_is_second = (d[r, ax] >= 0.0) != second_is_plus[node]
                if near_is_second:
                    stack[sp] = 2 * node + 1
                    stack[sp + 1] = 2 * node + 2
                else:
                    stack[sp] = 2 * node + 2
                    stack[sp + 1] = 2 * node + 1
                sp += 2
        best_t[r] = bt
        best_tri[r] = btri
        best_u[r] = bu
        best_v[r] = bv


@numba.njit(cache=True, nogil=True, parallel=True)
def leaf_fit(V, F, leaf_tris, v0, e1, e2, valid, leaf_lo, leaf_hi):
    """The leaves of :meth:`.raycast.TriangleBVH._fit` for vertex positions ``V``: each slot's triangle as
    ``v0, e1 = v1 - v0, e2 = v2 - v0`` (zeros in padding slots), whether it is one, and each leaf's box (the
    elementwise minimum and maximum of its triangles' vertices, +-inf for an empty leaf): the numpy fit's
    operations, one leaf per thread, so the same numbers bit for bit (min, max and one subtraction each)."""
    for lf in numba.prange(leaf_tris.shape[0]):
        lo0, lo1, lo2 = np.inf, np.inf, np.inf
        hi0, hi1, hi2 = -np.inf, -np.inf, -np.inf
        for k in range(leaf_tris.shape[1]):
            t = leaf_tris[lf, k]
            if t < 0:
                valid[lf, k] = False
                for j in range(3):
                    v0[lf, k, j] = 0.0
                    e1[lf, k, j] = 0.0
                    e2[lf, k, j] = 0.0
                continue
            valid[lf, k] = True
            ia, ib, ic = F[t, 0], F[t, 1], F[t, 2]
            for j in range(3):
                a, b, c = V[ia, j], V[ib, j], V[ic, j]
                v0[lf, k, j] = a
                e1[lf, k, j] = b - a
                e2[lf, k, j] = c - a
                lo = min(min(a, b), c)
                hi = max(max(a, b), c)
                if j == 0:
                    lo0, hi0 = min(lo0, lo), max(hi0, hi)
                elif j == 1:
                    lo1, hi1 = min(lo1, lo), max(hi1, hi)
                else:
                    lo2, hi2 = min(lo2, lo), max(hi2, hi)
        leaf_lo[lf, 0], leaf_lo[lf, 1], leaf_lo[lf, 2] = lo0, lo1, lo2
        leaf_hi[lf, 0], leaf_hi[lf, 1], leaf_hi[lf, 2] = hi0, hi1, hi2


@numba.njit(cache=True, nogil=True)
def tree_fit(lo, hi, n_leaves, nonempty, split_axis, second_is_plus):
    """The rest of :meth:`.raycast.TriangleBVH._fit` once the leaves' boxes are in ``lo[n_leaves - 1:]`` and
    ``hi[n_leaves - 1:]``: the inner boxes bottom-up (node p's children are 2p + 1 and 2p + 2), then, in
    place, the relative padding (zero boxes where a node is empty) and the traversal hints of every inner
    node (the axis along which its children's centres differ most, the first of equal ones, and whether the
    second child lies on its + side).  The numpy fit's operations in its order, so the same numbers bit for
    bit; in numpy the seven passes over the ~2 n_leaves boxes allocate as many temporaries and took 0.25 s
    of the 0.45 s fit of a 1.3 M-triangle mesh (a cold frame's shadow tree; every deformed frame's refit)."""
    start = n_leaves - 1
    while start > 0:  # one tree level at a time, as the numpy fit
        count = (start + 1) // 2
        p0 = start - count
        for p in range(p0, start):
            c = 2 * p + 1
            for j in range(3):
                lo[p, j] = min(lo[c, j], lo[c + 1, j])
                hi[p, j] = max(hi[c, j], hi[c + 1, j])
        start -= count
    pad = 1e-9 * (max(hi[0, 0] - lo[0, 0], hi[0, 1] - lo[0, 1], hi[0, 2] - lo[0, 2]) + 1e-300)
    for i in range(lo.shape[0]):
        full = lo[i, 0] <= hi[i, 0] and lo[i, 1] <= hi[i, 1] and lo[i, 2] <= hi[i, 2]
        nonempty[i] = full
        for j in range(3):
            if full:
                lo[i, j] = lo[i, j] - pad
                hi[i, j] = hi[i, j] + pad
            else:
                lo[i, j] = 0.0
                hi[i, j] = 0.0
    for p in range(n_leaves - 1):
        a, b = 2 * p + 1, 2 * p + 2
        best, axis, plus = -1.0, 0, True
        for j in range(3):
            dj = 0.5 * (lo[b, j] + hi[b, j]) - 0.5 * (lo[a, j] + hi[a, j])
            if abs(dj) > best:
                best, axis, plus = abs(dj), j, dj >= 0
        split_axis[p] = axis
        second_is_plus[p] = plus
