"""Surface voxels: extract and number them (Mochida et al., precomputation step 1).

A **surface voxel** is a voxel of the bake's grid that the outer mesh passes
through.  Each one stands for the patch of surface inside it: its area
``A_i`` (the mesh area within the voxel), its position (the patch's area
centroid, on the surface) and its normal (the area-weighted mean normal).
These are the entry and exit points x_in, x_out of the poster's sum.

The patches are found by sampling the mesh: every triangle is split into
k x k sub-triangles with k chosen so that a sub-triangle is smaller than a
third of a voxel, and each sub-triangle's area goes to the voxel that holds
its centroid (vectorised per k; no loop per triangle).  Numbering follows the
voxels' flat (x, y, z) index, so neighbouring numbers are neighbouring voxels
(what a GPU's texture cache likes).

Only the outer mesh has surface voxels: light enters and leaves there.
Cavity walls and interfaces between media are inside the object; the chords
between surface voxels cross them (:mod:`.lut`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.meshio import triangle_areas


@dataclass
class SurfaceVoxels:
    """The numbered surface voxels of a grid (object units)."""

    voxel: np.ndarray  # (n,) int64 flat voxel index in the grid
    position: np.ndarray  # (n, 3) area centroid of the patch
    normal: np.ndarray  # (n, 3) unit, outward
    area: np.ndarray  # (n,) patch area, units^2

    @property
    def n(self) -> int:
        return int(len(self.voxel))

    # duck type of a graph level for bake.vertex_mapping
    @property
    def surface_position(self) -> np.ndarray:
        return self.position


def _subtriangle_pattern(k: int):
    """Barycentric centroids (m, 3) of the k^2 congruent sub-triangles of a regular split."""
    up = [((i + 1 / 3) / k, (j + 1 / 3) / k) for i in range(k) for j in range(k - i)]
    down = [((i + 2 / 3) / k, (j + 2 / 3) / k) for i in range(k - 1) for j in range(k - 1 - i)]
    uv = np.array(up + down, dtype=np.float64)
    return np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])


def surface_samples(V, F, spacing: float):
    """Points (m, 3), areas (m,) and triangle ids (m,) covering the mesh with sub-triangles < ``spacing``."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    p = V[F]
    longest = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
    ks = np.maximum(np.ceil(longest / spacing).astype(np.int64), 1)
    areas = triangle_areas(V, F)
    pts, ars, tri = [], [], []
    for k in np.unique(ks):
        sel = np.flatnonzero(ks == k)
        bary = _subtriangle_pattern(int(k))  # (m, 3)
        pts.append(np.einsum("mb,tbc->tmc", bary, p[sel]).reshape(-1, 3))
        ars.append(np.repeat(areas[sel] / (k * k), len(bary)))
        tri.append(np.repeat(sel, len(bary)))
    return np.concatenate(pts), np.concatenate(ars), np.concatenate(tri)


def extract_surface_voxels(V, F, origin, h: float, shape, bvh=None) -> SurfaceVoxels:
    """Number the voxels the mesh passes through, with their patch area, centroid and normal.

    With ``bvh`` (of the same mesh) the centroids are moved onto the surface
    (the closest point): a curved patch's centroid lies inside the object by
    its sagitta, where a shadow ray towards the light would hit the patch's own
    surface and a chord would start short of the boundary.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    pts, ars, tri = surface_samples(V, F, h / 3.0)
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    fn = np.cross(e1, e2)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    shape = np.asarray(shape)
    # A face lying exactly on a voxel boundary (an axis-aligned box on the bbox-aligned grid) would split its
    # samples between the voxels on both sides by round-off: each sample goes to the voxel just inside it.
    inward = pts - (1e-4 * h) * fn[tri]
    ijk = np.clip(np.floor((inward - np.asarray(origin)) / h).astype(np.int64), 0, shape - 1)
    flat = np.ravel_multi_index(ijk.T, tuple(shape))
    voxel, inv = np.unique(flat, return_inverse=True)
    n = len(voxel)
    area = np.bincount(inv, weights=ars, minlength=n)
    pos = np.stack([np.bincount(inv, weights=ars * pts[:, c], minlength=n) for c in range(3)], axis=1)
    nrm = np.stack([np.bincount(inv, weights=ars * fn[tri, c], minlength=n) for c in range(3)], axis=1)
    pos /= np.maximum(area, 1e-300)[:, None]
    ln = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.where(ln > 0, nrm / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    keep = area > 0
    pos = pos[keep]
    if bvh is not None:
        pos = bvh.closest_point(pos)[0]
    return SurfaceVoxels(voxel=voxel[keep], position=pos, normal=nrm[keep], area=area[keep])


def extend_into_surface_voxels(components: np.ndarray, blocked: np.ndarray, surf: SurfaceVoxels,
                               origin, h: float) -> np.ndarray:
    """Component weights with every surface voxel filled by the medium just inside its patch.

    A surface voxel's centre can lie outside the mesh (its inside test says
    air) although part of it is medium; a chord that starts on the surface
    would then miss up to half a voxel of medium at each end, a one-sided bias
    that matters for thin walls (a bottle's glass is one or two voxels).  Such
    voxels take the weights of the voxel half a voxel inward along the patch
    normal (or, failing that, of the 6-neighbour with the most medium).
    Returns a copy of ``components`` (nx, ny, nz, C).
    """
    comp = np.array(components, dtype=np.float32, copy=True)
    shape = comp.shape[:3]
    C = comp.shape[3]
    flat = comp.reshape(-1, C)
    empty = (flat[surf.voxel].sum(axis=1) <= 0) & ~blocked.reshape(-1)[surf.voxel]
    if not empty.any():
        return comp
    sel = np.flatnonzero(empty)
    src_pos = surf.position[sel] - 0.5 * h * surf.normal[sel]
    ijk = np.clip(np.floor((src_pos - np.asarray(origin)) / h).astype(np.int64), 0, np.asarray(shape) - 1)
    src = np.ravel_multi_index(ijk.T, shape)
    got = flat[src].sum(axis=1) > 0
    vox = np.stack(np.unravel_index(surf.voxel[sel], shape), axis=1)
    best = src.copy()
    best_w = np.where(got, flat[src].sum(axis=1), 0.0)
    for d in np.vstack([np.eye(3, dtype=np.int64), -np.eye(3, dtype=np.int64)]):
        nb = np.clip(vox + d, 0, np.asarray(shape) - 1)
        nf = np.ravel_multi_index(nb.T, shape)
        w = flat[nf].sum(axis=1)
        better = ~got & (w > best_w)
        best[better] = nf[better]
        best_w[better] = w[better]
    fill = best_w > 0
    flat[surf.voxel[sel[fill]]] = flat[best[fill]]
    return comp


def vertex_weights(V, normals, surf: SurfaceVoxels, k: int = 6):
    """``(idx (n_v, k), w (n_v, k))``: each vertex's nearest patches, weighted like the QuadGraph's vertex map
    (normal agreement squared over distance squared; :func:`translucency_addon.quadgraph.bake.vertex_mapping`)."""
    from ..quadgraph.bake import vertex_mapping

    return vertex_mapping(np.asarray(V, dtype=np.float64), np.asarray(normals, dtype=np.float64), surf, k)


def sky_visibility(surf: SurfaceVoxels, bvh, directions: np.ndarray, diag: float) -> np.ndarray:
    """(n, D) bool: direction d is in patch i's outer hemisphere and its ray leaves the object unhit."""
    P, N = surf.position, surf.normal
    cos = N @ directions.T
    ii, dd = np.nonzero(cos > 0)
    vis = np.zeros(cos.shape, dtype=bool)
    chunk = 400_000
    for s in range(0, len(ii), chunk):
        a, d = ii[s:s + chunk], dd[s:s + chunk]
        _, tri, _, _ = bvh.intersect(P[a] + 1e-4 * diag * N[a], directions[d])
        vis[a[tri < 0], d[tri < 0]] = True
    return vis
