"""Brute-force reference for the same single-scattering integral (no RBFs, no SH).

For every view ray (surface point x, direction d into the object, segment
[0, t_exit]) the integral

    L(x) = integral_0^t_exit  sigma_s(x')/(4 pi) F_in exp(-tau(x', -d))
              [ sum_l E_l(x') exp(-tau_l(x')) + integral L_env(xi) exp(-tau(x', xi)) dxi ] ds

is evaluated by the midpoint rule on the view ray and, at every step, by
marching a shadow ray through the voxel field towards each light (up to the
light, for point/spot/area lights, or to the grid border) and, for the
environment, over ``env_dirs`` Fibonacci directions.  tau(x', -d) is the
depth accumulated along the view ray plus the depth from x outwards to the
grid border, like the baked optical depth (to infinity).  Steps are half a
voxel or a quarter of the shortest mean free path, whichever is shorter, and
marches stop once the optical depth exceeds 30 (exp(-30) ~ 1e-13), which
keeps dense media (marble at the scale of a bunny) affordable.  The
medium is the trilinear voxel field of :class:`~.volume.VoxelVolume` (the same
model the bake reads); Fresnel and eta conventions are those of
:mod:`.runtime` (``F_in`` at entry; the exit factor is applied by the caller), and, given the
mesh (``reference_vertices`` passes it), the world's light enters through the critical cone and after
reflections inside as in the bake (:mod:`.entry` eqs. 2-3: each march point's weights, in place of ``F_in``;
the reflected chords marched here, :func:`entered_world`).

``reference_vertices`` starts each view ray outside the surface and ends it beyond the far side by
:func:`.runtime.medium_margin`, so that it crosses the whole voxel field (its trilinear boundary ramp
lies half outside the mesh), as the RBF pass's rays do.

The result is the in-medium radiance at x, directly comparable with
:func:`.runtime.integrate_view_rays`.  Cost: rays x steps x (lights + env
directions) x shadow steps trilinear lookups; meant for tests and benches.
"""

from __future__ import annotations

import numpy as np

from ..scene import sh as shmod
from ..scene.lights import emitter_samples, light_irradiance
from .entry import WorldEntry
from .runtime import entry_transmittance
from .volume import trilinear


def _grid_exit(volume, p, w):
    """Distance from points p along unit dirs w to the grid box border."""
    lo = volume.origin
    hi = lo + np.asarray(volume.shape) * volume.h
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - p) / w
        tb = (hi - p) / w
    t = np.where(w > 0, tb, np.where(w < 0, ta, np.inf))
    return np.maximum(t.min(axis=1), 0.0)


def env_radiance(environment, directions) -> np.ndarray:
    """The world's radiance (n, 3) toward ``directions``: its constant plus its SH, clamped at zero."""
    L = np.broadcast_to(np.asarray(environment.radiance, dtype=np.float64), (len(directions), 3)).copy()
    if environment.sh is not None:
        esh = np.asarray(environment.sh, dtype=np.float64)
        L += shmod.sh_basis(np.asarray(directions, dtype=np.float64), int(round(np.sqrt(len(esh)))) - 1) @ esh
    return np.maximum(L, 0.0)


def default_step(volume) -> float:
    """Marching step (object units): half a voxel, or a quarter mean free path if that is shorter."""
    st = volume.sigma_t[volume.medium]
    st_max = float(st.max()) if st.size else 0.0
    step = 0.5 * volume.h
    if st_max > 0:
        step = min(step, 0.25 / (st_max * volume.mm_per_unit))
    return step


def march_optical_depth(volume, points, dirs, tmax=None, step=None, tau_cut: float = 30.0,
                        chunk: int = 200000) -> np.ndarray:
    """tau (n, 3) from each point along its unit dir, up to ``tmax`` / the grid border (midpoint rule).

    A ray stops early once its optical depth exceeds ``tau_cut`` in every
    channel (exp(-30) ~ 1e-13: nothing behind it can matter).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    step = default_step(volume) if step is None else float(step)
    L = _grid_exit(volume, p, w)
    if tmax is not None:
        L = np.minimum(L, np.asarray(tmax, dtype=np.float64).reshape(-1))
    out = np.zeros((len(p), 3))
    mm = volume.mm_per_unit
    for c0 in range(0, len(p), chunk):
        sl = slice(c0, min(len(p), c0 + chunk))
        Lc = L[sl]
        n = np.maximum(np.ceil(Lc / step).astype(np.int64), 1)
        ds = Lc / n
        pc, wc = p[sl], w[sl]
        acc = np.zeros((len(Lc), 3))
        act = np.arange(len(Lc))
        j = 0
        while act.size:
            x = pc[act] + ((j + 0.5) * ds[act])[:, None] * wc[act]
            acc[act] += trilinear(volume.sigma_t, volume.origin, volume.h, x) * (ds[act] * mm)[:, None]
            j += 1
            act = act[(n[act] > j) & (acc[act].min(axis=1) < tau_cut)]
        out[sl] = acc
    return out


def reference_radiance(volume, origins, dirs, t_exit, lights, environment, eta: float, *, step=None,
                       shadow_step=None, env_dirs: int = 256, tau_cut: float = 30.0,
                       chunk: int = 400000, mesh=None, bvh=None) -> np.ndarray:
    """Brute-force in-medium single-scattering radiance at each ray origin, (n_rays, 3).

    The view ray is marched from the surface point (midpoint rule, ``step``);
    its optical depth towards the viewer is accumulated along the way, on top
    of the depth from the surface point outwards to the grid border, and the
    ray stops once that depth exceeds ``tau_cut``.  Then a shadow ray is
    marched from every step to each light (and to ``env_dirs`` directions),
    all shadow rays at once (in chunks of ``chunk`` rays).  ``mesh``: ``(V, F)`` (and its ``bvh``) for the
    world's light through the critical cone and after reflections inside (:func:`entered_world`, :mod:`.entry`
    eq. 3); without it the straight model, ``F_in``.
    """
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    t1 = np.minimum(np.asarray(t_exit, dtype=np.float64).reshape(-1), _grid_exit(volume, o, d))  # inf: to the border
    step = default_step(volume) if step is None else float(step)
    mm = volume.mm_per_unit
    n_steps = np.where(t1 > 0, np.maximum(np.ceil(t1 / step).astype(np.int64), 1), 0)
    ds = np.where(n_steps > 0, t1 / np.maximum(n_steps, 1), 0.0)
    f_in = entry_transmittance(eta)
    has_env = environment is not None and not environment.is_black
    if has_env:
        W = shmod.fibonacci_directions(env_dirs)
        Lenv = env_radiance(environment, W)
    # 1. march the view rays: positions, sigma_s and the optical depth to the viewer at every step
    tau = march_optical_depth(volume, o, -d, step=shadow_step, tau_cut=tau_cut)  # surface point -> outside
    rec_r, rec_x, rec_w = [], [], []
    act = np.flatnonzero(n_steps > 0)
    j = 0
    while act.size:
        x = o[act] + ((j + 0.5) * ds[act])[:, None] * d[act]
        st = trilinear(volume.sigma_t, volume.origin, volume.h, x)
        ss = trilinear(volume.sigma_s, volume.origin, volume.h, x)
        dmm = (ds[act] * mm)[:, None]
        tv = tau[act] + 0.5 * st * dmm  # optical depth from the midpoint to the viewer
        rec_r.append(act)
        rec_x.append(x)
        rec_w.append(ss / (4.0 * np.pi) * f_in * np.exp(-tv) * dmm)  # everything but the incoming light
        tau[act] += st * dmm
        j += 1
        act = act[(n_steps[act] > j) & (tau[act].min(axis=1) < tau_cut)]
    out = np.zeros((len(o), 3))
    if not rec_r:
        return out
    R = np.concatenate(rec_r)
    X = np.concatenate(rec_x)
    Wv = np.concatenate(rec_w)
    keep = Wv.max(axis=1) > 0
    R, X, Wv = R[keep], X[keep], Wv[keep]
    # 2. shadow rays from every step: lights, then environment directions
    n_per = len(lights or ()) + (env_dirs if has_env else 0)
    if n_per == 0:
        return out
    per_chunk = max(1, chunk // n_per)
    for c0 in range(0, len(X), per_chunk):
        x = X[c0 : c0 + per_chunk]
        P = len(x)
        src, sdir, smax, weight = [], [], [], []
        for light in emitter_samples(lights):
            E, to_l, dist = light_irradiance(light, x, mm)
            src.append(x)
            sdir.append(to_l)
            smax.append(dist)
            weight.append(E)
        if has_env:
            src.append(np.repeat(x, env_dirs, axis=0))
            sdir.append(np.tile(W, (P, 1)))
            smax.append(np.full(P * env_dirs, np.inf))
            if mesh is None:
                w_env = np.tile(Lenv * (4.0 * np.pi / env_dirs), (P, 1))
            else:  # entry.py eq. 3 per march point and direction, / F_in (Wv carries F_in)
                w_env = entered_world(mesh, x, W, eta, environment, volume, bvh, shadow_step) \
                    * (4.0 * np.pi / env_dirs / f_in)
            weight.append(w_env)
        ts = march_optical_depth(volume, np.concatenate(src), np.concatenate(sdir), tmax=np.concatenate(smax),
                                 step=shadow_step, tau_cut=tau_cut)
        contrib = np.concatenate(weight) * np.exp(-ts)
        incoming = np.zeros((P, 3))
        k = 0
        for _ in lights or ():
            incoming += contrib[k : k + P]
            k += P
        if has_env:
            incoming += contrib[k:].reshape(P, env_dirs, 3).sum(axis=1)
        val = incoming * Wv[c0 : c0 + per_chunk]
        r = R[c0 : c0 + per_chunk]
        for ch in range(3):
            out[:, ch] += np.bincount(r, weights=val[:, ch], minlength=len(o))
    return out


def marched_depth(volume, step=None):
    """``depth(a, b)``: tau (m, 3) along the segments a -> b by :func:`march_optical_depth` (trilinear, midpoint
    rule at ``step``): the reference's own integral of the reflected chords and rays (the bake's and the frame's
    is :func:`.chords.segment_depth`)."""

    def depth(a, b):
        d = b - a
        t = np.linalg.norm(d, axis=1)
        return march_optical_depth(volume, a, d / np.maximum(t, 1e-300)[:, None], tmax=t, step=step)

    return depth


def entered_world(mesh, x, W, eta: float, environment, volume, bvh=None, step=None) -> np.ndarray:
    """``sum_k g_k L_world(w'_k)`` of :mod:`.entry` eq. 3 for every point of ``x`` and direction of ``W``,
    ((len(x) * len(W), 3), point-major): the world's light that comes back along each chord, through the
    critical cone and after reflections inside, per unit of the chord's own transmittance.  The reflected
    chords' depth is marched here (:func:`march_optical_depth`, trilinear, ``step``), not by the bake's
    :func:`.chords.segment_depth`."""
    entry = WorldEntry(mesh[0], mesh[1], x, eta, bvh)
    depth = marched_depth(volume, step)
    out = np.zeros((len(x), len(W), 3))
    for j, w in enumerate(np.asarray(W, dtype=np.float64)):
        for rows, g, w_out in entry.paths(w, None, None, depth):
            out[rows, j] += (g[:, None] if g.ndim == 1 else g) * env_radiance(environment, w_out)
    return out.reshape(-1, 3)


def reference_vertices(volume, V, F, normals, lights, environment, eta: float, *, camera_position=None,
                       view_dir=None, vertices=None, bvh=None, far_clip: bool = True, **kw) -> np.ndarray:
    """Outgoing radiance at vertices from the brute-force reference (same exit factor as ``render_vertices``)."""
    from ..geometry.raycast import TriangleBVH
    from .runtime import extend_rays, exit_factor, medium_margin, refract_in

    V = np.asarray(V, dtype=np.float64)
    idx = np.arange(len(V)) if vertices is None else np.asarray(vertices, dtype=np.int64)
    P = V[idx]
    if (camera_position is None) == (view_dir is None):
        raise ValueError("give exactly one of camera_position and view_dir")
    if camera_position is not None:
        wo = np.asarray(camera_position, dtype=np.float64).reshape(3) - P
    else:
        wo = np.broadcast_to(np.asarray(view_dir, dtype=np.float64).reshape(3), P.shape).copy()
    wo = wo / np.linalg.norm(wo, axis=1, keepdims=True)
    cos_o = np.einsum("ij,ij->i", np.asarray(normals)[idx], wo)
    vis = cos_o > 0
    out = np.zeros((len(V), 3))
    if not vis.any():
        return out
    d = refract_in(wo[vis], np.asarray(normals)[idx][vis], eta) if eta != 1.0 else -wo[vis]  # as the frame's rays
    if far_clip:
        bvh = bvh if bvh is not None else TriangleBVH(V, F)
        diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
        t, tri, _, _ = bvh.intersect(P[vis], d, tmin=1e-7 * diag)
        t_exit = np.where(tri >= 0, t, 0.0)
    else:
        t_exit = np.full(int(vis.sum()), np.inf)
    margin = medium_margin(volume.h)
    o, t_exit = extend_rays(P[vis], d, t_exit, margin)  # the whole voxel field's ramp
    kw.setdefault("mesh", (V, F))
    L = reference_radiance(volume, o, d, t_exit, lights, environment, eta, bvh=bvh, **kw)
    if far_clip and eta != 1.0:  # the far side's reflections (view_reflection.py eq. 1), the segments marched here
        from .entry import facet_normals
        from .runtime import ViewRays
        from .view_reflection import reflected_rays

        rays = ViewRays(n_vertices=len(V), vertices=idx[vis], origins=o, dirs=d, t_exit=t_exit, cos_o=cos_o[vis],
                        refracted=True)
        for child, weight in reflected_rays(rays, V, bvh, facet_normals(V, F), eta, marched_depth(volume), margin):
            live = weight.max(axis=1) > 0
            L[live] += weight[live] * reference_radiance(volume, child.origins[live], child.dirs[live],
                                                         child.t_exit[live], lights, environment, eta, bvh=bvh, **kw)
    out[idx[vis]] = L * exit_factor(cos_o[vis], eta)[:, None]
    return out
