"""Bulk ray casting and closest-point queries against a triangle BVH, in numpy.

The bake places surface nodes by casting rays onto the original surface, the
light pass casts shadow rays from every surface node, single scattering clips
view rays at the surface, and the tests measure distances to the surface.  All
of them query many points at once, so the traversal is vectorised over rays:
every ray keeps its own small stack, and each loop iteration pops one node for
*every* active ray with a handful of array operations.  The loop runs about as
many times as the deepest traversal, never once per ray.

The tree is an implicit, complete binary tree over triangles ordered by
recursive median splits of their centroids: node ``k`` has children
``2k+1`` and ``2k+2``; leaves hold ``LEAF`` consecutive triangles.  Building it
is ``log2(n)`` rounds of vectorised median splits and min/max reductions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .extent import bounds

LEAF = 4
_SHARED: dict = {}  # mesh_bvh's cache: content key -> TriangleBVH, most recent last
SHARED_MAX = 3


def _balanced_order(centroids: np.ndarray, n_slots: int) -> np.ndarray:
    """Order triangles for a complete binary tree by recursive median splits.

    Level by level, every node's range of slots is split at its median along
    the longest axis of its centroids' bounding box; the implicit tree then
    splits each range in the middle.  Padding slots (-1) go last.  A split
    needs only the median, not a sorted range, so each level is one
    ``argpartition`` per range (linear) rather than a global ``lexsort``
    (n log n): a BVH of 1.3 M triangles builds in 3.1 s instead of 10.2 s on
    two cores, queries as fast.  The tree is the same up to the order of
    triangles inside a leaf and ties at a median.
    """
    m = len(centroids)
    perm = np.full(n_slots, -1, dtype=np.int64)
    perm[:m] = np.arange(m)
    # Coordinates by axis in the current order of the slots, moved with them, NaN for padding: fmin/fmax
    # skip it and argpartition sorts it last.  Each level's moves stay inside a node's range, so the
    # gathers are local, and the reductions run along the last, contiguous axis.
    xyz = np.full((3, n_slots), np.nan)
    xyz[:, :m] = np.asarray(centroids, dtype=np.float64).T
    n_nodes = 1
    while n_slots // n_nodes > LEAF:
        size = n_slots // n_nodes
        c = xyz.reshape(3, n_nodes, size)
        ext = _range_reduce(np.fmax, c) - _range_reduce(np.fmin, c)
        axis = np.argmax(np.where(np.isfinite(ext), ext, -1.0), axis=0)
        split = np.argpartition(c[axis, np.arange(n_nodes)], size // 2, axis=1)
        split += (np.arange(n_nodes) * size)[:, None]  # one flat index moves the slots and their data
        split = split.ravel()
        perm, xyz = perm[split], np.take(xyz, split, axis=1)  # 2.5x faster than xyz[:, split]
        n_nodes *= 2
    return perm


def inward_thickness(bvh, V, points, normals) -> np.ndarray:
    """Local thickness (object units) of a closed mesh at surface ``points`` with outward ``normals``.

    One ray per point along its inward normal, from where it enters the surface to where it leaves
    again (``bvh``: the mesh's :class:`TriangleBVH`; ``V`` its vertices, for the scale).  A ray that
    meets no triangle (a grazing ray at an edge or corner, or a hole in an open mesh) takes the median
    of the rays that did: one lost ray must not make a thin part thick.
    """
    V = np.asarray(V, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    n = np.asarray(normals, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    # Enter from just outside and measure entry to exit: a point that sits a hair outside the mesh
    # (placement round-off; seen at 3e-5 units on the unit sphere) would otherwise measure ~0.
    eps = 1e-4 * diag
    origin = p + eps * n
    t_in, tri_in, _, _ = bvh.intersect(origin, -n, tmin=1e-7 * diag)
    entry = origin - np.where(tri_in >= 0, t_in + 1e-6 * diag, eps)[:, None] * n
    t_out, tri_out, _, _ = bvh.intersect(entry, -n, tmin=1e-7 * diag)
    hit = (tri_in >= 0) & (tri_out >= 0)
    t = np.where(hit, t_out + 1e-6 * diag, 0.0)
    return np.where(hit, t, np.median(t[hit]) if hit.any() else diag)


@dataclass
class KeptThickness:
    """:func:`inward_thickness` measured once (at bake time) with the :func:`thickness_digest` of what it was
    measured on, so that a reader can tell whether it still applies."""

    values: np.ndarray
    digest: str


def thickness_digest(V, F, points, normals) -> str:
    """A digest of a mesh and the points and normals its thickness is measured from, the same in every
    process (unlike Python's salted ``hash``): ~30 ms for a 1.3 M-triangle mesh."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    for a, dt in ((V, np.float64), (F, np.int64), (points, np.float64), (normals, np.float64)):
        a = np.ascontiguousarray(a, dtype=dt)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def mesh_bvh(V, F, order=None) -> "TriangleBVH":
    """The :class:`TriangleBVH` of the mesh ``(V, F)``, built once and shared by whoever asks for the
    same mesh: the bake's node placement, the planner's thickness rays, the shadow rays, the
    single-scattering and Voxel Number Map passes -- each built its own, so a frame of a 1.3 M-triangle
    mesh built the same tree two to four times (3 s each here).

    Keyed by the arrays' content (shapes and a hash of their bytes: ~20 ms for 1.3 M triangles), so an
    array edited in place or a moved mesh never gets a stale tree; the last :data:`SHARED_MAX` meshes are
    kept.  A deformed mesh's tree is a :meth:`TriangleBVH.refit`, not this.  ``order``: the tree's
    triangle order from a bake cache (:attr:`TriangleBVH.leaf_tris`, checked by :func:`check_order`
    when the cache was read), so a farm's first frame fits the boxes (1.2 s for 1.3 M triangles) instead
    of ordering the triangles again (another 1.5-2 s).
    """
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    key = content_key(V, F)
    bvh = _SHARED.pop(key, None)
    if bvh is None:
        bvh = TriangleBVH(V, F) if order is None else TriangleBVH.from_order(V, F, order)
    _SHARED[key] = bvh
    while len(_SHARED) > SHARED_MAX:
        _SHARED.pop(next(iter(_SHARED)))
    return bvh


def content_key(*arrays) -> tuple:
    """A key that changes with the arrays' shapes or bytes (Python's hash of the bytes): what a tree built
    from them is cached under (:func:`mesh_bvh`, the solvers' trees of a mesh plus its occluders)."""
    arrays = [np.ascontiguousarray(a) for a in arrays]
    return tuple(a.shape for a in arrays) + tuple(hash(a.tobytes()) for a in arrays)


def leaf_count(n_triangles: int) -> int:
    """The number of leaves the tree of ``n_triangles`` has: the power of two that holds them, LEAF each."""
    n_leaves = 1
    while n_leaves * LEAF < n_triangles:
        n_leaves *= 2
    return n_leaves


def check_order(order, n_triangles: int) -> None:
    """Raise ``ValueError`` unless ``order`` is a :attr:`TriangleBVH.leaf_tris` for ``n_triangles``
    triangles: (n_leaves, LEAF) with n_leaves the power of two the build picks, every triangle once,
    -1 padding."""
    o = np.asarray(order)
    n_leaves = leaf_count(n_triangles)
    if o.shape != (n_leaves, LEAF) or not np.issubdtype(o.dtype, np.integer):
        raise ValueError(f"BVH order has shape {o.shape} ({o.dtype}), expected ({n_leaves}, {LEAF}) integers "
                         f"for {n_triangles} triangles")
    flat = o.ravel()
    real = flat[flat >= 0]
    if (flat < -1).any() or len(real) != n_triangles or (
            n_triangles and (real.max() >= n_triangles or np.bincount(real, minlength=n_triangles).max() != 1)):
        raise ValueError(f"BVH order does not hold each of the {n_triangles} triangles exactly once")


def _range_reduce(op, a: np.ndarray) -> np.ndarray:
    """``op`` over the last axis of ``a`` (a power of two long) by halving: elementwise on
    contiguous halves, about 2x the array's size in all -- numpy's ``reduce`` over a short
    last axis pays a per-row overhead that dominated the build."""
    while a.shape[-1] > 1:
        h = a.shape[-1] // 2
        a = op(a[..., :h], a[..., h:])
    return a[..., 0]


def _morton_codes(c: np.ndarray) -> np.ndarray:
    lo, hi = bounds(c)
    ext = np.maximum(hi - lo, 1e-300)
    q = np.clip(((c - lo) / ext * 1023.0).astype(np.int64), 0, 1023)

    def spread(x):
        x = (x | (x << 16)) & 0x030000FF
        x = (x | (x << 8)) & 0x0300F00F
        x = (x | (x << 4)) & 0x030C30C3
        x = (x | (x << 2)) & 0x09249249
        return x

    return (spread(q[:, 0]) << 2) | (spread(q[:, 1]) << 1) | spread(q[:, 2])


class TriangleBVH:
    """Linear BVH over a triangle soup ``V[F]``.

    Degenerate triangles are kept (they never report a hit).  Coordinates are
    float64 throughout.
    """

    def __init__(self, V, F):
        V = np.asarray(V, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        if len(F) == 0:
            raise ValueError("TriangleBVH needs at least one triangle")
        m = len(F)
        n_leaves = leaf_count(m)
        from .meshio import triangle_centroids

        order = _balanced_order(triangle_centroids(V, F), n_leaves * LEAF)
        self.n_leaves = n_leaves
        self.depth = int(np.log2(n_leaves))
        self.leaf_tris = order.reshape(n_leaves, LEAF)  # original triangle ids, -1 padding
        self.F = F
        self._fit(V)

    @classmethod
    def from_order(cls, V, F, order) -> "TriangleBVH":
        """The tree of ``(V, F)`` with a known triangle order (``leaf_tris`` of an earlier build of the
        same mesh, checked by :func:`check_order`): only the boxes are computed."""
        new = object.__new__(cls)
        new.F = np.asarray(F, dtype=np.int64)
        new.leaf_tris = np.asarray(order, dtype=np.int64)
        new.n_leaves = len(new.leaf_tris)
        new.depth = int(np.log2(new.n_leaves))
        new._fit(np.asarray(V, dtype=np.float64))
        return new

    def refit(self, V) -> "TriangleBVH":
        """The same tree over moved vertices ``V`` (same triangles): new boxes, same triangle order.

        For a deforming mesh (``deformation.py``): a rebuild sorts the
        triangles again (0.6 s for 69k triangles here); a refit recomputes
        the leaf triangles and the boxes bottom-up, ~20x less.  Queries stay
        exact; only the traversal slows down if the motion scrambles the
        spatial order.
        """
        new = object.__new__(TriangleBVH)
        new.n_leaves, new.depth, new.leaf_tris, new.F = self.n_leaves, self.depth, self.leaf_tris, self.F
        new._fit(np.asarray(V, dtype=np.float64))
        return new

    def _fit(self, V):
        """Leaf triangles, boxes and traversal hints of the tree for vertex positions ``V``."""
        n_leaves = self.n_leaves
        n_nodes = 2 * n_leaves - 1
        lo = np.empty((n_nodes, 3))
        hi = np.empty((n_nodes, 3))
        fit = compiled_leaf_fit() if self.leaf_tris.size >= COMPILED_MIN_FIT else None
        if fit is not None:  # the same numbers bit for bit (compiled_raycast.leaf_fit and tree_fit)
            leaf_fit, tree_fit = fit
            self.v0, self.e1, self.e2 = (np.empty((n_leaves, LEAF, 3)) for _ in range(3))
            self.valid = np.empty((n_leaves, LEAF), dtype=np.bool_)
            leaf_fit(_c(V), _c(self.F, np.int64), _c(self.leaf_tris, np.int64), self.v0, self.e1, self.e2, self.valid,
                     lo[n_leaves - 1:], hi[n_leaves - 1:])
            self.nonempty = np.empty(n_nodes, dtype=np.bool_)
            self.split_axis = np.empty(n_leaves - 1, dtype=np.int64)
            self.second_is_plus = np.empty(n_leaves - 1, dtype=np.bool_)
            tree_fit(lo, hi, n_leaves, self.nonempty, self.split_axis, self.second_is_plus)
            self.lo, self.hi = lo, hi
        else:
            self._numpy_fit(V, lo, hi)
        self.first_leaf = n_leaves - 1
        self.V = V
        self._centroid_tree = None

    def _numpy_fit(self, V, lo, hi):
        """:meth:`_fit` in numpy (where numba is missing, and for small trees): ``lo`` and ``hi`` (2 n_leaves - 1,
        3) are filled."""
        n_leaves = self.n_leaves
        slots = self.leaf_tris.ravel()
        valid = slots >= 0
        tri = self.F[np.maximum(slots, 0)]
        a, b, c = (np.where(valid[:, None], V[tri[:, k]], 0.0) for k in range(3))
        self.v0 = a.reshape(n_leaves, LEAF, 3)
        self.e1 = (b - a).reshape(n_leaves, LEAF, 3)
        self.e2 = (c - a).reshape(n_leaves, LEAF, 3)
        self.valid = valid.reshape(n_leaves, LEAF)
        # Elementwise minima over the 3 vertices and the LEAF slots (a reduction along such short
        # axes costs numpy several times more).
        lo3 = np.where(valid[:, None], np.minimum(np.minimum(a, b), c), np.inf).reshape(n_leaves, LEAF, 3)
        hi3 = np.where(valid[:, None], np.maximum(np.maximum(a, b), c), -np.inf).reshape(n_leaves, LEAF, 3)
        tmin, tmax = lo3[:, 0], hi3[:, 0]
        for k in range(1, LEAF):
            tmin, tmax = np.minimum(tmin, lo3[:, k]), np.maximum(tmax, hi3[:, k])
        lo[n_leaves - 1 :] = tmin
        hi[n_leaves - 1 :] = tmax
        start = n_leaves - 1
        while start > 0:  # one tree level at a time; its children are a contiguous range, pairwise
            count = (start + 1) // 2
            p0 = start - count
            c0, c1 = 2 * p0 + 1, 2 * start + 1
            np.minimum(lo[c0:c1:2], lo[c0 + 1:c1 + 1:2], out=lo[p0:start])
            np.maximum(hi[c0:c1:2], hi[c0 + 1:c1 + 1:2], out=hi[p0:start])
            start -= count
        # Pad boxes by a relative epsilon so that axis-aligned flat leaves
        # are still hit by the slab test.
        pad = 1e-9 * (float(np.max(hi[0] - lo[0])) + 1e-300)
        self.nonempty = np.all(lo <= hi, axis=1)
        lo = np.where(self.nonempty[:, None], lo - pad, 0.0)
        hi = np.where(self.nonempty[:, None], hi + pad, 0.0)
        self.lo = lo
        self.hi = hi
        # For front-to-back traversal: the axis along which the two children's
        # centres differ most, and whether the second child lies on its + side.
        cen = 0.5 * (lo + hi)
        diff = cen[2:2 * n_leaves - 1:2] - cen[1:2 * n_leaves - 2:2]  # second child - first, per internal node
        self.split_axis = np.argmax(np.abs(diff), axis=1)
        self.second_is_plus = np.take_along_axis(diff, self.split_axis[:, None], axis=1)[:, 0] >= 0

    # ------------------------------------------------------------------ rays
    def intersect(self, origins, directions, tmin: float = 0.0, tmax=np.inf, any_hit: bool = False):
        """Cast rays; return ``(t, tri, u, v)`` for the closest hit of each ray.

        ``t`` is ``inf`` and ``tri`` is -1 where a ray misses.  ``directions``
        need not be normalised: ``t`` is in units of the given direction.
        With ``any_hit`` each ray stops at its first hit found (shadow rays);
        ``t`` is then a hit distance, not necessarily the closest.
        ``tmax`` may be a scalar or one value per ray.
        """
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.broadcast_to(np.asarray(directions, dtype=np.float64).reshape(-1, 3), o.shape)
        R = len(o)
        best_t = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (R,)).copy()
        best_tri = np.full(R, -1, dtype=np.int64)
        best_u = np.zeros(R)
        best_v = np.zeros(R)
        if R == 0:
            return best_t, best_tri, best_u, best_v
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # a subnormal component: inf, as 0
            inv = 1.0 / d
        inv = np.where(np.isfinite(inv), inv, 1e300)
        kernel = compiled_intersect() if R >= COMPILED_MIN_RAYS else None
        if kernel is not None:  # the same walk, one ray per thread (compiled_raycast.py)
            _walk(kernel, self, o, d, inv, tmin, any_hit, best_t, best_tri, best_u, best_v)
            return best_t, best_tri, best_u, best_v
        stack = np.zeros((R, self.depth + 2), dtype=np.int64)
        sp = np.ones(R, dtype=np.int64)
        active = np.arange(R)
        while active.size:
            node = stack[active, sp[active] - 1]
            sp[active] -= 1
            oa, ia = o[active], inv[active]
            t1 = (self.lo[node] - oa) * ia
            t2 = (self.hi[node] - oa) * ia
            tn = np.minimum(t1, t2).max(axis=1)
            tf = np.maximum(t1, t2).min(axis=1)
            hit = (tf >= np.maximum(tn, tmin)) & (tn <= best_t[active]) & self.nonempty[node]
            leaf = node >= self.first_leaf
            sel = hit & leaf
            if sel.any():
                rays = active[sel]
                lf = node[sel] - self.first_leaf
                self._leaf_test(o[rays], d[rays], lf, rays, tmin, best_t, best_tri, best_u, best_v)
                if any_hit:
                    sp[rays[best_tri[rays] >= 0]] = 0
            sel = hit & ~leaf
            if sel.any():
                rays = active[sel]
                nd = node[sel]
                s = sp[rays]
                # Push the far child first so the near one is popped next.
                dplus = d[rays, self.split_axis[nd]] >= 0
                near_is_second = dplus != self.second_is_plus[nd]
                stack[rays, s] = np.where(near_is_second, 2 * nd + 1, 2 * nd + 2)
                stack[rays, s + 1] = np.where(near_is_second, 2 * nd + 2, 2 * nd + 1)
                sp[rays] = s + 2
            active = active[sp[active] > 0]
        return best_t, best_tri, best_u, best_v

    def _leaf_test(self, o, d, leaf, rays, tmin, best_t, best_tri, best_u, best_v):
        """Moller-Trumbore against the LEAF triangles of each (ray, leaf) pair."""
        t, u, v, ok = ray_triangle(o[:, None, :], d[:, None, :], self.v0[leaf], self.e1[leaf], self.e2[leaf])
        ok &= self.valid[leaf] & (t > tmin) & (t < best_t[rays][:, None])
        t = np.where(ok, t, np.inf)
        j = np.argmin(t, axis=1)
        tj = t[np.arange(len(t)), j]
        better = tj < best_t[rays]
        if better.any():
            r = rays[better]
            k = np.nonzero(better)[0]
            best_t[r] = tj[better]
            best_tri[r] = self.leaf_tris[leaf[k], j[k]]
            best_u[r] = u[k, j[k]]
            best_v[r] = v[k, j[k]]

    def occluded(self, origins, directions, tmax, tmin: float = 0.0) -> np.ndarray:
        """True where the segment ``origin + t dir``, ``tmin < t < tmax``, hits a triangle."""
        _, tri, _, _ = self.intersect(origins, directions, tmin=tmin, tmax=tmax, any_hit=True)
        return tri >= 0

    # ------------------------------------------------------- closest points
    def closest_point(self, points):
        """Closest point on the surface for each query point.

        Returns ``(closest (n, 3), triangle id (n,), distance (n,))``.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        R = len(p)
        # Seed every query with the triangle of its nearest centroid: a tight
        # upper bound prunes almost the whole tree from the first pop.
        from scipy.spatial import cKDTree

        if getattr(self, "_centroid_tree", None) is None:
            from .meshio import triangle_centroids

            # Built once per tree: centroids by component (0.25 s for 1.3 M triangles, 0.75 s as V[F]); a
            # sliding-midpoint tree without compacted nodes builds in 0.4 s instead of 1.0 s and answered
            # queries near the surface ~15 % faster here; the seed only bounds the search, the answer is exact.
            self._centroid_tree = cKDTree(triangle_centroids(self.V, self.F), balanced_tree=False,
                                          compact_nodes=False)
        _, seed = self._centroid_tree.query(p)
        tri = self.V[self.F[seed]]
        best_pt = closest_point_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
        best_d2 = ((best_pt - p) ** 2).sum(axis=1) * (1 + 1e-12)
        best_tri = np.asarray(seed, dtype=np.int64)
        stack = np.zeros((R, self.depth + 2), dtype=np.int64)
        sp = np.ones(R, dtype=np.int64)
        active = np.arange(R)
        while active.size:
            node = stack[active, sp[active] - 1]
            sp[active] -= 1
            pa = p[active]
            dbox = np.maximum(np.maximum(self.lo[node] - pa, pa - self.hi[node]), 0.0)
            near = ((dbox * dbox).sum(axis=1) < best_d2[active]) & self.nonempty[node]
            leaf = node >= self.first_leaf
            sel = near & leaf
            if sel.any():
                rays = active[sel]
                lf = node[sel] - self.first_leaf
                cp = closest_point_on_triangles(
                    p[rays][:, None, :], self.v0[lf], self.v0[lf] + self.e1[lf], self.v0[lf] + self.e2[lf]
                )
                d2 = ((cp - p[rays][:, None, :]) ** 2).sum(axis=2)
                d2 = np.where(self.valid[lf], d2, np.inf)
                j = np.argmin(d2, axis=1)
                dj = d2[np.arange(len(d2)), j]
                better = dj < best_d2[rays]
                r = rays[better]
                k = np.nonzero(better)[0]
                best_d2[r] = dj[better]
                best_tri[r] = self.leaf_tris[lf[k], j[k]]
                best_pt[r] = cp[k, j[k]]
            sel = near & ~leaf
            if sel.any():
                rays = active[sel]
                nd = node[sel]
                s = sp[rays]
                # Visit the nearer child first: push it last.
                c1, c2 = 2 * nd + 1, 2 * nd + 2
                pr = p[rays]
                d1 = (np.maximum(np.maximum(self.lo[c1] - pr, pr - self.hi[c1]), 0) ** 2).sum(axis=1)
                d2_ = (np.maximum(np.maximum(self.lo[c2] - pr, pr - self.hi[c2]), 0) ** 2).sum(axis=1)
                first = np.where(d1 <= d2_, c1, c2)
                second = np.where(d1 <= d2_, c2, c1)
                stack[rays, s] = second
                stack[rays, s + 1] = first
                sp[rays] = s + 2
            active = active[sp[active] > 0]
        return best_pt, best_tri, np.sqrt(best_d2)


def _cross(a, b):
    """a x b over the last axis, written out (np.cross copies its inputs; same arithmetic)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


_COMPILED: dict = {}  # {"fn": the compiled traversal} or {"error": why not}; filled at the first cast
# Casts of fewer rays take the numpy walk: loading numba and the compiled walk costs a process ~0.5-0.9 s once
# (2.5 s the first time on a machine).  By the call's size only, so a frame's rays take the same walk whatever
# the process did before (a farm's frames do not depend on the worker's history, not even in the last bit).
# 1024, not 4096 as before: a Preview frame's lamp chords (one cast per lit surface node, ~4,030 on a 41 k-
# vertex sphere) took the numpy walk at 80-180 ms a cast against 3-6 ms compiled, twice a frame -- half of a
# warm Preview frame (0.27 -> 0.13 s; 655 k vertices 0.51 -> 0.23 s).  A process whose largest cast has
# 1024-4095 rays (a Draft frame) now pays the load once, which every later frame wins back.
COMPILED_MIN_RAYS = 1024
# Trees of at least this many triangle slots fit their leaves in compiled code: the same numbers bit for bit
# (min, max and one subtraction per value), so which path ran never shows; 1.3 M triangles: 0.5 s in numpy.
COMPILED_MIN_FIT = 1 << 17


def ray_path_note() -> str:
    """'' where large ray casts run compiled, else why they take the numpy walk and what that costs (the bake's
    report says it: the results are the same, the sky visibility and shadow rays about 12x slower).  It does
    not load numba to find out: a process that cast no large batch says only whether numba is installed."""
    import importlib.util
    import os

    if os.environ.get("TRANSLUCENCY_NUMPY_RAYS") == "1":
        why = "TRANSLUCENCY_NUMPY_RAYS=1 is set"
    elif "error" in _COMPILED:
        why = _COMPILED["error"]
    elif not _COMPILED and importlib.util.find_spec("numba") is None:
        why = "numba is not installed"
    else:
        return ""
    return (f"ray casts take the numpy walk ({why}): the same hits, about 12x slower than compiled; the "
            "extension's zips bundle numba except for macOS x86-64")


def compiled_intersect():
    """The compiled traversal (:mod:`.compiled_raycast`), or None where numba is missing or cannot compile it
    (then the numpy walk runs: the same hits).  ``TRANSLUCENCY_NUMPY_RAYS=1`` forces the numpy walk (tests)."""
    import os

    if os.environ.get("TRANSLUCENCY_NUMPY_RAYS") == "1":
        return None
    if not _COMPILED:
        try:
            from . import compiled_raycast
        except Exception as ex:  # noqa: BLE001 - numba missing or broken: the numpy walk
            _COMPILED["error"] = f"{type(ex).__name__}: {ex}"
            return None
        fn, why = _built(compiled_raycast.intersect, _warm_up)
        if fn is None:
            _COMPILED["error"] = f"the compiled walk could not be built ({why})"
        else:
            _COMPILED["fn"] = fn
    return _COMPILED.get("fn")


def _built(fn, warm_up):
    """``(fn, '')`` once ``warm_up(fn)`` ran it (numba compiled it, or loaded it from its on-disk cache), else
    ``(None, why)``.  A cache that cannot be loaded (see :func:`_warm_up`) is dropped and ``fn`` compiled
    afresh, once."""
    try:
        warm_up(fn)
        return fn, ""
    except Exception:  # noqa: BLE001 - a stale on-disk cache: compile afresh, once
        try:
            from numba.core.caching import NullCache

            fn._cache = NullCache()
            warm_up(fn)
            return fn, ""
        except Exception as ex:  # noqa: BLE001 - it does not compile here: the numpy path, with the reason
            return None, f"{type(ex).__name__}: {ex}"


def _c(a, dtype=np.float64):
    """C-contiguous, writable, of ``dtype``: every call of the compiled walk has the one signature its warm-up
    compiled (numba compiles, and caches, one version per layout, read-only flag and dtype)."""
    return np.require(a, dtype, ["C", "W"])


def _walk(kernel, bvh, o, d, inv, tmin, any_hit, best_t, best_tri, best_u, best_v) -> None:
    """Run the compiled walk on ``bvh``'s arrays (normalised once per tree) into the ``best_*`` arrays."""
    tree = getattr(bvh, "_walk_arrays", None)
    if tree is None:
        tree = bvh._walk_arrays = (
            _c(bvh.lo), _c(bvh.hi), _c(bvh.nonempty, np.bool_), int(bvh.first_leaf), _c(bvh.split_axis, np.int64),
            _c(bvh.second_is_plus, np.bool_), _c(bvh.v0), _c(bvh.e1), _c(bvh.e2), _c(bvh.valid, np.bool_),
            _c(bvh.leaf_tris, np.int64), int(bvh.depth))
    kernel(_c(o), _c(d), _c(inv), float(tmin), _c(best_t.copy()), bool(any_hit), *tree, best_t, best_tri, best_u,
           best_v)


def compiled_leaf_fit():
    """The compiled fit, ``(leaf_fit, tree_fit)`` of :mod:`.compiled_raycast`, or None (then the numpy fit: the
    same numbers).  Built with the ray walk, and dropped with it where that cannot be built."""
    if compiled_intersect() is None:
        return None
    if "fit" not in _COMPILED:
        from . import compiled_raycast

        leaf = _built(compiled_raycast.leaf_fit, _fit_warm_up)[0]
        tree = _built(compiled_raycast.tree_fit, _tree_fit_warm_up)[0] if leaf is not None else None
        _COMPILED["fit"] = None if tree is None else (leaf, tree)
    return _COMPILED["fit"]


def _fit_warm_up(fn) -> None:
    """Two triangles in a leaf of four slots, through the types every fit passes."""
    V = _c(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    F = _c(np.array([[0, 1, 2], [0, 1, 3]]), np.int64)
    leaf = _c(np.array([[0, 1, -1, -1]]), np.int64)
    v0, e1, e2 = (np.empty((1, LEAF, 3)) for _ in range(3))
    valid = np.empty((1, LEAF), dtype=np.bool_)
    lo, hi = np.empty((2, 3)), np.empty((2, 3))
    fn(V, F, leaf, v0, e1, e2, valid, lo[1:], hi[1:])  # a view of the tree's rows, as _fit passes
    if not (valid.tolist() == [[True, True, False, False]] and lo[1:].tolist() == [[0.0, 0.0, 0.0]]
            and hi[1:].tolist() == [[1.0, 1.0, 1.0]]):
        raise RuntimeError("the compiled leaf fit gave a wrong box for a test leaf")


def _tree_fit_warm_up(fn) -> None:
    """A root over two leaves, the second one +2 along x and empty in a grandchild's place, as _fit passes."""
    lo = np.array([[9.0, 9.0, 9.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    hi = np.array([[9.0, 9.0, 9.0], [1.0, 1.0, 1.0], [3.0, 1.0, 1.0]])
    nonempty, axis, plus = np.empty(3, dtype=np.bool_), np.empty(1, dtype=np.int64), np.empty(1, dtype=np.bool_)
    fn(lo, hi, 2, nonempty, axis, plus)
    pad = 3e-9
    if not (np.allclose(lo[0], -pad, rtol=1e-9, atol=0) and np.allclose(hi[0], [3 + pad, 1 + pad, 1 + pad])
            and nonempty.all() and axis[0] == 0 and plus[0]):
        raise RuntimeError("the compiled tree fit gave a wrong root or hint for a test tree")


def _warm_up(fn) -> None:
    """One ray against one triangle, through :func:`_walk` as every cast: numba compiles the walk, or loads
    it from its on-disk cache.  A cache written for the same file under another package name (the
    repository's ``translucency_addon`` where the add-on runs as ``translucency.translucency_addon``) cannot
    be loaded and raises here, not mid-cast; :func:`compiled_intersect` then compiles without the cache."""
    bvh = TriangleBVH(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[0, 1, 2]]))
    o, d = np.array([[0.2, 0.2, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    inv = np.where(d != 0, 1.0 / np.where(d != 0, d, 1.0), 1e300)
    t, tri, u, v = np.full(1, np.inf), np.full(1, -1, dtype=np.int64), np.zeros(1), np.zeros(1)
    _walk(fn, bvh, o, d, inv, 0.0, False, t, tri, u, v)
    if tri[0] != 0 or abs(t[0] - 1.0) > 1e-12:
        raise RuntimeError(f"the compiled walk missed a test triangle (t {t[0]}, triangle {tri[0]})")


def ray_triangle(o, d, v0, e1, e2):
    """Moller-Trumbore, broadcast over leading axes: ``(t, u, v, ok)`` for rays ``o + t d`` against
    triangles ``v0 + u e1 + v e2`` (all (..., 3)); ``ok`` says the line meets the triangle (t of
    either sign).  The BVH's leaf test and ``single_scattering.projected`` both call it."""
    d = np.broadcast_to(d, np.broadcast_shapes(d.shape, e2.shape))
    p = _cross(d, e2)
    det = np.einsum("...j,...j->...", e1, p)
    ok = np.abs(det) > 1e-300
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - v0
    u = np.einsum("...j,...j->...", s, p) * inv_det
    qv = _cross(s, e1)
    v = np.einsum("...j,...j->...", d, qv) * inv_det
    t = np.einsum("...j,...j->...", e2, qv) * inv_det
    ok &= (u >= 0) & (v >= 0) & (u + v <= 1)
    return t, u, v, ok


def closest_point_on_triangles(p, a, b, c):
    """Closest point on triangle (a, b, c) to p, broadcast over leading axes.

    Ericson, *Real-Time Collision Detection*, sec. 5.1.5, vectorised: the
    Voronoi region of the point is resolved with masks instead of branches.
    """
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = (ab * ap).sum(-1)
    d2 = (ac * ap).sum(-1)
    bp = p - b
    d3 = (ab * bp).sum(-1)
    d4 = (ac * bp).sum(-1)
    cp = p - c
    d5 = (ab * cp).sum(-1)
    d6 = (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in = np.where(denom != 0, vb / denom, 0.0)
        w_in = np.where(denom != 0, vc / denom, 0.0)
        # edge regions
        v_ab = np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0)
        w_ac = np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0)
        w_bc = np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0)
    out = a + ab * v_in[..., None] + ac * w_in[..., None]
    # Resolve regions from the least to the most specific so later masks win.
    m_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    out = np.where(m_bc[..., None], b + (c - b) * w_bc[..., None], out)
    m_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(m_ac[..., None], a + ac * w_ac[..., None], out)
    m_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(m_ab[..., None], a + ab * v_ab[..., None], out)
    m_c = (d6 >= 0) & (d5 <= d6)
    out = np.where(m_c[..., None], c, out)
    m_b = (d3 >= 0) & (d4 <= d3)
    out = np.where(m_b[..., None], b, out)
    m_a = (d1 <= 0) & (d2 <= 0)
    out = np.where(m_a[..., None], a, out)
    return np.broadcast_to(out, np.broadcast_shapes(p.shape, a.shape)).copy()


def inside_mesh(bvh: TriangleBVH, points, n_rays: int = 3) -> np.ndarray:
    """Point-in-solid test by majority vote of ray-parity along several directions.

    Robust to small holes (a few rays may leak through a hole; the vote
    does not).  ``n_rays`` should be odd.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    dirs = np.array([[0.5773, 0.5774, 0.5775], [-0.7071, 0.0123, 0.7070], [0.0213, -0.9995, 0.0231],
                     [0.8, 0.36, -0.48], [-0.3, -0.5, -0.81]])[:n_rays]
    votes = np.zeros(len(p), dtype=np.int64)
    for d in dirs:
        d = d / np.linalg.norm(d)
        votes += count_crossings(bvh, p, d) % 2
    return votes * 2 > n_rays


def count_crossings(bvh: TriangleBVH, points, direction) -> np.ndarray:
    """Number of surface crossings of the ray ``p + t d``, t > 0, for each point."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = np.broadcast_to(np.asarray(direction, dtype=np.float64), p.shape)
    count = np.zeros(len(p), dtype=np.int64)
    origin = p.copy()
    active = np.arange(len(p))
    scale = float(np.linalg.norm(bvh.hi[0] - bvh.lo[0]))
    eps = 1e-9 * scale
    for _ in range(256):
        if active.size == 0:
            break
        t, tri, _, _ = bvh.intersect(origin[active], d[active], tmin=eps)
        hit = tri >= 0
        count[active[hit]] += 1
        origin[active[hit]] = origin[active[hit]] + t[hit, None] * d[active[hit]]
        active = active[hit]
    return count
