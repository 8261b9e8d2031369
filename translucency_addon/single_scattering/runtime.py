"""Run-time evaluation of eq. 3, split like the GPU kernel.

    L_ss(x, w_o) ~ sum_i  k sigma_s(b_i) psi_i(w_o)                  (per sample, view)
                        * integral psi_i(xi) F_t L(b_i, xi) d xi       (per sample, lights)
                        * integral_x^y gamma_i(x') dx'                (per ray and sample)

with k = 1 / (4 pi) (isotropic phase function).  Three passes:

1. ``light_term`` (one value per sample and frame): ``sigma_s(b_i) / (4 pi) *
   F_in * [ sum_lights E_l(b_i) psi_i(toward l) + integral L_env psi_i ]``.
   ``E_l`` is the irradiance on a plane facing the light at b_i
   (``lights.light_irradiance``, W/m^2, spot cones and area cosines
   included); the environment integral is the SH dot product (uniform
   radiance L is the constant ``L sqrt(4 pi) Y_00``; an SH world adds its
   coefficients up to the order the samples hold).  A light costs one SH evaluation per sample, which is
   why the cost grows sub-linearly with the number of lights.
2. ``view_term`` (optional, one value per sample): psi_i toward the camera.
   Exact for an orthographic view (one direction); for a perspective camera
   it uses the direction from b_i to the camera, which differs from the
   direction of the rays that cross the Gaussian by at most its angular size.
   Without it ``integrate_view_rays`` evaluates psi_i at each ray's own
   direction (the GPU kernel's per-fragment form).
3. ``integrate_view_rays`` (per ray): sum over the Gaussians the ray passes of
   view psi * light term * the closed-form integral of the truncated Gaussian
   over the ray segment (erf, :func:`.ray_pairs.chord_integrals`), found through the
   uniform sample grid (:func:`.ray_pairs.ray_sample_pairs`, the GPU kernel's walk) or,
   for the rays of one camera, in the image plane (:func:`.ray_pairs.projected_pairs`).
   The rays end at the far side (``rays_from_points``: the closest hit of the
   surface's BVH, found through the same image-plane bins for one camera).

Fresnel and refraction conventions (the paper neglects the refraction of
rays; lamps' light is a straight line through the boundary here too; view rays refract where eta != 1,
:func:`refract_in`, and the far side's reflection of them is :mod:`.view_reflection`):

* **The world's entry** (:mod:`.entry`): where the bake holds ``sh_env``, light from the world comes
  back along each chord only inside the critical cone of the point where the chord leaves, eta^2 T
  times brighter (entry.py eq. 1-2); no ``F_in`` then.
* **Lamps' entry** (and the world's in data without ``sh_env``): light entering the object is scaled by ``F_in = 1 - F_dr,ext(eta)``,
  the cosine-weighted hemispherical mean of the Fresnel transmittance.  The
  bake does not store where the light reaching b_i entered, so we use the
  mean: for a sphere it is exactly the fraction of a collimated beam that
  enters (its projected area has a 2 mu d mu distribution of incidence
  cosines), and it is the transmitted fraction of diffuse light.  A beam at
  normal incidence would get F_t(1) (0.983 at eta = 1.3, against 0.939).
  No eta^2 at entry: with straight rays the irradiance (not the radiance)
  is what is carried, and it is conserved up to F_t.
* **Exit**: the in-medium radiance reaching the surface point x is returned
  by ``integrate_view_rays``; ``render_vertices`` turns it into outgoing
  radiance with ``F_t(n . w_o, eta) / eta^2``: exact Fresnel transmittance at
  the outside angle (equal to the inside one by reciprocity) and the 1/eta^2
  of radiance crossing into a less dense medium.  This is the same output
  query as the diffusion term, ``L_o = F_t J+ / (pi eta^2)``, so the two add.

psi is clamped to [0, 1] wherever it is evaluated from SH (ringing of a
truncated SH series can push it slightly outside).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import sh as shmod
from ..scene.fresnel import diffuse_reflectance_external, fresnel_transmittance, check_eta
from ..scene.lights import emitter_samples, light_irradiance
from .projected import ImageBins, exit_distances
from .ray_pairs import all_ray_sample_pairs, projected_pairs, ray_sample_pairs


def entry_transmittance(eta: float) -> float:
    """F_in = 1 - F_dr,ext(eta): the Fresnel factor applied to light entering the medium."""
    return 1.0 - diffuse_reflectance_external(check_eta(eta))


def exit_factor(cos_o, eta: float):
    """F_t(cos_o, eta) / eta^2: in-medium radiance at the surface -> outgoing radiance."""
    eta = check_eta(eta)
    c = np.asarray(cos_o, dtype=np.float64)
    return np.where(c > 0, fresnel_transmittance(c, eta), 0.0) / (eta * eta)


def eval_psi(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """psi_i(dir_i) for per-sample directions: sh (N, K, 3), dirs (N, 3) -> (N, 3), clamped to [0, 1]."""
    K = sh.shape[1]
    order = int(round(np.sqrt(K))) - 1
    Y = shmod.sh_basis(dirs, order).astype(np.float32)
    return np.clip(np.einsum("nk,nkc->nc", Y, np.asarray(sh, dtype=np.float32)), 0.0, 1.0).astype(np.float64)


ETA_MATCH = 1e-6  # light_term: sh_env serves an eta this close to the one it was baked for


def light_term(data, lights, environment, eta: float, mm_per_unit: float | None = None) -> np.ndarray:
    """Per-sample light factor (N, 3): sigma_s/(4 pi) * (F_in sum_l E_l psi_i(to l) + world).

    The world's light enters through the critical cone (:mod:`.entry` eq. 2): its SH against ``sh_env``,
    where the data holds them for this ``eta``; else (eta 1, or data of format 1, whose key is stale) the
    straight chords, ``F_in`` times its SH against psi's own.  Units: W/m^2 per mm; times the ray integral
    of the Gaussians (mm) it is radiance.
    """
    mm = data.mm_per_unit if mm_per_unit is None else float(mm_per_unit)
    b = data.centers
    f_in = entry_transmittance(eta)
    acc = np.zeros((len(b), 3))
    for light in emitter_samples(lights):
        E, to_light, _ = light_irradiance(light, b, mm)
        if not np.any(E > 0):
            continue
        acc += E * eval_psi(data.sh, to_light)
    acc *= f_in
    if environment is not None and not environment.is_black:
        sh_env = getattr(data, "sh_env", None)
        # the baked eta, to Blender's float32 (the add-on's 1.3 is 1.2999999523; a CLI gets "1.3")
        if sh_env is not None and abs(float(getattr(data, "entry_eta", 1.0)) - float(eta)) <= ETA_MATCH:
            sh, scale = sh_env, 1.0
        else:
            sh, scale = data.sh, f_in
        env = np.zeros((len(b), 3))
        L = np.asarray(environment.radiance, dtype=np.float64)
        env += L[None, :] * np.sqrt(4.0 * np.pi) * sh[:, 0, :]
        if environment.sh is not None:  # (k, 3) radiance coefficients, k = 1, 4, 9, 16 or 25
            esh = np.asarray(environment.sh, dtype=np.float64)
            k = min(len(esh), sh.shape[1])  # psi is stored up to its order only
            env += np.einsum("nkc,kc->nc", sh[:, :k, :], esh[:k])
        acc += scale * np.maximum(env, 0.0)
    return data.sigma_s / (4.0 * np.pi) * acc


def view_term(data, camera_position=None, view_dir=None) -> np.ndarray:
    """psi_i toward the viewer, (N, 3): from b_i to ``camera_position``, or along ``view_dir``.

    ``view_dir`` points from the object *to* the (orthographic) camera.
    """
    if (camera_position is None) == (view_dir is None):
        raise ValueError("give exactly one of camera_position and view_dir")
    if view_dir is not None:
        w = np.asarray(view_dir, dtype=np.float64).reshape(3)
        w = np.broadcast_to(w / np.linalg.norm(w), data.centers.shape)
    else:
        w = np.asarray(camera_position, dtype=np.float64).reshape(3) - data.centers
        w = w / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-300)
    return eval_psi(data.sh, w)


def pair_psi_weights(data, pairs, dirs) -> np.ndarray:
    """``psi_i(-dir_r) g`` per ray-sample pair ``(r, s, g)`` of rays ``dirs`` (n_pairs, 3) float32: the part of
    :func:`integrate_view_rays`' sum without a view term that the lights do not change, kept with the pairs
    (:class:`CPUIntegrator`) so that a frame that moves only the lights is one weighted sum, as it is with a
    view term (measured on the bunny, refracted rays: a lights-only frame 0.7 s -> tens of ms)."""
    r, s, g = pairs
    Y, sh32 = _psi_basis(data, dirs)
    out = np.empty((len(r), 3), dtype=np.float32)
    for p0 in range(0, len(r), 1 << 15):  # bounds the per-pair SH memory
        sl = slice(p0, p0 + (1 << 15))
        out[sl] = _pair_psi(Y, sh32, r[sl], s[sl], g[sl])
    return out


def _psi_basis(data, dirs):
    """``(Y, sh)`` in float32: the SH basis at each ray's reversed direction (towards its origin) and the
    samples' psi coefficients, what :func:`_pair_psi` reads."""
    order = int(round(np.sqrt(data.sh.shape[1]))) - 1
    Y = shmod.sh_basis(-np.asarray(dirs, dtype=np.float64).reshape(-1, 3), order).astype(np.float32)
    return Y, np.asarray(data.sh, dtype=np.float32)


def _pair_psi(Y, sh32, r, s, g) -> np.ndarray:
    """``psi_s(-dir_r) g`` for ray-sample pairs, (m, 3): psi from the SH, clamped to [0, 1]."""
    return np.clip(np.einsum("pk,pkc->pc", Y[r], sh32[s]), 0.0, 1.0) * g[:, None]


def integrate_view_rays(data, light_term, origins, dirs, t_exit, mm_per_unit: float | None = None, *,
                        view_term=None, chunk: int = 2048, pairs=None, camera_position=None,
                        view_dir=None, pair_weights=None, compiled: bool | None = None) -> np.ndarray:
    """In-medium single-scattering radiance arriving at each ray origin, (n_rays, 3).

    ``origins`` are surface points (mesh vertices), ``dirs`` unit directions
    *into* the object (minus the view direction) and ``t_exit`` the distance
    to the far side (object units).  ``light_term`` comes from
    :func:`light_term`; ``view_term`` (N, 3) from :func:`view_term`, or None to
    evaluate psi_i at each ray's own direction.  ``pairs``: the output of
    :func:`ray_sample_pairs` / :func:`all_ray_sample_pairs` for these rays (all of
    them at once), to skip the geometry when only the lights changed.
    ``camera_position`` / ``view_dir``: the camera the rays run away from (as given to
    :func:`view_rays`); the pairs are then found in the image plane (:func:`projected_pairs`)
    rather than by the grid walk that the GPU kernel does (same pairs, same sum).
    ``pair_weights``: :func:`pair_psi_weights` of ``pairs`` (without a view term: the same sum, in float32).
    ``compiled``: the sums over the pairs in one compiled pass (:mod:`.pair_kernels`; the same as numpy's
    ``bincount`` bit for bit, 3-5x faster: 356k pairs of the bottle of wine 5.6 -> 1.4 ms) -- None where
    numba runs, False for numpy, True to require it.

    Result = mm_per_unit * sum_i psi_i(-dir) * light_term_i * integral gamma_i.
    """
    mm = data.mm_per_unit if mm_per_unit is None else float(mm_per_unit)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    t1 = np.asarray(t_exit, dtype=np.float64).reshape(-1)
    n = len(o)
    out = np.zeros((3, n))
    LT = np.asarray(light_term, dtype=np.float64)
    A = np.ascontiguousarray((LT * np.asarray(view_term, dtype=np.float64)).T) if view_term is not None else None
    Y = sh32 = None
    if A is None and pair_weights is None:  # psi toward the viewer (= -dir) per ray, from the SH
        Y, sh32 = _psi_basis(data, d)

    kernels = _pair_kernels() if compiled is not False else {"error": "turned off"}
    if compiled is True and "error" in kernels:
        raise RuntimeError(f"the compiled pair sums cannot run: {kernels['error']}")
    fast = "error" not in kernels

    def accumulate(r, s, g):
        if A is not None:
            if fast:
                kernels["view"](r, s, np.asarray(g, dtype=np.float64), A, out)
                return
            for ch in range(3):
                out[ch] += np.bincount(r, weights=A[ch].take(s) * g, minlength=n)
            return
        if pair_weights is not None:  # psi_i(-dir) g per pair, kept with the pairs (pair_psi_weights)
            if fast:
                kernels["weighted"](r, s, np.ascontiguousarray(LT), pair_weights, out)
                return
            for ch in range(3):
                out[ch] += np.bincount(r, weights=LT[:, ch].take(s) * pair_weights[:, ch], minlength=n)
            return
        for p0 in range(0, len(r), 1 << 15):  # bounds the per-pair SH memory
            rr, ss, gg = r[p0 : p0 + (1 << 15)], s[p0 : p0 + (1 << 15)], g[p0 : p0 + (1 << 15)]
            val = LT[ss] * _pair_psi(Y, sh32, rr, ss, gg)
            for ch in range(3):
                out[ch] += np.bincount(rr, weights=val[:, ch], minlength=n)

    if pair_weights is not None and (pairs is None or len(pair_weights) != len(pairs[0])):
        raise ValueError("pair_weights belong to the pairs given with them")
    if pairs is None and (camera_position is not None or view_dir is not None):
        pairs = projected_pairs(data, o, d, t1, camera_position=camera_position, view_dir=view_dir)
    if pairs is not None:
        accumulate(*pairs)
        return out.T * mm
    for c0 in range(0, n, chunk):
        m = min(chunk, n - c0)
        r, s, g = ray_sample_pairs(data, o[c0 : c0 + m], d[c0 : c0 + m], t1[c0 : c0 + m])
        accumulate(r + c0, s, g)
    return out.T * mm


_PAIR_KERNELS: dict = {}


def _pair_kernels() -> dict:
    """The compiled pair sums (:mod:`.pair_kernels`), or ``{"error": why}`` where numba cannot run them."""
    from ..compiled import load_kernels

    def load():
        from . import pair_kernels as k

        one = np.zeros(1, dtype=np.int64)
        out = np.zeros((3, 1))
        k.sum_view(one, one, np.ones(1), np.ones((3, 1)), out)
        k.sum_weighted(one, one.astype(np.int32), np.ones((1, 3)), np.ones((1, 3), dtype=np.float32), out)
        return {"view": k.sum_view, "weighted": k.sum_weighted}

    return load_kernels(_PAIR_KERNELS, load, "the view rays' pair sums")


@dataclass
class ViewRays:
    """The view rays of the front-facing vertices for one camera pose (reusable while it stays)."""

    n_vertices: int
    vertices: np.ndarray  # (n,) indices of the evaluated (front-facing) vertices
    origins: np.ndarray  # (n, 3)
    dirs: np.ndarray  # (n, 3) into the object
    t_exit: np.ndarray  # (n,)
    cos_o: np.ndarray  # (n,) n . w_o
    camera_position: np.ndarray | None = None  # None where the rays are refracted (not through one camera)
    view_dir: np.ndarray | None = None
    pairs: tuple | None = None  # cached ray_sample_pairs (per baked data)
    pairs_key: int | None = None
    pair_weights: np.ndarray | None = None  # pair_psi_weights of the cached pairs (kept without a view term)
    refracted: bool = False  # bent into the medium at their vertex (eta != 1): psi is evaluated per ray


def medium_margin(voxel_size: float) -> float:
    """How far the baked medium reaches beyond the mesh's surface (object units): 2 voxels.

    The voxel model (:mod:`.volume`) is the trilinear interpolation of voxel-centre values, so its
    boundary is a ramp about one voxel wide centred on the surface: half of the medium's first layer lies
    outside the mesh, and the Gaussians fitted to it reach their truncation radius (1.6 voxels at the
    default settings) beyond their centres.  A view ray that starts at the vertex misses that half of the
    ramp -- and with it the most strongly lit layer: a 10 mm sphere of a dark medium (albedo 0.2, eta 1,
    48 voxels) returned 12 % less than the exact single scattering of the same sphere (a random walk),
    7.5 % of it the brute-force integral of the voxel field itself.  Started 2 voxels outside (and ended
    2 beyond the far side) the rays cross the whole baked medium: +0.9 % against the walk, and 2, 3 or 5
    voxels change the sum by < 0.03 % (docs/accuracy.md, "Media where diffusion fails").
    """
    return 2.0 * max(float(voxel_size), 0.0)


def extend_rays(o, d, t_exit, margin: float):
    """Rays moved ``margin`` back out of the object and lengthened by it at both ends."""
    if margin <= 0 or len(o) == 0:
        return o, t_exit
    t = np.asarray(t_exit, dtype=np.float64)
    return o - d * margin, np.where(np.isfinite(t) & (t > 0), t + 2.0 * margin, t)


def view_rays(V, F, normals, *, camera_position=None, view_dir=None, view_dirs=None, vertices=None, bvh=None,
              far_clip: bool = True, margin: float = 0.0, eta: float = 1.0) -> ViewRays:
    """Rays from the front-facing vertices into the object, clipped at the far side by a BVH cast.

    Exactly one of ``camera_position`` (perspective), ``view_dir``
    (orthographic; from the object to the camera) or ``view_dirs`` (one
    direction to the viewer per vertex, (n_vertices, 3)).  ``far_clip=False``
    skips the BVH cast and integrates to infinity, as the paper's renderer
    does (it clips only against the depth of the visible surface): Gaussians
    lie inside the object, so this differs only by the tails beyond the far
    side and by re-entries of concave shapes, and costs no ray cast.
    """
    from ..geometry.raycast import mesh_bvh

    V = np.asarray(V, dtype=np.float64)
    if far_clip and bvh is None:
        bvh = mesh_bvh(V, F)
    return rays_from_points(V, normals, camera_position=camera_position, view_dir=view_dir, view_dirs=view_dirs,
                            points=vertices, bvh=bvh if far_clip else None, margin=margin, eta=eta)


def refract_in(wo, normals, eta: float) -> np.ndarray:
    """The directions inside the medium of view rays that leave it towards ``wo`` (unit, (n, 3), towards the
    viewer) through surfaces of outward ``normals`` (normalised here) with outside cosine ``n . wo`` > 0:
    Snell's law (:func:`..scene.fresnel.refract_into`, as the lamps' beams enter)."""
    from ..scene.fresnel import refract_into

    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return refract_into(wo, n, eta)[0]


def rays_from_points(P, normals, *, camera_position=None, view_dir=None, view_dirs=None, points=None,
                     bvh=None, margin: float = 0.0, eta: float = 1.0) -> ViewRays:
    """View rays from arbitrary surface points ``P`` with ``normals`` (e.g. the vertices of a
    mesh other than the baked one): like :func:`view_rays`, clipped by ``bvh`` (a
    :class:`~translucency_addon.geometry.raycast.TriangleBVH` of the baked surface) or, when it is
    None, integrated to infinity.  ``points`` restricts the rays to a subset of indices.
    ``margin`` (object units, :func:`medium_margin` of the bake): each ray starts that far outside
    the surface and ends that far beyond the far side, so it crosses the whole baked medium.
    ``eta`` != 1: each ray is refracted into the medium at its point (:func:`refract_in`, the point's normal),
    as light that leaves towards the viewer was travelling inside; the rays then do not pass through one
    camera (``ViewRays.refracted``), so their far side is found by the BVH and psi is evaluated per ray.
    (With eta = 1, or as the paper does, the rays go straight through the boundary.)
    """
    P_all = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    N = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if sum(x is not None for x in (camera_position, view_dir, view_dirs)) != 1:
        raise ValueError("give exactly one of camera_position, view_dir and view_dirs")
    idx = np.arange(len(P_all)) if points is None else np.asarray(points, dtype=np.int64).reshape(-1)
    P = P_all[idx]
    cam = vd = None
    if camera_position is not None:
        cam = np.asarray(camera_position, dtype=np.float64).reshape(3)
        wo = cam - P
    elif view_dir is not None:
        vd = np.asarray(view_dir, dtype=np.float64).reshape(3)
        vd = vd / np.linalg.norm(vd)
        wo = np.broadcast_to(vd, P.shape).copy()
    else:
        wo = np.asarray(view_dirs, dtype=np.float64).reshape(len(P_all), 3)[idx]
    wo = wo / np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-300)
    cos_o = np.einsum("ij,ij->i", N[idx], wo)
    vis = cos_o > 0
    o = P[vis]
    refracted = float(eta) != 1.0
    d = refract_in(wo[vis], N[idx][vis], float(eta)) if refracted else -wo[vis]
    if refracted:
        cam = vd = None
    if len(o) and bvh is None:
        t_exit = np.full(len(o), np.inf)
    elif len(o):
        lo, hi = P_all.min(axis=0), P_all.max(axis=0)
        tmin = 1e-7 * max(float(np.linalg.norm(hi - lo)), 1e-30)
        bins = None if view_dirs is not None or refracted else ImageBins.build(o, camera_position=cam, view_dir=vd)
        if bins is not None:  # the BVH's closest hits, found through image-plane bins (``projected``)
            t = exit_distances(bins, bvh.V, bvh.F, o, d, tmin)
            t_exit = np.where(np.isfinite(t), t, 0.0)
        else:
            t, tri, _, _ = bvh.intersect(o, d, tmin=tmin)
            t_exit = np.where(tri >= 0, t, 0.0)
    else:
        t_exit = np.zeros(0)
    o, t_exit = extend_rays(o, d, t_exit, float(margin))
    return ViewRays(n_vertices=len(P_all), vertices=idx[vis], origins=o, dirs=d, t_exit=t_exit, cos_o=cos_o[vis],
                    camera_position=cam, view_dir=vd, refracted=refracted)


class CPUIntegrator:
    """The per-ray pass in numpy, with the interface of the GPU kernel's dispatcher
    (``gpu_shaders.single_scattering.GPUSingleScattering``).

    ``cache_pairs``: keep the ray-sample pairs of the last ``rays`` (in
    ``rays.pairs``), so that a frame in which only the lights changed costs one
    weighted sum; pairs of rays with more than ``max_cached_pairs`` entries are
    not kept (memory: 24 bytes per pair).
    """

    backend = "CPU"
    last_backend = "CPU"
    message = ""

    def __init__(self, data, cache_pairs: bool = True, max_cached_pairs: int = 8_000_000, chunk: int = 2048):
        self.data = data
        self.cache_pairs = bool(cache_pairs)
        self.max_cached_pairs = int(max_cached_pairs)
        self.chunk = int(chunk)

    def integrate(self, light_term, rays, *, view_term=None, eta: float, mm_per_unit: float | None = None,
                  use_gpu: bool = True) -> np.ndarray:
        """Outgoing radiance per ray of ``rays`` (:class:`ViewRays`), (n_rays, 3), W/(m^2 sr).

        ``light_term`` from :func:`light_term`; ``view_term`` from
        :func:`view_term` or None (psi at each ray's own direction).
        ``use_gpu`` is ignored (interface of the GPU dispatcher).
        """
        mm = self.data.mm_per_unit if mm_per_unit is None else float(mm_per_unit)
        if len(rays.origins) == 0:
            return np.zeros((0, 3))
        pairs = None
        if self.cache_pairs:
            key = id(self.data)
            if rays.pairs is None or rays.pairs_key != key:
                pairs = all_ray_sample_pairs(self.data, rays.origins, rays.dirs, rays.t_exit, self.chunk,
                                             camera_position=rays.camera_position, view_dir=rays.view_dir)
                if len(pairs[0]) <= self.max_cached_pairs:
                    rays.pairs, rays.pairs_key, rays.pair_weights = pairs, key, None
            else:
                pairs = rays.pairs
        weights = None
        if view_term is None and pairs is not None and rays.pairs is pairs:  # kept: psi per pair, once
            if rays.pair_weights is None:
                rays.pair_weights = pair_psi_weights(self.data, pairs, rays.dirs)
            weights = rays.pair_weights
        Lin = integrate_view_rays(self.data, light_term, rays.origins, rays.dirs, rays.t_exit, mm,
                                  view_term=view_term, chunk=self.chunk, pairs=pairs,
                                  camera_position=rays.camera_position, view_dir=rays.view_dir, pair_weights=weights)
        return Lin * exit_factor(rays.cos_o, eta)[:, None]

    def free(self) -> None:
        pass


def render_vertices(data, V, F, normals, lights, environment, material, mm_per_unit: float | None = None, *,
                    camera_position=None, view_dir=None, view_dirs=None, vertices=None, bvh=None, rays=None,
                    far_clip: bool = True, per_ray_psi: bool = False, cache_pairs: bool = False,
                    chunk: int = 2048) -> np.ndarray:
    """Outgoing single-scattering radiance at mesh vertices, (n_vertices, 3), W/(m^2 sr).

    The viewer is given by exactly one of ``camera_position`` (perspective),
    ``view_dir`` (orthographic; points from the object to the camera) or
    ``view_dirs`` (one direction to the viewer per vertex), or by ``rays``
    from :func:`view_rays` (reused while the camera stays; with
    ``cache_pairs`` the ray-sample pairs are kept in it too, so that a frame
    in which only the lights changed costs the light term and one weighted
    sum).  Vertices facing away from the viewer get 0.  ``vertices``
    restricts the evaluation to a subset of vertex indices (e.g. a decimated
    set); the others get 0.  ``far_clip``: see :func:`view_rays`.  ``material`` is a
    :class:`~translucency_addon.scene.materials.Material` (for eta) or eta itself.
    The exit factor is ``F_t(n . w_o, eta) / eta^2``.  psi_i toward the viewer
    is evaluated per sample (toward the camera) unless ``per_ray_psi`` or
    ``view_dirs`` ask for each ray's own direction, or the rays are refracted (eta != 1: then also the far
    side's reflection of them, :mod:`.view_reflection`, where the data keeps its extinction voxels).
    """
    eta = float(getattr(material, "eta", material))
    mm = data.mm_per_unit if mm_per_unit is None else float(mm_per_unit)
    if rays is None:
        rays = view_rays(V, F, normals, camera_position=camera_position, view_dir=view_dir, view_dirs=view_dirs,
                         margin=medium_margin(data.voxel_size),
                         vertices=vertices, bvh=bvh, far_clip=far_clip, eta=eta)
    out = np.zeros((rays.n_vertices, 3))
    if len(rays.vertices) == 0:
        return out
    LT = light_term(data, lights, environment, eta, mm)
    VT = None
    if not per_ray_psi and (rays.camera_position is not None or rays.view_dir is not None):
        VT = view_term(data, camera_position=rays.camera_position, view_dir=rays.view_dir)
    pairs = None
    if cache_pairs:
        key = id(data)
        if rays.pairs is None or rays.pairs_key != key:
            rays.pairs = all_ray_sample_pairs(data, rays.origins, rays.dirs, rays.t_exit, chunk,
                                              camera_position=rays.camera_position, view_dir=rays.view_dir)
            rays.pairs_key = key
        pairs = rays.pairs
    Lin = integrate_view_rays(data, LT, rays.origins, rays.dirs, rays.t_exit, mm, view_term=VT, chunk=chunk,
                              pairs=pairs, camera_position=rays.camera_position, view_dir=rays.view_dir)
    if far_clip and rays.refracted:  # the view rays' reflections inside, view_reflection.py
        from ..geometry.raycast import mesh_bvh
        from .entry import facet_normals
        from .view_reflection import reflected_rays_of

        V = np.asarray(V, dtype=np.float64)
        tree = bvh if bvh is not None else mesh_bvh(V, F)
        for child, weight in reflected_rays_of(data, rays, V, tree, facet_normals(V, F), eta):
            Lin = Lin + weight * integrate_view_rays(data, LT, child.origins, child.dirs, child.t_exit, mm,
                                                     chunk=chunk)
    out[rays.vertices] = Lin * exit_factor(rays.cos_o, eta)[:, None]
    return out
