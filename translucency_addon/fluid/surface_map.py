r"""Carrying the surface cells' radiance onto what Blender renders (issue 14, item 4).

Kang & Kim blur their screen-space radiance map to hide the cell boundaries
(sec. 6); a screen blur mixes the two sides of a thin sheet.  Here each
output point x (a vertex of the liquid's surface mesh, or a particle of a
point cloud) takes a weighted mean of the partial currents J+ of the surface
nodes s near it, in object space::

    w_s(x) = a_s  W(|x - x_s| / rho)  max(0, n(x) . n_s)^2,      rho = 2 R

with a_s the surface node's boundary area, n_s its normal, n(x) the vertex
normal and W the Wendland C2 kernel ``(1 - q)^4 (4 q + 1)`` on q < 1.

* **No cell boundaries**: the weights are continuous in x and in the node
  positions, and a node that appears or disappears between frames does so
  with a_s -> 0 (:mod:`.cells` is exact, so a_s is continuous), so neither the
  image nor the animation shows the cells.
* **No light across thin sheets**: a node whose normal faces away from the
  point's normal (the other side of a sheet, ``n . n_s <= 0``) gets weight 0,
  however close it is.
* A point with no node within rho on its side takes its nearest node on its
  side (or, failing that, its nearest node): a mesh vertex far from the
  particles, or an inner particle of a point cloud, which has no normal and
  is weighted by distance alone.

The weights are ``(idx, w)`` arrays in the layout of the bake's vertex map, so
the output is :meth:`..diffusion.DiffusionSolver.radiance_at` (J+ clamp,
corrected eq. 4/7) unchanged.  The k-nearest weights of
:func:`..bake.vertex_mapping` are not reused: their set of k nodes changes
abruptly as particles move (flicker), and they ignore the node areas.
"""

from __future__ import annotations

import numpy as np

KERNEL_RADII = 2.0  # rho in particle radii
MAX_NODES = 24  # surface nodes considered per point


def wendland(q: np.ndarray) -> np.ndarray:
    """Wendland C2 kernel ``(1 - q)^4 (4 q + 1)`` for q < 1, else 0."""
    t = np.clip(1.0 - q, 0.0, None)
    return t**4 * (4.0 * q + 1.0)


def surface_weights(points, normals, surface_position, surface_normal, surface_area, radius: float,
                    kernel_radii: float = KERNEL_RADII, tree=None):
    """Weights from surface nodes to ``points`` (see the module docstring).

    ``normals``: (n, 3) unit normals of the points, or None (distance only).
    Returns ``(idx (n, k) int32, w (n, k) float, far (n,) bool)``: rows summing
    to 1, and which points had no node within rho on their side (they took
    their nearest node on their side).
    """
    from scipy.spatial import cKDTree

    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ns = len(surface_position)
    if ns == 0 or len(X) == 0:
        return np.zeros((len(X), 1), np.int32), np.zeros((len(X), 1)), np.ones(len(X), dtype=bool)
    tree = tree if tree is not None else cKDTree(surface_position)
    rho = kernel_radii * float(radius)
    k = min(MAX_NODES, ns)
    dist, idx = tree.query(X, k=k, distance_upper_bound=rho)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    found = idx < ns
    idx = np.where(found, idx, 0)
    w = wendland(np.where(found, dist / rho, 1.0)) * np.asarray(surface_area)[idx]
    side = None
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        side = np.einsum("vj,vkj->vk", n, surface_normal[idx])
        w *= np.maximum(side, 0.0) ** 2
    lost = w.sum(axis=1) <= 0
    if lost.any():
        w[lost] = 0.0
        idx[lost] = _nearest_on_side(X[lost], None if normals is None else n[lost], tree, surface_normal,
                                     min(ns, 4 * MAX_NODES))[:, None]
        w[lost, 0] = 1.0
    w /= w.sum(axis=1, keepdims=True)
    return idx.astype(np.int32), w, lost


def _nearest_on_side(X, normals, tree, surface_normal, k):
    """Nearest surface node whose normal agrees with the point's (else the nearest)."""
    _, idx = tree.query(X, k=k)
    idx = idx.reshape(len(X), -1)
    if normals is None:
        return idx[:, 0]
    agree = np.einsum("vj,vkj->vk", normals, surface_normal[idx]) > 0
    first = np.argmax(agree, axis=1)
    pick = idx[np.arange(len(X)), first]
    return np.where(agree.any(axis=1), pick, idx[:, 0])


def smooth_normals(position, normal, area, radius: float, kernel_radii: float = KERNEL_RADII,
                   tree=None) -> np.ndarray:
    """Surface-node normals averaged over the nodes within rho on the same side (the weights above).

    A cell's own normal (its surface face's vector area) turns by 10-20
    degrees when its particle moves by a tenth of the spacing; the fluid's
    surface is smooth above the particle scale, and the light pass (eq. 3's
    ``n . w``) needs that smooth normal, or the radiance near a terminator
    flickers from frame to frame.  Nodes on the other side of a thin sheet
    do not take part (``n . n_s <= 0``).  ``tree``: the positions' ``cKDTree`` where one is built already.
    """
    idx, w, _ = surface_weights(position, normal, position, normal, area, radius, kernel_radii, tree)
    n = np.einsum("vk,vkj->vj", w, np.asarray(normal)[idx])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), normal)
