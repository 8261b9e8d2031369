r"""The view rays' reflections inside (issue 30, item 3): what a view ray sees after the far side reflects it.

A view ray enters at the surface point x along d (refracted there: :func:`.runtime.refract_in`) and meets
the far side at x_1 with inside cosine ``mu_1 = d . n(x_1)``.  The light arriving at x along -d comes
straight from the medium between x and x_1 (the integral :func:`.runtime.integrate_view_rays` evaluates)
and, for the part ``R(mu_1)`` the far side reflects (all of it past the critical angle), from the medium
along the mirrored ray ``d_1 = d - 2 mu_1 n(x_1)``, seen through the first segment::

    L_in(x, -d) = I(x, d) + R(mu_1) exp(-tau(x, x_1)) [I(x_1, d_1) + R(mu_2) exp(-tau(x_1, x_2)) [...]]     (1)

with I(o, w) the once-scattered light a ray from o along w collects (every sample it passes: its light
term, psi towards the ray's origin) and tau along the segments from :mod:`.chords` eq. 1 on the bake's
extinction voxels (``SingleScatteringData.extinction``).  :func:`reflected_rays` builds the reflected rays
(each a :class:`.runtime.ViewRays` of the same vertices, with the parent's exit cosine, so the integrator's
exit factor is the vertex's) and their weights; :func:`integrate_with_reflections` adds their integrals.
This is the view's side of the reflections whose light's side :mod:`.entry` eq. 3 bakes.

The view rays must be refracted for eq. 1 to hold: a straight ray (the paper's) that enters a ball at a
grazing angle meets the far side past the critical angle, where a refracted ray, whose chord meets both
ends at the same angle inside the cone, never is (tried: the brute-force sphere comparison of
``tests/test_single_scattering.py`` went from 0.09 to 0.22 relative RMS with straight rays).  Measured on the
inner-parts bench (albedo 0.2, eta 1.3, a directional sky; single scattering with the orders after the first
against Mitsuba): the hollow cube 18.3 % with straight rays -> 15.1 % refracted -> 10.6 % refracted with eq. 1,
the cube with a stone 19.9 % -> 13.2 % -> 5.8 %.
"""

from __future__ import annotations

import numpy as np

from .entry import inside_transmittance

VIEW_REFLECTIONS = 2  # eq. 1: a view ray is followed through at most this many reflections
VIEW_WEIGHT_CUT = 1e-3  # eq. 1: and while its weight R exp(-tau) is above this in some channel


def reflected_rays(rays, points, bvh, normals, eta: float, depth, margin: float) -> list:
    """Eq. 1's reflected rays of ``rays`` (:class:`.runtime.ViewRays` from ``points``, their vertices' positions
    on the surface): ``[(ViewRays, weight (n, 3)), ...]``, one entry per reflection, rows as in ``rays``
    (weight 0, and a ray of no length, where a ray is not reflected there).  ``bvh``/``normals``: the surface's
    tree and outward facet normals (:func:`.entry.facet_normals`); ``depth(a, b)``: tau along a segment;
    ``margin``: how far a reflected ray runs on beyond the surface (:func:`.runtime.medium_margin`)."""
    from .runtime import ViewRays

    if eta == 1.0 or len(rays.vertices) == 0:
        return []
    P = np.asarray(points, dtype=np.float64)[rays.vertices]
    D = np.asarray(rays.dirs, dtype=np.float64)
    lo, hi = bvh.V.min(axis=0), bvh.V.max(axis=0)
    tmin = 1e-7 * max(float(np.linalg.norm(hi - lo)), 1e-30)
    n = len(P)
    rows = np.arange(n)
    x = P
    w = np.ones((n, 3))
    out = []
    for _ in range(VIEW_REFLECTIONS):
        t, tri, _, _ = bvh.intersect(x, D, tmin=tmin)
        nk = normals[np.maximum(tri, 0)]
        mu = np.where(tri >= 0, np.einsum("ij,ij->i", nk, D), -1.0)
        hit = mu > 0.0  # it meets the far side from inside (else the mesh is open there: the ray ends)
        rows, x, D, w, t, nk, mu = rows[hit], x[hit], D[hit], w[hit], t[hit], nk[hit], mu[hit]
        xn = x + t[:, None] * D
        w = w * np.exp(-depth(x, xn)) * (1.0 - inside_transmittance(mu, eta))[:, None]
        D = D - 2.0 * mu[:, None] * nk
        keep = w.max(axis=1) > VIEW_WEIGHT_CUT
        rows, x, D, w = rows[keep], xn[keep], D[keep], w[keep]
        if not rows.size:
            break
        t2, tri2, _, _ = bvh.intersect(x, D, tmin=tmin)
        weight = np.zeros((n, 3))
        weight[rows] = w
        origins, dirs, t_exit = np.array(P), np.array(rays.dirs, dtype=np.float64), np.zeros(n)
        origins[rows], dirs[rows], t_exit[rows] = x, D, np.where(tri2 >= 0, t2 + margin, 0.0)
        out.append((ViewRays(n_vertices=rays.n_vertices, vertices=rays.vertices, origins=origins, dirs=dirs,
                             t_exit=t_exit, cos_o=rays.cos_o, refracted=True), weight))
    return out


def reflected_rays_of(data, rays, points, bvh, normals, eta: float) -> list:
    """:func:`reflected_rays` with the segments' depth on ``data``'s extinction voxels (:mod:`.chords` eq. 1)
    and its medium margin; none where the data keeps no extinction voxels (eta 1, formats 1-2) or the rays are
    not refracted."""
    from .chords import ChordField, segment_depth
    from .runtime import medium_margin

    field = ChordField.of_data(data)
    if field is None or not rays.refracted:
        return []
    return reflected_rays(rays, points, bvh, normals, eta, lambda a, b: segment_depth(field, a, b),
                          medium_margin(data.voxel_size))


def integrate_with_reflections(integrator, light_term, rays, reflected, *, view_term, eta: float, mm_per_unit,
                               use_gpu: bool = True) -> np.ndarray:
    """Eq. 1 at the vertices of ``rays``: the integrator's pass over the view rays (``view_term`` as given) plus
    each reflected ray set's, psi towards each ray's own origin, times its weight; (n_rays, 3)."""
    L = integrator.integrate(light_term, rays, view_term=view_term, eta=eta, mm_per_unit=mm_per_unit,
                             use_gpu=use_gpu)
    for child, weight in reflected:
        L = L + weight * integrator.integrate(light_term, child, view_term=None, eta=eta, mm_per_unit=mm_per_unit,
                                              use_gpu=use_gpu)
    return L
