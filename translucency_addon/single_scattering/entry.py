"""Where the world's light enters: the critical cone (issue 30, item 3).

The paper's light term (eq. 3) carries the outside light along straight chords: at a sample b_i, light from
direction w arrives attenuated by ``psi_i(w) = exp(-tau(b_i, w))``, and :func:`.runtime.light_term` scales
the sum by one mean Fresnel factor ``F_in = 1 - F_dr,ext``.  Inside a dielectric the light does not arrive
that way.  A chord from b_i along w leaves the medium at a boundary point x with inside cosine
``mu = w . n(x)``, and the radiance that comes back along it is::

    L_in(b_i, w) = exp(-tau(b_i, w)) eta^2 T(mu) L_world(w'),    mu > mu_c = sqrt(1 - 1/eta^2),       (1)

and nothing once scattered without an internal reflection where ``mu <= mu_c``.  (F_in = 1 - F_dr,ext is
the mean of T over the outside hemisphere, cosine-weighted: the straight model's stand-in for eq. 1.)  ``T`` is the Fresnel
transmittance (the same from either side), ``eta^2`` is radiance crossing into the denser medium, and w' is
w refracted out.  Light from the whole outside hemisphere is squeezed into the cone ``mu > mu_c`` and made
eta^2 brighter.  For a half-space at albedo 0.2 and eta 1.3 (unit extinction, seen along the normal), eq. 1
returns 0.888 of the straight chords' once-scattered light.  Samples deep in a ball see every chord leave
near the normal, and eq. 1 gives them ``eta^2 T(1) / F_in = 1.77`` times the straight chords' light.

So the bake weighs each sample's psi for the world's light by::

    g_i(w) = eta^2 T(mu) [mu > mu_c]                                                               (2)

and keeps those SH coefficients (``SingleScatteringData.sh_env``) beside psi's own, projected on the
SH basis at w' (:func:`world_entry`), not at w: a world given by its SH coefficients is then looked up
where each chord's light comes from outside, ``sum_k c_k L_k``; a uniform world sees only the constant.  The frame's
world term then uses them in place of ``F_in`` times psi's.  Lamps keep psi and ``F_in``: a lamp's irradiance is carried
along straight chords, where its refracted path would start elsewhere on the surface.  The view rays and
their psi toward the viewer are unchanged.

What eq. 2 leaves out:

* light reflected inside before it scatters: the rest of the total internal reflection, and the cavities'
  and inner parts' own interfaces.  The chords are cast against the mesh the bake was given.

Where the chord enters the object rather than leaves it (a sample outside the surface, in the voxel
model's boundary ramp) or meets nothing, ``g = F_in``: the straight model there.
"""

from __future__ import annotations

import numpy as np

from ..geometry.meshio import signed_volume
from ..scene.fresnel import check_eta, fresnel_transmittance
from .runtime import entry_transmittance


def inside_transmittance(mu, eta: float) -> np.ndarray:
    """``T(mu) [mu > mu_c]``: the Fresnel transmittance of light leaving the medium at inside cosine ``mu``
    (zero past the critical angle), the same as entering at the refracted outside angle."""
    mu = np.clip(np.asarray(mu, dtype=np.float64), 0.0, 1.0)
    s2 = eta * eta * (1.0 - mu * mu)
    cos_out = np.sqrt(np.clip(1.0 - s2, 0.0, 1.0))
    return np.where(s2 < 1.0, fresnel_transmittance(cos_out, eta), 0.0)


class WorldEntry:
    """Eq. 1-2 for chords from fixed ``points`` through the mesh ``(V, F)`` (its BVH if given): called with a
    direction w and the indices of the points that need it, returns ``(g, w_out)`` for those points: the
    weight, and the world's direction the chord's light comes from (w refracted out where it leaves; w
    itself where it does not, or past the critical angle, where g is 0).  One chord cast per point."""

    def __init__(self, V, F, points, eta: float, bvh=None):
        from ..geometry.raycast import mesh_bvh

        self.eta = check_eta(eta)
        self.points = np.asarray(points, dtype=np.float64)
        self.f_in = entry_transmittance(self.eta)
        if self.eta == 1.0:
            return
        V = np.asarray(V, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        self.bvh = bvh if bvh is not None else mesh_bvh(V, F)
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        self.normals = n * (np.sign(signed_volume(V, F)) / np.maximum(np.linalg.norm(n, axis=1), 1e-300))[:, None]

    def __call__(self, direction, index=None) -> tuple[np.ndarray, np.ndarray]:
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        P = self.points if index is None else self.points[index]
        g = np.full(len(P), self.f_in)
        w_out = np.broadcast_to(d, P.shape).copy()
        if self.eta == 1.0 or not len(P):
            return g, w_out
        eta = self.eta
        _, tri, _, _ = self.bvh.intersect(P, np.broadcast_to(d, P.shape))
        nk = self.normals[np.maximum(tri, 0)]
        mu = np.where(tri >= 0, nk @ d, -1.0)
        leaves = mu > 0.0
        g[leaves] = eta * eta * inside_transmittance(mu[leaves], eta)
        out = leaves & (eta * eta * (1.0 - mu * mu) < 1.0)  # inside the cone: Snell's law, out of the medium
        tangent = eta * (d - mu[out, None] * nk[out])
        w_out[out] = tangent + np.sqrt(np.clip(1.0 - np.einsum("ij,ij->i", tangent, tangent), 0.0, 1.0))[:, None] * nk[out]
        return g, w_out


def world_entry(V, F, points, directions, eta: float, bvh=None) -> tuple[np.ndarray, np.ndarray]:
    """:class:`WorldEntry` for every point and direction: ``g`` (n_directions, n_points) and ``w_out``
    (n_directions, n_points, 3)."""
    entry = WorldEntry(V, F, points, eta, bvh)
    parts = [entry(d) for d in np.asarray(directions, dtype=np.float64)]
    P = len(entry.points)
    if not parts:
        return np.zeros((0, P)), np.zeros((0, P, 3))
    return np.stack([p[0] for p in parts]), np.stack([p[1] for p in parts])
