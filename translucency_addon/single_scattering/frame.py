"""Per-frame single scattering at surface points for a view (used by the CLI and the Blender side).

:class:`FrameEvaluator` owns one baked data set, the surface it was baked
for (a BVH for the far-side clip) and the points where radiance is wanted
(the mesh vertices, or any points on that surface with their normals).  Per
frame it computes the light term (numpy, per sample), the view term when the
view is a camera, and runs the per-ray pass through an *integrator*: the
numpy :class:`~.runtime.CPUIntegrator` or the GPU kernel's dispatcher
(``gpu_shaders.single_scattering``), which share one interface.  View rays
are cached per view (a BVH cast each), so a frame in which only the lights
changed costs the light term and the ray pass (on the CPU: one weighted sum
over the cached ray-sample pairs).

Views (object space, as ``ops.scene_inputs.camera_view`` returns them):

* ``None``: every point is seen along its normal (per-ray psi from the SH);
* ``("PERSP", eye)``: a perspective camera at ``eye``;
* ``("ORTHO", towards_camera)``: an orthographic camera.
"""

from __future__ import annotations

import time

import numpy as np

from .runtime import CPUIntegrator, light_term, medium_margin, rays_from_points, view_term
from .view_reflection import integrate_with_reflections


def _view_key(view):
    if view is None:
        return None
    kind, value = view
    return (str(kind), tuple(round(float(x), 9) for x in value))


class FrameEvaluator:
    """Single scattering at ``points`` (default: the vertices ``V``) of the baked surface ``(V, F)``."""

    def __init__(self, data, V, F, normals=None, *, points=None, point_normals=None, integrator=None,
                 far_clip: bool = True):
        from ..geometry.meshio import vertex_normals
        from ..geometry.raycast import mesh_bvh

        self.data = data
        self.V = np.asarray(V, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        self.far_clip = bool(far_clip)
        self._bvh = None
        if points is None:
            self.points = self.V
            self.normals = np.asarray(normals if normals is not None else vertex_normals(self.V, self.F),
                                      dtype=np.float64)
        else:
            # Points off the baked surface (another mesh's vertices) start from the closest surface point.
            self._bvh = mesh_bvh(self.V, self.F)
            self.points = self._bvh.closest_point(np.asarray(points, dtype=np.float64))[0]
            self.normals = np.asarray(point_normals, dtype=np.float64).reshape(-1, 3)
        self.integrator = integrator if integrator is not None else CPUIntegrator(data)
        self._rays = None
        self._rays_key = object()
        self._reflected = None  # view_reflection.reflected_rays of the current rays
        self._facet_normals = None
        self._last = None  # the last radiance()'s light terms, rays and settings (weighted_radiance)
        self.seconds = {}

    @property
    def bvh(self):
        if self._bvh is None:
            from ..geometry.raycast import mesh_bvh

            self._bvh = mesh_bvh(self.V, self.F)
        return self._bvh

    def rays(self, view, eta: float = 1.0):
        """The view rays of ``view``, refracted into a medium of index ``eta`` (:func:`.runtime.refract_in`),
        kept while the view and eta stay."""
        key = (_view_key(view), float(eta))
        if self._rays is None or self._rays_key != key:
            bvh = self.bvh if self.far_clip else None
            kw = dict(bvh=bvh, margin=medium_margin(self.data.voxel_size), eta=float(eta))
            if view is None:
                r = rays_from_points(self.points, self.normals, view_dirs=self.normals, **kw)
            elif view[0] == "ORTHO":
                r = rays_from_points(self.points, self.normals, view_dir=view[1], **kw)
            else:
                r = rays_from_points(self.points, self.normals, camera_position=view[1], **kw)
            self._rays, self._rays_key = r, key
            self._reflected = None
        return self._rays

    def reflected(self) -> list:
        """The current view rays' reflections inside (:mod:`.view_reflection` eq. 1), kept with them; none where
        the data keeps no extinction voxels (eta 1, data of formats 1-2), the rays are not refracted, or without
        the far side's clip."""
        from .entry import facet_normals
        from .view_reflection import reflected_rays_of

        rays = self._rays
        if rays is None or not rays.refracted or not self.far_clip:
            return []
        if self._reflected is None:
            if self._facet_normals is None:
                self._facet_normals = facet_normals(self.V, self.F)
            self._reflected = reflected_rays_of(self.data, rays, self.points, self.bvh, self._facet_normals,
                                                self._rays_key[1])
        return self._reflected

    def radiance(self, lights, environment, eta: float, mm_per_unit: float | None = None, view=None, *,
                 use_gpu: bool = True) -> np.ndarray:
        """Outgoing single-scattering radiance at the points, (n_points, 3), W/(m^2 sr)."""
        mm = self.data.mm_per_unit if mm_per_unit is None else float(mm_per_unit)
        t0 = time.perf_counter()
        rays = self.rays(view, eta)
        reflected = self.reflected()
        t1 = time.perf_counter()
        out = np.zeros((len(self.points), 3))
        if len(rays.vertices):
            LT = light_term(self.data, lights, environment, eta, mm)
            VT = None  # psi per sample towards the camera, where the rays go straight to it
            if rays.view_dir is not None:
                VT = view_term(self.data, view_dir=rays.view_dir)
            elif rays.camera_position is not None:
                VT = view_term(self.data, camera_position=rays.camera_position)
            t2 = time.perf_counter()
            out[rays.vertices] = integrate_with_reflections(self.integrator, LT, rays, reflected, view_term=VT,
                                                            eta=eta, mm_per_unit=mm, use_gpu=use_gpu)
            self._last = (LT, rays, reflected, VT, float(eta), mm, use_gpu)
        else:
            t2 = t1
            self._last = None
        t3 = time.perf_counter()
        self.seconds = {"rays": t1 - t0, "light_view_terms": t2 - t1, "ray_pass": t3 - t2, "total": t3 - t0}
        return out

    def rest_media(self) -> np.ndarray | None:
        """(N, 3) albedo of each sample where the baked object holds media of different albedo (a bottle's
        glass and wine, a heterogeneous field), else None (one medium: its surface's albedo is every
        sample's; data of formats 1-3 keep none).  ``frame.orders_after_the_first`` eq. 1."""
        a = getattr(self.data, "albedo", None)
        if a is None or not len(a):
            return None
        a = np.asarray(a, dtype=np.float64)
        scattering = np.any(np.asarray(self.data.sigma_s) > 0, axis=1)
        if not scattering.any() or not np.any(np.ptp(a[scattering], axis=0) > 1e-4):
            return None
        return a

    def weighted_radiance(self, weights: np.ndarray) -> np.ndarray:
        """The last :meth:`radiance` with each sample's light term times ``weights`` (N, 3): the same rays,
        reflections and view term, ``sum_i w_i k sigma_s(b_i) ...`` (the module's eq. 3 term by term); (n_points,
        3).  What the frame weighs each medium's once-scattered light by (``frame.orders_after_the_first``)."""
        out = np.zeros((len(self.points), 3))
        last = getattr(self, "_last", None)
        if last is None:
            return out
        LT, rays, reflected, VT, eta, mm, use_gpu = last
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != LT.shape:
            raise ValueError(f"sample weights of shape {w.shape} for {LT.shape} light terms")
        out[rays.vertices] = integrate_with_reflections(self.integrator, LT * w, rays, reflected, view_term=VT,
                                                        eta=eta, mm_per_unit=mm, use_gpu=use_gpu)
        return out

    @property
    def backend(self) -> str:
        return getattr(self.integrator, "last_backend", getattr(self.integrator, "backend", "CPU"))

    def free(self) -> None:
        free = getattr(self.integrator, "free", None)
        if callable(free):
            free()
