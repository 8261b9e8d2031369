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
along straight chords, where its refracted path would start elsewhere on the surface.  The view rays are
not this module's (they refract where they enter, :func:`.runtime.refract_in`, and the far side's reflections
of them are :mod:`.view_reflection`).

**Light reflected inside before it scatters** (eq. 3).  Where the chord leaves at x_1, the part
``R(mu_1) = 1 - T(mu_1)`` of what comes back along it (all of it past the critical angle) was reflected
there: it came along the mirrored chord ``w_1 = w - 2 mu_1 n(x_1)``, which leaves at x_2, and so on::

    L_in(b_i, w) = exp(-tau(b_i, w)) sum_{k>=0} [prod_{j<=k, j>=1} R(mu_j) exp(-tau(x_j, x_{j+1}))]
                                     eta^2 T(mu_{k+1}) L_world(w'_{k+1})                              (3)

(the k = 0 term is eq. 1; ``tau(x_j, x_{j+1})`` along the reflected chord, :mod:`.chords` eq. 1).  Each term
is a weight ``g_k`` on psi's chord and a direction ``w'_k`` to look the world up: the bake adds each to
``sh_env`` as eq. 2's (:meth:`WorldEntry.paths`).  The chords are followed for up to :data:`REFLECTIONS`
reflections, and only while ``psi g`` stays above :data:`THROUGHPUT_CUT` of the world's light in some
channel.  In a box a direction past the critical angle at one face meets the next face nearly along its
normal, so much of the light a straight chord loses at the critical cone comes in this way; in a ball a
chord past the critical angle stays past it at every reflection and only eq. 3's partial reflections
count.  Measured on the inner-parts bench's hollow cube (albedo 0.2, 2.5-3.9 optical depths across, a
directional sky, seen from its dark side): single scattering 0.50-0.59 of Mitsuba's light -> 0.64-0.72
with eq. 3 (four reflections in that trial).

What eq. 3 leaves out: the cavities' and inner parts' own interfaces (the chords are cast against the
mesh the bake was given, and cross the inner parts straight).  The view's side of the same reflections is
:mod:`.view_reflection`.

Where the chord enters the object rather than leaves it (a sample outside the surface, in the voxel
model's boundary ramp) or meets nothing, ``g = F_in``: the straight model there.
"""

from __future__ import annotations

import numpy as np

from ..geometry.meshio import signed_volume
from ..scene.fresnel import check_eta, fresnel_transmittance
from .runtime import entry_transmittance

REFLECTIONS = 4  # eq. 3: a chord is followed through at most this many reflections inside
THROUGHPUT_CUT = 1e-3  # eq. 3: and while psi g is above this in some channel (a uniform world of radiance 1)


def facet_normals(V, F) -> np.ndarray:
    """Outward unit normals of the facets of the closed mesh ``(V, F)`` (outward from its signed volume, so
    either winding gives the same)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n * (np.sign(signed_volume(V, F)) / np.maximum(np.linalg.norm(n, axis=1), 1e-300))[:, None]


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
    itself where it does not, or past the critical angle, where g is 0).  One chord cast per point.
    :meth:`paths` adds eq. 3, the chords' light reflected inside, one cast per point and reflection."""

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
        self.normals = facet_normals(V, F)
        self.eps = 1e-7 * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))  # a reflected chord leaves its facet

    def __call__(self, direction, index=None) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 2: ``(g, w_out)`` of the points ``index`` (default all) for the chords along ``direction``."""
        return self._first(np.asarray(direction, dtype=np.float64).reshape(3), index)[:2]

    def _first(self, d, index):
        """Eq. 2 with where each chord leaves: ``(g, w_out, t, normal, mu)`` (mu -1 where it does not)."""
        P = self.points if index is None else self.points[index]
        g = np.full(len(P), self.f_in)
        w_out = np.broadcast_to(d, P.shape).copy()
        if self.eta == 1.0 or not len(P):
            return g, w_out, None, None, None
        eta = self.eta
        t, tri, _, _ = self.bvh.intersect(P, np.broadcast_to(d, P.shape))
        nk = self.normals[np.maximum(tri, 0)]
        mu = np.where(tri >= 0, nk @ d, -1.0)
        leaves = mu > 0.0
        g[leaves] = eta * eta * inside_transmittance(mu[leaves], eta)
        w_out[leaves] = refract_out(np.broadcast_to(d, P.shape)[leaves], nk[leaves], mu[leaves], eta)
        return g, w_out, t, nk, mu

    def paths(self, direction, index=None, psi=None, depth=None):
        """Eq. 3 term by term, for the points ``index`` (default all) and the chords along ``direction``:
        yields ``(rows, g, w_out)`` for k = 0, 1, ...: the rows (into ``index``) whose chord's light reflected
        k times inside leaves, its weight on psi's chord and the world's direction it comes from.  k = 0 is
        eq. 2 (every row, g (n,)); then g is (m, 3), the reflected chords' optical depth per channel.
        ``psi`` (n, 3): the chords' own transmittance, for :data:`THROUGHPUT_CUT`; ``depth(a, b)``: tau along
        a reflected chord (:func:`.chords.segment_depth`).  Without ``depth``, or at eta 1, eq. 2 alone."""
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        g, w_out, t, nk, mu = self._first(d, index)
        n = len(g)
        yield np.arange(n), g, w_out
        if depth is None or t is None:
            return
        eta = self.eta
        rows = np.flatnonzero(mu > 0.0)
        thr = np.repeat((1.0 - inside_transmittance(mu[rows], eta))[:, None], 3, axis=1)  # R(mu_1)
        x = self.points[rows if index is None else np.asarray(index)[rows]] + t[rows, None] * d
        D = d - 2.0 * mu[rows, None] * nk[rows]
        w = np.ones((n, 3)) if psi is None else np.asarray(psi, dtype=np.float64).reshape(n, 3)
        for _ in range(REFLECTIONS):
            keep = (thr * w[rows]).max(axis=1) > THROUGHPUT_CUT
            rows, x, D, thr = rows[keep], x[keep], D[keep], thr[keep]
            if not rows.size:
                return
            t, tri, _, _ = self.bvh.intersect(x, D, tmin=self.eps)
            nk = self.normals[np.maximum(tri, 0)]
            mu = np.where(tri >= 0, np.einsum("ij,ij->i", nk, D), -1.0)
            hit = mu > 0.0  # it leaves through a facet (else the mesh is open there: the chord ends)
            rows, x, D, thr, t, nk, mu = rows[hit], x[hit], D[hit], thr[hit], t[hit], nk[hit], mu[hit]
            xn = x + t[:, None] * D
            thr = thr * np.exp(-depth(x, xn))
            T = inside_transmittance(mu, eta)
            out = T > 0.0
            if out.any():
                yield rows[out], (eta * eta * T[out])[:, None] * thr[out], refract_out(D[out], nk[out], mu[out], eta)
            thr = thr * (1.0 - T)[:, None]
            D = D - 2.0 * mu[:, None] * nk
            x = xn


def refract_out(D, normal, mu, eta: float) -> np.ndarray:
    """The outside direction of chords ``D`` (m, 3) leaving through facets of outward ``normal`` at inside
    cosine ``mu`` > 0 (Snell's law in the plane of the chord and the normal); ``D`` itself past the
    critical angle (no light leaves there)."""
    w_out = np.array(D, dtype=np.float64, copy=True)
    cone = eta * eta * (1.0 - mu * mu) < 1.0
    tangent = eta * (D[cone] - mu[cone, None] * normal[cone])
    w_out[cone] = tangent + np.sqrt(np.clip(1.0 - np.einsum("ij,ij->i", tangent, tangent), 0.0, 1.0))[:, None] \
        * normal[cone]
    return w_out


def world_entry(V, F, points, directions, eta: float, bvh=None) -> tuple[np.ndarray, np.ndarray]:
    """:class:`WorldEntry` for every point and direction: ``g`` (n_directions, n_points) and ``w_out``
    (n_directions, n_points, 3)."""
    entry = WorldEntry(V, F, points, eta, bvh)
    parts = [entry(d) for d in np.asarray(directions, dtype=np.float64)]
    P = len(entry.points)
    if not parts:
        return np.zeros((0, P)), np.zeros((0, P, 3))
    return np.stack([p[0] for p in parts]), np.stack([p[1] for p in parts])
