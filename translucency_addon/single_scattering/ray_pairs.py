"""Which truncated Gaussians each view ray passes, and the closed-form integral of each along its chord:
the per-ray half of Bernabei et al.'s eq. 3 (:func:`.runtime.integrate_view_rays` sums the products).

Two ways to find the (ray, sample) pairs, with the same result: the uniform sample grid walked by a 3D DDA
(:func:`ray_sample_pairs`, the GPU kernel's walk), or, for the rays of one camera, the image plane's bins
(:func:`projected_pairs`); :func:`chord_integrals` is the erf of the Gaussian over the segment.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

from .projected import ImageBins, expand


def _dda(grid, o, d, t0, t1):
    """Cells crossed by the segments o + t d, t in [t0, t1] (3D DDA, vectorised over rays).

    Returns (ray, cell, t_in, t_out) sorted by ray then along the ray; the
    first interval of every ray starts at -inf and the last ends at +inf so
    that the intervals of a ray partition the whole line.
    """
    lo = grid.origin
    c = grid.cell_size
    dims = grid.dims
    hi = lo + dims * c
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta = (lo - o) * inv
        tb = (hi - o) * inv
    ta = np.where(np.isnan(ta), -np.inf, ta)
    tb = np.where(np.isnan(tb), np.inf, tb)
    tn = np.minimum(ta, tb).max(axis=1)
    tf = np.maximum(ta, tb).min(axis=1)
    t_enter = np.maximum(t0, tn)
    t_leave = np.minimum(t1, tf)
    ray = np.flatnonzero(t_enter < t_leave)
    if ray.size == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e, np.zeros(0), np.zeros(0)
    o, d, inv = o[ray], d[ray], inv[ray]
    t_cur = t_enter[ray]
    t_end = t_leave[ray]
    p = o + t_cur[:, None] * d
    cell = np.clip(np.floor((p - lo) / c).astype(np.int64), 0, dims - 1)
    pos = d > 0
    strides = np.array([dims[1] * dims[2], dims[2], 1])
    lin = cell @ strides
    lstep = np.where(pos, 1, np.where(d < 0, -1, 0)) * strides  # linear index step per axis
    # how many more cells each ray may enter along each axis before leaving the grid
    left = np.where(pos, dims - 1 - cell, np.where(d < 0, cell, 0))
    with np.errstate(invalid="ignore"):
        tmax = np.where(d != 0, (lo + (cell + pos) * c - o) * inv, np.inf)
        tdelta = np.where(d != 0, c * np.abs(inv), np.inf)
    out_r, out_c, out_a, out_b = [], [], [], []
    while ray.size:
        ax = np.argmin(tmax, axis=1)
        k = np.arange(len(ray))
        tn_ = tmax[k, ax]
        t_next = np.minimum(tn_, t_end)
        out_r.append(ray)
        out_c.append(lin)
        out_a.append(t_cur)
        out_b.append(t_next)
        ok = (tn_ < t_end) & (left[k, ax] > 0)
        lin = lin + lstep[k, ax]
        left[k, ax] -= 1
        tmax[k, ax] += tdelta[k, ax]
        t_cur = t_next
        if not ok.all():
            ray, lin, t_cur, t_end, tmax, tdelta, lstep, left = (
                ray[ok], lin[ok], t_cur[ok], t_end[ok], tmax[ok], tdelta[ok], lstep[ok], left[ok])
    r = np.concatenate(out_r)
    order = np.argsort(r, kind="stable")
    r = r[order]
    cells = np.concatenate(out_c)[order]
    a = np.concatenate(out_a)[order]
    b = np.concatenate(out_b)[order]
    first = np.ones(len(r), dtype=bool)
    first[1:] = r[1:] != r[:-1]
    last = np.ones(len(r), dtype=bool)
    last[:-1] = r[1:] != r[:-1]
    a[first] = -np.inf
    b[last] = np.inf
    return r, cells, a, b


def ray_sample_pairs(data, origins, dirs, t_exit):
    """Every (ray, sample) pair whose truncated Gaussian meets the segment, exactly once.

    Returns ``(ray, sample, g)`` with g the integral of the sample's weighted,
    truncated Gaussian along the segment, in object units.

    A pair is evaluated in the cell that contains the point of the ray's line
    closest to the sample centre, ``m = (b - o) . d``; the intervals of one
    ray's cells partition the line (the first starts at -inf, the last ends at
    +inf), so this needs no clamping to the segment and no de-duplication.
    """
    grid = data.grid
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    t1 = np.asarray(t_exit, dtype=np.float64).reshape(-1)
    vr, vc, va, vb = _dda(grid, o, d, np.zeros(len(o)), t1)
    start = grid.cell_start[vc]
    cnt = grid.cell_start[vc + 1] - start
    keep = cnt > 0
    vr, va, vb, start, cnt = vr[keep], va[keep], vb[keep], start[keep], cnt[keep]
    total = int(cnt.sum())
    if total == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e, np.zeros(0)
    cum = np.cumsum(cnt) - cnt
    cache = _cache(data)
    idx = np.arange(total) + np.repeat(start - cum, cnt)  # positions in the cell lists
    # Ownership: b . d against the visit's interval shifted by o . d, in float32
    # from cell-ordered copies of the centres (contiguous per cell).  Equal
    # inputs give bit-equal values in every cell of a ray, and consecutive
    # intervals share their end points exactly, so each pair has one owner.
    dv = d[vr].astype(np.float32)
    bd = cache["px"].take(idx) * np.repeat(dv[:, 0], cnt)
    bd += cache["py"].take(idx) * np.repeat(dv[:, 1], cnt)
    bd += cache["pz"].take(idx) * np.repeat(dv[:, 2], cnt)
    od = np.einsum("ij,ij->i", o[vr], d[vr]).astype(np.float32)
    own = bd >= np.repeat(va.astype(np.float32) + od, cnt)
    own &= bd < np.repeat(vb.astype(np.float32) + od, cnt)
    s = cache["items"].take(idx[own])
    r = np.repeat(vr, cnt)[own]
    return chord_integrals(data, ray_arrays(data, o, d, t1), r, s)


def ray_arrays(data, o, d, t1) -> dict:
    """Per-ray inputs of :func:`chord_integrals`: coordinates about the centre of the samples, as
    separate contiguous arrays, with o . d and |o|^2."""
    c = _cache(data)
    o = np.asarray(o, dtype=np.float64) - c["origin"]
    ox, oy, oz = (np.ascontiguousarray(o[:, k]) for k in range(3))
    dx, dy, dz = (np.ascontiguousarray(d[:, k], dtype=np.float64) for k in range(3))
    return {"ox": ox, "oy": oy, "oz": oz, "dx": dx, "dy": dy, "dz": dz, "od": ox * dx + oy * dy + oz * dz,
            "o2": ox * ox + oy * oy + oz * oz, "t1": np.asarray(t1, dtype=np.float64)}


def chord_integrals(data, rays: dict, r, s):
    """g for candidate (ray, sample) pairs (each pair once): ``(ray, sample, g)`` for the pairs whose
    truncated Gaussian meets the ray segment [0, t_exit], the others dropped; ``rays`` from
    :func:`ray_arrays`.  The one implementation of the integral for both ways of finding the
    candidates (the grid walk, :func:`ray_sample_pairs`; the image-plane bins, :func:`projected_pairs`):

        g = w_i * integral_ta^tb exp(-a_i |o + t d - b_i|^2) dt
          = w_i sqrt(pi) / (2 sqrt(a_i)) exp(-a_i dp^2) [erf(sqrt(a_i) (tb - m)) - erf(sqrt(a_i) (ta - m))]

    in object units, with m = (b - o) . d the ray parameter closest to b_i, dp^2 = |b - o|^2 - m^2
    = |b|^2 - 2 b . o + |o|^2 - m^2 its squared distance (float64, coordinates about the centre of
    the samples) and [ta, tb] the chord of the truncation ball clipped to [0, t_exit].
    """
    c = _cache(data)
    bx, by, bz = c["bx"].take(s), c["by"].take(s), c["bz"].take(s)
    m = bx * rays["dx"].take(r)
    m += by * rays["dy"].take(r)
    m += bz * rays["dz"].take(r)
    m -= rays["od"].take(r)
    bo = bx * rays["ox"].take(r)
    bo += by * rays["oy"].take(r)
    bo += bz * rays["oz"].take(r)
    hc2 = c["support2"].take(s)  # R^2 - dp^2
    hc2 -= c["b2"].take(s)
    hc2 += 2.0 * bo
    hc2 -= rays["o2"].take(r)
    hc2 += m * m
    hc = np.sqrt(np.maximum(hc2, 0.0))  # half chord of the truncation ball
    u0 = np.maximum(-m, -hc)  # ta - m
    u1 = np.minimum(rays["t1"].take(r) - m, hc)  # tb - m
    k = np.flatnonzero((hc2 > 0) & (u1 > u0))
    r, s, u0, u1 = r.take(k), s.take(k), u0.take(k), u1.take(k)
    dp2 = c["support2"].take(s) - hc2.take(k)
    sa = c["sqrt_alpha"].take(s)
    g = np.exp(-c["alpha"].take(s) * dp2)
    g *= c["coef"].take(s)
    g *= erf(sa * u1) - erf(sa * u0)
    return r, s, g


def _cache(data):
    """Per-data arrays for the pair loops: int64 cell items, cell-ordered float32 centres, sample
    constants, centres about their mean as separate contiguous coordinates."""
    c = data.ray_cache.get("pairs")
    key = (id(data.centers), id(data.grid.cell_items), id(data.weight), id(data.sigma))
    if c is None or c["key"] != key:
        items = data.grid.cell_items.astype(np.int64)
        pos = data.centers[items].astype(np.float32)
        origin = data.centers.mean(axis=0) if len(data.centers) else np.zeros(3)
        b = data.centers - origin
        alpha = np.asarray(data.alpha, dtype=np.float64)
        c = {"key": key, "items": items, "px": np.ascontiguousarray(pos[:, 0]), "py": np.ascontiguousarray(pos[:, 1]),
             "pz": np.ascontiguousarray(pos[:, 2]), "support2": data.support**2, "alpha": alpha,
             "sqrt_alpha": np.sqrt(alpha),
             "coef": np.asarray(data.weight, dtype=np.float64) * 0.5 * np.sqrt(np.pi) / np.sqrt(alpha),
             "origin": origin, "bx": np.ascontiguousarray(b[:, 0]), "by": np.ascontiguousarray(b[:, 1]),
             "bz": np.ascontiguousarray(b[:, 2]), "b2": (b * b).sum(axis=1)}
        data.ray_cache["pairs"] = c
    return c


def projected_pairs(data, origins, dirs, t_exit, *, camera_position=None, view_dir=None, max_pairs: int = 1 << 16):
    """:func:`ray_sample_pairs` for rays that run away from one camera (``camera_position``, or
    along ``-view_dir``), found through image-plane bins (``projected``) instead of the grid walk:
    the same pairs and values, not sorted by ray.  None when the bins do not apply (a ray origin
    at or behind the eye plane): walk the grid then."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    t1 = np.asarray(t_exit, dtype=np.float64).reshape(-1)
    bins = ImageBins.build(o, camera_position=camera_position, view_dir=view_dir)
    if bins is None:
        return None
    cu, cv, rho = bins.project_balls(data.centers, data.support)
    live = rho >= 0
    R, S, G = [], [], []
    if live.any():
        row = 0.5 * float(np.median(rho[live]))
        ra = ray_arrays(data, o, d, t1)
        for ray, smp in expand(*bins.segments(cu, cv, rho, rho, row, disc=True), max_pairs):
            r, s, g = chord_integrals(data, ra, ray, smp)
            R.append(r)
            S.append(s)
            G.append(g)
    if not R:
        e = np.zeros(0, dtype=np.int64)
        return e, e, np.zeros(0)
    return np.concatenate(R), np.concatenate(S), np.concatenate(G)


def all_ray_sample_pairs(data, origins, dirs, t_exit, chunk: int = 2048, *, camera_position=None, view_dir=None):
    """:func:`ray_sample_pairs` over many rays in chunks, concatenated (sorted by ray); with
    ``camera_position`` / ``view_dir`` the pairs of :func:`projected_pairs` (not sorted by ray)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    t1 = np.asarray(t_exit, dtype=np.float64).reshape(-1)
    if camera_position is not None or view_dir is not None:
        pairs = projected_pairs(data, o, d, t1, camera_position=camera_position, view_dir=view_dir)
        if pairs is not None:
            return pairs
    R, S, G = [], [], []
    for c0 in range(0, len(o), chunk):
        r, s, g = ray_sample_pairs(data, o[c0 : c0 + chunk], d[c0 : c0 + chunk], t1[c0 : c0 + chunk])
        order = np.argsort(r, kind="stable")
        R.append(r[order] + c0)
        S.append(s[order])
        G.append(g[order])
    if not R:
        e = np.zeros(0, dtype=np.int64)
        return e, e, np.zeros(0)
    return np.concatenate(R), np.concatenate(S), np.concatenate(G)
