"""Points kept on a deforming triangle mesh (the surface half of :mod:`.deformation`).

A point near the user's mesh -- a surface node, a boundary vertex of a level's tet mesh, a
vertex of the resampled shadow surface -- keeps its closest triangle, its barycentric
coordinates there and its small offset (:class:`SurfaceAttachment`); a pose moves it to the
same place on the deformed triangle.  :class:`TriangleGeometry` is what a pose computes once
per triangle for all of them; :func:`triangle_frames` the rotation of a triangle's frame
(what turns the sky visibility's directions, :mod:`.deformed_sky`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


def _cross(a, b) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross's generality costs 2x on these sizes)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def unit(v) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


@dataclass
class TriangleGeometry:
    """Per triangle of the user's mesh in one pose: edge vectors, their cross product, unit normal, area."""

    e1: np.ndarray  # (m, 3) b - a
    e2: np.ndarray  # (m, 3) c - a
    cross: np.ndarray  # (m, 3) e1 x e2 (twice the area; summed into the vertex normals)
    normal: np.ndarray  # (m, 3) unit (0 for a degenerate triangle)
    area: np.ndarray  # (m,)

    @classmethod
    def of(cls, V, F) -> "TriangleGeometry":
        a = V[F[:, 0]]
        e1, e2 = V[F[:, 1]] - a, V[F[:, 2]] - a
        n = _cross(e1, e2)
        ln = np.sqrt(np.einsum("mi,mi->m", n, n))
        unit = np.divide(n, ln[:, None], out=np.zeros_like(n), where=ln[:, None] > 0)
        return cls(e1, e2, n, unit, 0.5 * ln)


def triangle_frames(V, F, tri) -> np.ndarray:
    """(m, 3, 3) orthonormal frames of triangles ``tri``: rows (e1 direction, normal x e1, normal);
    the identity for a degenerate triangle."""
    p = V[F[tri]]
    e1 = p[:, 1] - p[:, 0]
    n = _cross(e1, p[:, 2] - p[:, 0])
    ok = (np.linalg.norm(n, axis=1) > 0) & (np.linalg.norm(e1, axis=1) > 0)
    frames = np.broadcast_to(np.eye(3), (len(tri), 3, 3)).copy()
    t, nn = unit(e1[ok]), unit(n[ok])
    frames[ok] = np.stack([t, _cross(nn, t), nn], axis=1)
    return frames


def _barycentric(p, a, b, c) -> np.ndarray:
    """(m, 3) barycentric coordinates of points ``p`` lying on triangles (a, b, c)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    ok = den > 0
    den = np.where(ok, den, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / den, 1.0 / 3.0)
    w = np.where(ok, (d00 * d21 - d01 * d20) / den, 1.0 / 3.0)
    return np.stack([1.0 - v - w, v, w], axis=1)


@dataclass
class SurfaceAttachment:
    """Points kept on the user's mesh: closest triangle, barycentric coordinates, small offset.

    At rest ``p = sum_j bary_j V[F[tri, j]] + c_1 e1 + c_2 e2 + h n`` (e1, e2: the triangle's
    edge vectors, n its unit normal; c and h are zero for a point on the surface).  A pose
    moves the point to the same expression on the deformed triangle, with h scaled by
    sqrt(area ratio): exact for every affine map in the plane and for similarities (rigid
    motion, uniform scale) off it.  :meth:`displacement` forms the difference, so a pose that
    moves nothing moves nothing.
    """

    tri: np.ndarray  # (m,) triangle of the user's mesh
    bary: np.ndarray  # (m, 3)
    weights: object  # sparse (m, n_vertices): the barycentric interpolation
    off: np.ndarray  # indices of the points with an offset
    offset: np.ndarray  # (len(off), 3): c_1, c_2, h

    @classmethod
    def locate(cls, bvh, points, geo: TriangleGeometry) -> "SurfaceAttachment":
        """Attach ``points`` to their closest triangles (``bvh`` over the user's mesh in ``geo``'s pose)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        m = len(points)
        cp, tri, _ = bvh.closest_point(points)
        tri = np.asarray(tri, dtype=np.int64)
        p = bvh.V[bvh.F[tri]]
        bary = _barycentric(cp, p[:, 0], p[:, 1], p[:, 2])
        weights = sp.csr_matrix((bary.ravel(), (np.repeat(np.arange(m), 3), bvh.F[tri].ravel())),
                                shape=(m, len(bvh.V)))
        r = points - cp
        off = np.nonzero(np.any(r != 0.0, axis=1))[0]
        t, r = tri[off], r[off]
        h = np.einsum("mi,mi->m", r, geo.normal[t])
        E = np.stack([geo.e1[t], geo.e2[t]], axis=2)
        G = np.einsum("mki,mkj->mij", E, E)
        ok = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2 > 0
        rhs = np.einsum("mki,mk->mi", E, r - h[:, None] * geo.normal[t])
        c = np.zeros((len(off), 2))
        c[ok] = np.linalg.solve(G[ok], rhs[ok][..., None])[..., 0]
        return cls(tri, bary, weights, off, np.column_stack([c, h]))

    def displacement(self, D, rest: TriangleGeometry, pose: TriangleGeometry) -> np.ndarray:
        """(m, 3) motion of the points for vertex displacement ``D`` from pose ``rest`` to ``pose``."""
        u = self.weights @ D
        if len(self.off):
            t, c = self.tri[self.off], self.offset
            scale = np.sqrt(np.divide(pose.area[t], rest.area[t], out=np.ones(len(t)), where=rest.area[t] > 0))
            u[self.off] += ((pose.e1[t] - rest.e1[t]) * c[:, :1] + (pose.e2[t] - rest.e2[t]) * c[:, 1:2]
                            + c[:, 2:] * (scale[:, None] * pose.normal[t] - rest.normal[t]))
        return u

    def interpolate(self, values) -> np.ndarray:
        """Per-vertex ``values`` (n, k) interpolated at the points."""
        return self.weights @ values
