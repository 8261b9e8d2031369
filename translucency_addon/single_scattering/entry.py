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

and keeps those SH coefficients (``SingleScatteringData.sh_env``) beside psi's own.  The frame's
world term then uses them in place of ``F_in`` times psi's.  Lamps keep psi and ``F_in``: a lamp's irradiance is carried
along straight chords, where its refracted path would start elsewhere on the surface.  The view rays and
their psi toward the viewer are unchanged.

What eq. 2 leaves out:

* the world's direction bent by refraction: w' is looked up as w, which matters only for a world that is
  not uniform, through its low SH orders;
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


def entry_weights(V, F, points, directions, eta: float, bvh=None) -> np.ndarray:
    """``g_i(w_k)`` of eq. 2, ``(n_directions, n_points)``: one chord cast from each point along each
    direction through the mesh ``(V, F)`` (its BVH if given), weighted by where it leaves."""
    from ..geometry.raycast import mesh_bvh

    eta = check_eta(eta)
    P = np.asarray(points, dtype=np.float64)
    D = np.asarray(directions, dtype=np.float64)
    out = np.full((len(D), len(P)), entry_transmittance(eta))
    if eta == 1.0 or not len(P):
        return out
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    bvh = bvh if bvh is not None else mesh_bvh(V, F)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n *= np.sign(signed_volume(V, F)) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]  # outward
    scale = eta * eta
    for k, d in enumerate(D):  # one cast per direction (batching several: no faster, the walk dominates)
        _, tri, _, _ = bvh.intersect(P, np.broadcast_to(d, P.shape))
        mu = np.where(tri >= 0, n[np.maximum(tri, 0)] @ d, -1.0)
        leaves = mu > 0.0
        out[k, leaves] = scale * inside_transmittance(mu[leaves], eta)
    return out
