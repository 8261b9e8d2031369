"""Run time of the Voxel Number Map (Mochida et al., run-time steps 1-2): lights -> radiance per vertex.

Per frame (eq. numbers of :mod:`.transport`):

1. **Irradiance maps.**  For every light and surface voxel: the irradiance on
   a plane facing the light (``lights.light_irradiance``), the incidence
   mu = n . w_light, shadow rays against the outer mesh and the scene's
   occluders (``lights.shadow_visibility``; cached per light pose), the Fresnel
   transmittance F_t(mu): the fluence Phi = F_t E_perp, clamped so that no
   voxel returns more than it took in.  A world (uniform or SH) adds the same
   per baked sky direction, with the bake's sky visibility.
2. **Transport.**  ``J+ = S (A Phi) + rho(mu) Phi`` (eq. 6): one packed
   symmetric matrix-vector product per channel -- BLAS ``sspmv`` on the CPU,
   the ``voxel_number_map.glsl`` kernel on a GPU (``gpu_shaders``), which reads
   the fp16 LUT directly -- plus the near-entry term.
3. **Output.**  J+ is carried to the outer mesh's vertices with the bake's
   vertex weights and leaves as ``L_o = F_t(n . w_o) J+ / (pi eta^2)``
   (eq. 7, ``radiance.outgoing_radiance``: the diffusion pass's own query, so
   the passes add in the same attribute, overlay and AOV).

Views are those of :class:`~translucency_addon.single_scattering.FrameEvaluator`:
``None`` (each vertex seen along its normal), ``("PERSP", eye)`` or
``("ORTHO", towards_camera)``; only the Fresnel factor of the exit depends on
it.
"""

from __future__ import annotations

import time

import numpy as np

from ..scene.fresnel import fresnel_transmittance
from ..scene.lights import emitter_samples, light_irradiance, shadow_visibility
from ..diffusion.radiance import outgoing_radiance
from .transport import Coefficients, environment_weights, prepare_kernel


def _light_key(light) -> tuple:
    return (light.kind, tuple(np.round(light.position, 9)), tuple(np.round(light.unit_direction, 9)))


class VoxelNumberMapEvaluator:
    """Radiance of one baked :class:`~.bake.VoxelNumberMap` for one material, frame after frame.

    ``material``: the outer part's :class:`~translucency_addon.scene.materials.Material`
    (the inner media come from the bake).  ``transmission``: an object with
    ``product(x) -> (n, 3)`` and ``set_coefficients(coef)`` running step 2 on
    another backend (``gpu_shaders.voxel_number_map``); None: numpy/BLAS.
    """

    def __init__(self, vnm, material, *, mm_per_unit: float | None = None, transmission=None):
        from ..geometry.raycast import mesh_bvh

        self.vnm = vnm
        self.mm_per_unit = float(vnm.mm_per_unit if mm_per_unit is None else mm_per_unit)
        self.bvh = mesh_bvh(vnm.mesh_vertices, vnm.mesh_faces)
        self.diag = float(np.linalg.norm(np.ptp(vnm.mesh_vertices, axis=0)))
        self.transmission = transmission
        self._shadows: dict = {}
        self._occluders = None
        self.seconds: dict = {}
        self.set_material(material)

    @property
    def backend(self) -> str:
        return "CPU" if self.transmission is None else getattr(self.transmission, "backend", "GPU")

    def set_material(self, material) -> None:
        """Coefficients of every component medium -> the packed kernel, rho tables, environment weights."""
        t0 = time.perf_counter()
        sa, ss = self.vnm.coefficients(material)
        self.material = material
        self.eta = float(material.eta)
        self.coef = Coefficients(sigma_t=sa + ss, sigma_s=ss, h_mm=self.vnm.h * self.mm_per_unit)
        self.kernel = prepare_kernel(self.vnm.surface, self.vnm.lengths, self.vnm.blocked, self.coef)
        self.env_w = self.env_phi = self.env_local = None
        if len(self.vnm.env_directions):
            w, phi, local = environment_weights(self.kernel, self.vnm.surface.normal, self.vnm.visible(),
                                                self.vnm.env_directions, self.eta)
            mu = np.clip(self.vnm.surface.normal @ self.vnm.env_directions.T, 0.0, 1.0)
            self.env_w = w * mu  # irradiance that enters per unit radiance (power accounting only)
            # (3, n, D) per channel: a frame's world term is one (n, D) x (D,) product per channel
            self.env_phi = np.ascontiguousarray(np.moveaxis(phi, 2, 0))
            self.env_local = np.ascontiguousarray(np.moveaxis(local, 2, 0))
        if self.transmission is not None:
            self.transmission.set_coefficients(self.coef)
        self.seconds = {"prepare": time.perf_counter() - t0}

    # -- step 1 ---------------------------------------------------------------------------------
    def _shadow_bvh(self, occluders):
        from ..geometry.raycast import TriangleBVH, content_key

        if occluders is None:
            return self.bvh, None
        if isinstance(occluders, TriangleBVH):
            return occluders, id(occluders)
        Vo, Fo = (np.ascontiguousarray(a) for a in occluders)
        key = content_key(Vo, Fo)
        if self._occluders is None or self._occluders[0] != key:
            V = np.vstack([self.vnm.mesh_vertices, Vo])
            F = np.vstack([self.vnm.mesh_faces, np.asarray(Fo) + len(self.vnm.mesh_vertices)])
            self._occluders = (key, TriangleBVH(V, F))
        return self._occluders[1], key

    def visibility(self, light, to_light, dist, lit, occluders=None) -> np.ndarray:
        """Shadow rays of the lit voxels towards ``light``, cached per light pose and occluder set."""
        bvh, okey = self._shadow_bvh(occluders)
        key = (_light_key(light), okey)
        vis = self._shadows.get(key)
        if vis is None:
            surf = self.vnm.surface
            vis = np.zeros(surf.n, dtype=bool)
            idx = np.flatnonzero(lit)
            if idx.size:
                test = shadow_visibility(bvh, offset=1e-4 * self.diag)
                vis[idx] = test(surf.position[idx], surf.normal[idx], to_light[idx], dist[idx])
            if len(self._shadows) > 64:
                self._shadows.clear()
            self._shadows[key] = vis
        return vis

    def sources(self, lights=(), environment=None, *, shadows: bool = True, occluders=None, rest=None):
        """``(x, local, E)`` per surface voxel (n, 3): x = A Phi (clamped) for the transport product, the
        near-entry exitance rho(mu) Phi, and the irradiance that entered, E = F_t mu E_perp (W/m^2;
        for the power balance).  ``rest``: a :class:`_RestKernel`, whose near-entry exitance (the same
        clamped Phi) then takes the place of ``local``."""
        surf = self.vnm.surface
        n = surf.n
        phi = np.zeros((n, 3))
        local = np.zeros((n, 3))
        E_in = np.zeros((n, 3))
        near = self.kernel if rest is None else rest.kernel
        for light in emitter_samples(lights):
            E, to_light, dist = light_irradiance(light, surf.position, self.mm_per_unit)
            mu = np.einsum("ij,ij->i", surf.normal, to_light)
            lit = (mu > 0) & np.any(E > 0, axis=1)
            if shadows and lit.any():
                lit &= self.visibility(light, to_light, dist, lit, occluders)
            if not lit.any():
                continue
            mu_l = np.where(lit, np.clip(mu, 0.0, 1.0), 0.0)
            fl = E * np.where(lit, fresnel_transmittance(mu_l, self.eta), 0.0)[:, None]
            E_in += fl * mu_l[:, None]
            rho = self.kernel.rho_at(mu_l)
            fl = fl * self.kernel.clamp(mu_l, rho)
            phi += fl
            local += fl * (rho if rest is None else near.rho_at(mu_l))
        if environment is not None and not environment.is_black and self.env_phi is not None:
            L = environment.radiance_at(self.vnm.env_directions)  # (D, 3)
            env_local = self.env_local if rest is None else rest.env_local
            for c in range(3):
                phi[:, c] += self.env_phi[c] @ L[:, c]
                local[:, c] += env_local[c] @ L[:, c]
            E_in += self.env_w @ L
        return surf.area[:, None] * phi, local, E_in

    # -- step 2 ---------------------------------------------------------------------------------
    def exitance(self, lights=(), environment=None, *, shadows: bool = True, occluders=None) -> np.ndarray:
        """J+ at every surface voxel (n, 3), W/m^2 (eq. 6)."""
        t0 = time.perf_counter()
        x, local, _ = self.sources(lights, environment, shadows=shadows, occluders=occluders)
        t1 = time.perf_counter()
        if self.transmission is not None:
            J = self.transmission.product(x)
        else:
            J = self.kernel.product(x)
        t2 = time.perf_counter()
        self.seconds.update({"lights": t1 - t0, "transport": t2 - t1})
        return J + local

    # -- step 3 ---------------------------------------------------------------------------------
    def radiance(self, lights=(), environment=None, view=None, *, shadows: bool = True, occluders=None,
                 points=None):
        """Outgoing radiance (W/(m^2 sr)) at the outer mesh's vertices, (n_vertices, 3).

        ``points``: ``(P, N)``, other points on the outer surface (object units) and their unit
        normals -- the vertices of a mesh whose vertex count a modifier changed -- to get the
        radiance there instead, (len(P), 3); they are mapped to the surface voxels as the mesh's
        vertices are (:func:`.surface.vertex_weights`, cached for the last point set).
        """
        t0 = time.perf_counter()
        J = self.exitance(lights, environment, shadows=shadows, occluders=occluders)
        self._last = (list(lights), environment, shadows, occluders, view, points)
        t1 = time.perf_counter()
        L = self._outgoing(J, view, points)
        t2 = time.perf_counter()
        self.seconds.update({"output": t2 - t1, "total": t2 - t0})
        return L

    def _outgoing(self, J, view, points):
        """Eq. 7 at the vertices (or ``points``) seen from ``view``."""
        if points is None:
            (idx, w), V, N = self.vnm.vertex_map, self.vnm.mesh_vertices, self.vnm.mesh_normals
        else:
            V, N = (np.asarray(a, dtype=np.float64) for a in points)
            idx, w = self._point_map(V, N)
        j_v = np.einsum("vk,vkc->vc", np.asarray(w, dtype=np.float64), J[np.asarray(idx)])
        if view is None:
            cos_o = np.ones(len(V))
        elif view[0] == "ORTHO":
            d = np.asarray(view[1], dtype=np.float64)
            cos_o = N @ (d / np.linalg.norm(d))
        else:
            d = np.asarray(view[1], dtype=np.float64)[None, :] - V
            cos_o = np.einsum("ij,ij->i", N, d) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        return outgoing_radiance(j_v, cos_o, self.eta)

    # -- the orders after the first of several media (frame.orders_after_the_first eq. 1) ------------
    def rest_media(self) -> np.ndarray | None:
        """(C, 3) albedo of each component medium where the scattering ones differ (a bottle's glass and
        wine), else None (one albedo: the frame takes the surface's)."""
        st, ss = self.coef.sigma_t, self.coef.sigma_s
        a = np.divide(ss, st, out=np.zeros_like(ss), where=st > 0)
        scattering = np.any(ss > 0, axis=1)
        if scattering.sum() < 2 or not np.any(np.ptp(a[scattering], axis=0) > 1e-4):
            return None
        return a

    def weighted_radiance(self, weights) -> np.ndarray:
        """The last :meth:`radiance` with each component's sigma_s times ``weights`` (C, 3) where the light
        scatters -- the kernel's tau_s and the near-entry albedo (eqs. 4-6); the same entering fluence Phi,
        chords' extinction and exit.  A second packed kernel per material and weights (built once, BLAS)."""
        last = getattr(self, "_last", None)
        if last is None:
            raise RuntimeError("weighted_radiance follows a radiance() call")
        lights, environment, shadows, occluders, view, points = last
        w = np.asarray(weights, dtype=np.float64)
        key = (w.tobytes(), id(self.coef))
        rest = getattr(self, "_rest", None)
        if rest is None or rest.key != key:
            rest = self._rest = _RestKernel(self, w, key)
        x, local, _ = self.sources(lights, environment, shadows=shadows, occluders=occluders, rest=rest)
        return self._outgoing(rest.kernel.product(x) + local, view, points)

    def _point_map(self, V: np.ndarray, N: np.ndarray):
        from .surface import vertex_weights

        key = (V.shape, hash(V.tobytes()), hash(N.tobytes()))
        cached = getattr(self, "_points", None)
        if cached is None or cached[0] != key:
            k = int(np.asarray(self.vnm.vertex_map[0]).shape[1])
            cached = self._points = (key, vertex_weights(V, N, self.vnm.surface, k))
        return cached[1]

    def power(self, J: np.ndarray, E_in: np.ndarray) -> dict:
        """Power (W per channel) that entered (``E_in`` from :meth:`sources`) and that leaves through the
        boundary, ``(1 - F_dr,int) J+`` over the surface voxels."""
        from ..scene.fresnel import diffuse_reflectance_internal

        a = self.vnm.surface.area * (self.mm_per_unit * 1e-3) ** 2
        return {"in": a @ E_in, "out": (1.0 - diffuse_reflectance_internal(self.eta)) * (a @ J)}

    def free(self) -> None:
        free = getattr(self.transmission, "free", None)
        if callable(free):
            free()


class _RestKernel:
    """The kernel of :meth:`VoxelNumberMapEvaluator.weighted_radiance`: sigma_s times per-component weights
    (the chords' tau_s and near-entry albedo), and its world near-entry weights with the evaluator's own
    clamped fluence per direction."""

    def __init__(self, ev, weights, key):
        self.key = key
        c = ev.coef
        coef = Coefficients(sigma_t=c.sigma_t, sigma_s=c.sigma_s * weights, h_mm=c.h_mm)
        self.kernel = prepare_kernel(ev.vnm.surface, ev.vnm.lengths, ev.vnm.blocked, coef)
        self.env_local = None
        if ev.env_phi is not None:
            mu = np.clip(ev.vnm.surface.normal @ ev.vnm.env_directions.T, 0.0, 1.0)
            phi = np.moveaxis(ev.env_phi, 0, 2)  # (n, D, 3), clamped with the evaluator's kernel
            self.env_local = np.ascontiguousarray(np.moveaxis(phi * self.kernel.rho_at(mu), 2, 0))
