"""View rays that share a centre of projection, binned in the image plane.

The rays of a frame (``runtime.rays_from_points``) start at the front-facing
surface points and run away from one camera: through its eye (perspective) or
along its view direction (orthographic).  Each ray is then one point of the
image plane, and anything a ray can meet -- a sample's truncated Gaussian (a
ball), a triangle of the far side -- covers a known region of that plane.
Pairing the rays with those regions replaces two per-ray walks:

* the 3D DDA through the sample grid (``ray_pairs._dda``), which meets every
  (ray, sample) pair once per grid cell the ball touches (3.6 times on the
  Final bunny) and needs an ownership test to keep one, and
* the triangle BVH cast to the far side (``raycast.TriangleBVH.intersect``),
  whose numpy loop pops one tree node per ray per iteration.

Here each region is one query: the rays lie sorted by (image row, u) in one
array, so a query is one ``searchsorted`` range per image row it covers, and
every (ray, region) candidate comes out exactly once.  The candidates then go
through the same exact tests as before (``ray_pairs.chord_integrals`` for the
Gaussians, ``raycast.ray_triangle`` for the triangles), so the result is the
same set of pairs and the same numbers; this module only decides which pairs
to test.  Hand-written because no dependency (numpy, scipy) bins 2D points for
range queries with a radius per query and returns the pairs as arrays.

Conservative regions (image coordinates u = X/Z, v = Y/Z in the camera frame,
Z along the mean ray; orthographic: u = X, v = Y):

* a ball of centre c and radius R, met only where Z >= z_lo > 0: the disc of
  radius R |c| / (c_Z z_lo) around the image of c (|w(c + e) - w(c)| =
  |c_Z e_perp - e_Z c_perp| / (c_Z (c_Z + e_Z)) <= |c| |e| / (c_Z z_lo));
  orthographic: the disc of radius R;
* a triangle: the bounding box of the image of its part at Z >= z_lo.

``z_lo`` is the smallest depth of a ray origin: every ray point with t >= 0
lies deeper.  A camera that has a ray origin at or behind its eye plane is not
handled here (``ImageBins.build`` returns None and the caller walks the grid).
"""

from __future__ import annotations

import numpy as np

EPS = 1e-7  # relative padding of every image region (rounding of the projections)


def _frame(forward):
    f = forward / np.linalg.norm(forward)
    a = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    r = np.cross(f, a)
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f])  # rows: right, up, forward


class ImageBins:
    """Ray origins sorted by image row and u, for region queries (see the module docstring)."""

    def __init__(self, M, eye, persp, u, v, z, z_lo):
        self.M, self.eye, self.persp, self.z_lo = M, eye, persp, z_lo
        self.u, self.v, self.z = u, v, z  # image coordinates and depth of the ray origins
        self.u0, self.v0 = float(u.min()), float(v.min())
        self.span = float(max(u.max() - self.u0, v.max() - self.v0, 1e-300))

    @classmethod
    def build(cls, origins, *, camera_position=None, view_dir=None):
        """Bins for rays from ``origins`` away from ``camera_position`` (or along ``-view_dir``);
        None when a ray origin is not in front of the eye (the caller falls back)."""
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        if len(o) == 0:
            return None
        if camera_position is not None:
            eye = np.asarray(camera_position, dtype=np.float64).reshape(3)
            q = o - eye
            fwd = (q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)).mean(axis=0)
            if not np.linalg.norm(fwd) > 0.5:  # rays spread over more than a hemisphere
                return None
            M = _frame(fwd)
            X, Y, Z = (q @ M.T).T
            if not Z.min() > 1e-9 * float(np.abs(q).max()):
                return None
            return cls(M, eye, True, X / Z, Y / Z, Z, float(Z.min()))
        w = np.asarray(view_dir, dtype=np.float64).reshape(3)
        M = _frame(-w)
        X, Y, Z = (o @ M.T).T
        return cls(M, np.zeros(3), False, X, Y, Z, -np.inf)

    # ------------------------------------------------------------ projection
    def project_balls(self, centers, radii):
        """Image discs ``(cu, cv, rho)`` of balls; balls the rays cannot reach get rho = -1."""
        X, Y, Z = ((np.asarray(centers) - self.eye) @ self.M.T).T
        R = np.asarray(radii, dtype=np.float64)
        if not self.persp:
            return X, Y, R * (1 + EPS) + EPS * self.span
        zlo = np.maximum(Z - R, self.z_lo)
        ok = (Z > 0) & (Z + R >= self.z_lo)
        Zs = np.where(ok, Z, 1.0)
        rho = np.where(ok, R * np.sqrt(X * X + Y * Y + Z * Z) / (Zs * zlo), -1.0)
        # A ball reaching past the eye plane (Z <= 0 < Z + R) cannot be bounded by a disc: box of
        # its image over z_lo <= Z <= Z + R, as a disc around the box centre.
        odd = (Z <= 0) & (Z + R >= self.z_lo)
        cu, cv = X / Zs, Y / Zs
        if odd.any():
            zhi = Z[odd] + R[odd]
            ends = [(X[odd] + sx * R[odd]) / zz for sx in (-1, 1) for zz in (self.z_lo, zhi)]
            endv = [(Y[odd] + sy * R[odd]) / zz for sy in (-1, 1) for zz in (self.z_lo, zhi)]
            ulo, uhi = np.min(ends, axis=0), np.max(ends, axis=0)
            vlo, vhi = np.min(endv, axis=0), np.max(endv, axis=0)
            cu[odd], cv[odd] = 0.5 * (ulo + uhi), 0.5 * (vlo + vhi)
            rho[odd] = 0.5 * np.hypot(uhi - ulo, vhi - vlo)
        return cu, cv, np.where(rho >= 0, rho * (1 + EPS) + EPS * self.span, -1.0)

    def project_triangles(self, V, F):
        """Image boxes ``(ulo, uhi, vlo, vhi)`` of triangles (of their part at Z >= z_lo; empty,
        ulo > uhi, for triangles wholly nearer than every ray origin) and their greatest depth Z."""
        P = (np.asarray(V, dtype=np.float64) - self.eye) @ self.M.T
        F = np.asarray(F, dtype=np.int64)
        if not self.persp:
            uv = P[:, :2]
        else:
            zc = self.z_lo * (1 - 1e-9)
            uv = P[:, :2] / np.where(P[:, 2:] > 0, P[:, 2:], 1.0)
        a, b, c = uv[F[:, 0]], uv[F[:, 1]], uv[F[:, 2]]
        lo, hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
        if self.persp:
            near = np.flatnonzero((P[:, 2] < zc)[F].any(axis=1))
            if len(near):  # only the part at Z >= zc counts: corners there and edge crossings of Z = zc
                T = P[F[near]]  # (k, 3 corners, 3)
                z = T[:, :, 2]
                pts, keep = [T], [z >= zc]
                for i, j in ((0, 1), (1, 2), (2, 0)):
                    zi, zj = z[:, i], z[:, j]
                    cross = (zi - zc) * (zj - zc) < 0
                    s = np.where(cross, (zc - zi) / np.where(cross, zj - zi, 1.0), 0.0)
                    pts.append((T[:, i] + s[:, None] * (T[:, j] - T[:, i]))[:, None, :])
                    keep.append(cross[:, None])
                pts, keep = np.concatenate(pts, axis=1), np.concatenate(keep, axis=1)
                q = pts[:, :, :2] / np.where(keep, pts[:, :, 2], 1.0)[:, :, None]
                lo[near] = np.where(keep[:, :, None], q, np.inf).min(axis=1)
                hi[near] = np.where(keep[:, :, None], q, -np.inf).max(axis=1)
        pad = EPS * self.span
        zmax = np.maximum(np.maximum(P[F[:, 0], 2], P[F[:, 1], 2]), P[F[:, 2], 2])
        return lo[:, 0] - pad, hi[:, 0] + pad, lo[:, 1] - pad, hi[:, 1] + pad, zmax

    # --------------------------------------------------------------- queries
    def segments(self, cu, cv, hw, hh, row: float, disc: bool):
        """Ranges of sorted rays for queries centred at (cu, cv) with half sizes (hw, hh; < 0: none).

        ``disc``: the query is the disc of radius hw (= hh); otherwise the box.  The image is cut
        into rows ``row`` high (at most 4096) and each row into columns (1/8 of a row wide, at most
        4M cells);
        rays are sorted by cell.  Returns ``(order, query, lo, hi)``: ``order[lo:hi]`` are the rays
        of the columns that the query's region covers in one row (each ray once per query).
        """
        row = float(max(row, self.span / 4096))  # at most 4096 rows
        n_rows = int(np.floor(self.span / row)) + 1
        col = max(row / 8.0, self.span / max(1, (4 << 20) // n_rows))
        n_cols = int(np.floor(self.span / col)) + 1
        r_of = np.minimum(((self.v - self.v0) / row).astype(np.int64), n_rows - 1)
        c_of = np.minimum(((self.u - self.u0) / col).astype(np.int64), n_cols - 1)
        cell = r_of * n_cols + c_of
        order = np.argsort(cell, kind="stable").astype(np.int32)
        start = np.zeros(n_rows * n_cols + 1, dtype=np.int64)
        np.cumsum(np.bincount(cell, minlength=n_rows * n_cols), out=start[1:])
        live = np.flatnonzero(hw >= 0)
        cu, cv, hw, hh = cu[live], cv[live], hw[live], hh[live]
        r0 = np.clip(np.floor((cv - hh - self.v0) / row), 0, n_rows).astype(np.int64)
        r1 = np.clip(np.floor((cv + hh - self.v0) / row), -1, n_rows - 1).astype(np.int64)
        nr = np.maximum(r1 - r0 + 1, 0)
        q = np.repeat(np.arange(len(live)), nr)
        rr = np.arange(len(q)) - np.repeat(np.cumsum(nr) - nr, nr) + np.repeat(r0, nr)
        half = hw[q]
        if disc:  # chord of the disc over the row band
            band_lo = self.v0 + rr * row
            dy = np.maximum(np.maximum(band_lo - cv[q], cv[q] - band_lo - row), 0.0)
            half = np.sqrt(np.maximum(half * half - dy * dy, 0.0))
        c0 = np.clip(np.floor((cu[q] - half - self.u0) / col), 0, n_cols).astype(np.int64)
        c1 = np.clip(np.floor((cu[q] + half - self.u0) / col), -1, n_cols - 1).astype(np.int64)
        ok = c1 >= c0
        rr, c0, c1, q = rr[ok], c0[ok], c1[ok], q[ok]
        lo = start[rr * n_cols + c0]
        hi = start[rr * n_cols + c1 + 1]
        keep = hi > lo
        return order, live[q[keep]], lo[keep], hi[keep]


def expand(order, query, lo, hi, max_pairs: int):
    """Yield ``(ray, query)`` index arrays (int32) of the candidates of :meth:`ImageBins.segments`,
    in chunks of at most about ``max_pairs`` (one segment is never split)."""
    cnt = hi - lo
    cum = np.cumsum(cnt)
    query = query.astype(np.int32)
    start = 0
    while start < len(cnt):
        base = cum[start] - cnt[start]
        stop = max(int(np.searchsorted(cum, base + max_pairs, side="right")), start + 1)
        c = cnt[start:stop]
        total = int(cum[stop - 1] - base)
        idx = np.arange(total, dtype=np.int32) + np.repeat((lo[start:stop] - (np.cumsum(c) - c)).astype(np.int32), c)
        yield order.take(idx), np.repeat(query[start:stop], c)
        start = stop


def exit_distances(bins: ImageBins, V, F, origins, dirs, tmin: float, max_pairs: int = 1 << 18) -> np.ndarray:
    """Distance from each ray origin to the first triangle of ``V[F]`` beyond ``tmin`` (inf: none).

    The closest hit of ``TriangleBVH.intersect`` with the same ``tmin`` (same Moller-Trumbore
    arithmetic, ``raycast.ray_triangle``), found among the triangles whose image box holds the ray.
    """
    from ..geometry.raycast import ray_triangle

    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    best = np.full(len(o), np.inf)
    ulo, uhi, vlo, vhi, zmax = bins.project_triangles(V, F)
    zmax = zmax + 1e-9 * (float(np.abs(zmax).max()) + 1e-300)  # rounding of the projections
    with np.errstate(invalid="ignore"):
        hw, hh = 0.5 * (uhi - ulo), 0.5 * (vhi - vlo)
        cu, cv = 0.5 * (ulo + uhi), 0.5 * (vlo + vhi)
    live = hw >= 0
    if not live.any():
        return best
    row = float(np.median(2.0 * hh[live]))
    v0 = V[F[:, 0]]
    e1, e2 = V[F[:, 1]] - v0, V[F[:, 2]] - v0
    for ray, tri in expand(*bins.segments(cu, cv, np.where(live, hw, -1.0), hh, row, disc=False), max_pairs):
        # Depth grows along every ray (d . forward > 0): a triangle wholly nearer than the origin is behind it.
        k = np.flatnonzero(zmax.take(tri) > bins.z.take(ray))
        ray, tri = ray.take(k), tri.take(k)
        t, _, _, ok = ray_triangle(o.take(ray, axis=0), d.take(ray, axis=0), v0.take(tri, axis=0),
                                   e1.take(tri, axis=0), e2.take(tri, axis=0))
        ok &= t > tmin
        np.minimum.at(best, ray[ok], t[ok])
    return best
