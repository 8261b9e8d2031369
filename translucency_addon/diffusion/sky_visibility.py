# SPDX-License-Identifier: GPL-3.0-or-later
"""Self-occlusion of environment light and one interreflection bounce (extends eq. 3).

Eq. 3's environment term, ``lights.environment_flux``, assumes that every
surface point sees the whole sky::

    q_env(x) = int_{H(n)} F_t(eta, cos) cos L(w) dw                      (eq. 3)

On a concave object part of that hemisphere looks at the object itself.
There the sky is hidden, and what arrives instead is the object's own
outgoing radiance L_o at the point the ray hits (light that left the
object, crossed the concavity through the air and enters again: transport
outside the medium, which the diffusion solve does not contain).  With the
directions d of a Fibonacci set and V(x, d) = 0 where the ray from x hits
the mesh::

    q(x) = q_env(x) - c(x) sum_{d: V=0} w(x, d) L(d)        (hidden sky)
                    + c(x) sum_{d: V=0} w(x, d) L_o(hit(x, d))   (one bounce)

    w(x, d) = F_t(eta, n.d) n.d  for n.d > 0,
    c(x)    = pi (1 - F_dr,ext(eta)) / sum_d w(x, d)

``c`` normalises the quadrature per node so that a fully visible hemisphere
gives exactly the closed form of a uniform environment; the exact q_env is
kept and only the hidden part is quadrature, so a convex object (nothing
hidden) gets exactly the unoccluded term.  ``L_o(hit)`` is interpolated from
the mesh's vertex radiance (the previous solve's, viewed along the normal:
the diffuse approximation of the light the hit point sends back).

:func:`compute_sky_visibility` casts the rays once per bake (they depend
only on the geometry) and stores, per level, the hidden (node, direction)
pairs with their weight ``c w`` and the hit's three vertices and barycentric
weights.  Per frame, :meth:`LevelSky.hidden_sky` and :meth:`LevelSky.bounce`
are two sparse sums.

The accuracy benchmark (docs/accuracy.md, "Where the bunny's model error
comes from") measured this correction on the marble bunny against Mitsuba 3.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import BakeCancelled, CacheError
from ..scene.fresnel import diffuse_reflectance_external, fresnel_transmittance
from ..scene.sh import fibonacci_directions

RAY_CHUNK = 400_000  # rays per BVH call (memory)
DEFAULT_DIRECTIONS = 64  # what the add-on bakes; 128 changed the bunny's error by < 0.1 % (docs/accuracy.md)


@dataclass
class LevelSky:
    """The hidden (surface node, direction) pairs of one level."""

    n_surface: int
    node: np.ndarray  # (m,) int32, surface node index (0 .. n_surface-1)
    direction: np.ndarray  # (m,) int32, index into SkyVisibility.directions
    cosine: np.ndarray  # (m,) n.d of the pair
    hit_vertices: np.ndarray  # (m, 3) int32, vertices of the mesh triangle the ray hits
    hit_bary: np.ndarray  # (m, 3) barycentric weights of the hit on that triangle
    _cache: dict = field(default_factory=dict, repr=False, compare=False)  # eta -> weights, matrices

    def weight(self, eta: float, normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """``c(x) w(x, d)`` of every hidden pair for refractive index ``eta``: q (W/m^2) per unit
        radiance (W/(m^2 sr)).  ``normals``: the level's surface normals (for c's hemisphere sum)."""
        key = ("w", float(eta))
        w = self._cache.get(key)
        if w is None:
            w_all = hemisphere_sums(normals, directions, eta)
            c = np.divide(np.pi * (1.0 - diffuse_reflectance_external(eta)), w_all, out=np.zeros_like(w_all),
                          where=w_all > 0)
            w = c[self.node] * self.cosine * fresnel_transmittance(np.clip(self.cosine, 0.0, 1.0), eta)
            self._cache.clear()
            self._cache[key] = w
        return w

    def hidden_sky(self, weight: np.ndarray, sky_radiance: np.ndarray) -> np.ndarray:
        """``c sum_{hidden} w L(d)`` per surface node, (n_surface, 3); ``sky_radiance`` is (D, 3)."""
        if not len(self.node):
            return np.zeros((self.n_surface, 3))
        key = ("H", id(weight), len(sky_radiance))
        m = self._cache.get(key)
        if m is None:  # the weights as a sparse (n_surface, D) matrix, once per weight: a product per frame
            # (np.add.at over the hidden rays cost ~10 ms a frame at Final)
            m = sp.csr_matrix((weight, (self.node, self.direction)), shape=(self.n_surface, len(sky_radiance)))
            self._cache[key] = m
        return np.asarray(m @ np.asarray(sky_radiance, dtype=np.float64))

    def bounce(self, weight: np.ndarray, vertex_radiance: np.ndarray) -> np.ndarray:
        """``c sum_{hidden} w L_o(hit)`` per surface node, (n_surface, 3), from (n_vertices, 3) radiance."""
        L = np.asarray(vertex_radiance, dtype=np.float64)
        key = ("B", id(weight), len(L))
        m = self._cache.get(key)
        if m is None:
            rows = np.repeat(self.node, 3)
            vals = (weight[:, None] * self.hit_bary).ravel()
            m = sp.csr_matrix((vals, (rows, self.hit_vertices.ravel())), shape=(self.n_surface, len(L)))
            self._cache[key] = m
        return np.asarray(m @ L)



HEMISPHERE_ROWS = 1024  # surface nodes per block of hemisphere_sums: 1024 x 64 directions = 0.5 MB a temporary


def hemisphere_sums(normals: np.ndarray, directions: np.ndarray, eta: float) -> np.ndarray:
    """``sum_d max(0, n.d) F_t(n.d)`` per node: the direction set's own hemisphere integral of the light that
    enters (the normalisation c of the module docstring).  In blocks of HEMISPHERE_ROWS nodes, so each
    temporary of the Fresnel formula stays in the cache: the finest Final bunny level (34,272 surface
    nodes x 64 directions) in 35-40 ms against 70-80 ms warm and 250-440 ms in a cold process for the
    whole (n, D) arrays at once (fresh pages for every temporary); the same sums bit for bit."""
    n = np.asarray(normals, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    out = np.empty(len(n))
    for i in range(0, len(n), HEMISPHERE_ROWS):
        cos = n[i:i + HEMISPHERE_ROWS] @ d.T
        out[i:i + HEMISPHERE_ROWS] = np.where(cos > 0, cos * fresnel_transmittance(np.clip(cos, 0.0, 1.0), eta),
                                              0.0).sum(axis=1)
    return out


@dataclass
class SkyVisibility:
    """Per-level hidden sky directions of a bake (see the module docstring)."""

    directions: np.ndarray  # (D, 3) unit directions
    levels: list  # [LevelSky], coarse -> fine, like Bake.levels

    def correct(self, level: int, normals: np.ndarray, eta: float, q_env, environment=None,
                vertex_radiance=None) -> np.ndarray:
        """q of the environment on ``level`` with the hidden sky removed and the bounce added.

        ``q_env``: the unoccluded environment term (n_surface, 3) or None;
        ``environment`` may be None (then only the bounce is added);
        ``normals``: the level's surface normals.  The hidden-sky part is
        clamped so that no node gets less than zero sky light.
        """
        lv = self.levels[level]
        w = lv.weight(eta, normals, self.directions)
        q = np.zeros((lv.n_surface, 3)) if q_env is None else np.array(q_env, dtype=np.float64)
        if environment is not None and not environment.is_black:
            q = np.maximum(q - lv.hidden_sky(w, environment.radiance_at(self.directions)), 0.0)
        if vertex_radiance is not None:
            q = q + lv.bounce(w, vertex_radiance)
        return q

    def hidden_fraction(self, level: int, normals: np.ndarray, eta: float = 1.0) -> np.ndarray:
        """Per surface node of ``level``, the share of eq. 3's hemisphere weight that sees the object."""
        lv = self.levels[level]
        out = np.zeros(lv.n_surface)
        np.add.at(out, lv.node, lv.weight(eta, normals, self.directions))
        return out / (np.pi * (1.0 - diffuse_reflectance_external(eta)))

    # -- cache ----------------------------------------------------------------------------
    def to_arrays(self, prefix: str = "sky/") -> dict:
        d = {f"{prefix}directions": self.directions}
        for i, lv in enumerate(self.levels):
            p = f"{prefix}L{i}/"
            d.update({f"{p}n_surface": np.array([lv.n_surface]), f"{p}node": lv.node, f"{p}direction": lv.direction,
                      f"{p}cosine": lv.cosine, f"{p}hit_vertices": lv.hit_vertices, f"{p}hit_bary": lv.hit_bary})
        return d

    @classmethod
    def from_arrays(cls, arrays: dict, n_levels: int, n_vertices: int, prefix: str = "sky/") -> "SkyVisibility":
        dirs = np.asarray(arrays[f"{prefix}directions"], dtype=np.float64)
        levels = []
        for i in range(n_levels):
            p = f"{prefix}L{i}/"
            lv = LevelSky(int(arrays[f"{p}n_surface"][0]), arrays[f"{p}node"].astype(np.int64),
                          arrays[f"{p}direction"].astype(np.int64), arrays[f"{p}cosine"].astype(np.float64),
                          arrays[f"{p}hit_vertices"].astype(np.int64), arrays[f"{p}hit_bary"].astype(np.float64))
            m = len(lv.node)
            ok = (dirs.ndim == 2 and dirs.shape[1] == 3 and lv.direction.shape == (m,) and lv.cosine.shape == (m,)
                  and lv.hit_vertices.shape == (m, 3) and lv.hit_bary.shape == (m, 3)
                  and (m == 0 or (0 <= lv.node.min() and lv.node.max() < lv.n_surface
                                  and 0 <= lv.direction.min() and lv.direction.max() < len(dirs)
                                  and 0 <= lv.hit_vertices.min() and lv.hit_vertices.max() < n_vertices))
                  and np.all(np.abs(lv.cosine) <= 1.0) and np.all(np.isfinite(lv.hit_bary)))
            if not ok:
                raise CacheError(f"sky visibility of level {i} is inconsistent with the bake")
            levels.append(lv)
        return cls(dirs, levels)


def compute_sky_visibility(bake, n_directions: int = 64, bvh=None, progress=None) -> SkyVisibility:
    """Cast ``n_directions`` rays over each surface node's hemisphere against the user's mesh.

    Only the geometry enters; the Fresnel weights are formed per refractive
    index when the solver asks (:meth:`LevelSky.weight`).
    ``progress(fraction)`` returning False cancels (:class:`BakeCancelled`).
    """
    from ..geometry.raycast import mesh_bvh

    if n_directions < 8:
        raise ValueError(f"n_directions must be at least 8, got {n_directions}")
    V = np.asarray(bake.mesh_vertices, dtype=np.float64)
    F = np.asarray(bake.mesh_faces, dtype=np.int64)
    bvh = mesh_bvh(V, F) if bvh is None else bvh
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    dirs = fibonacci_directions(int(n_directions))
    total = max(sum(lv.n_surface for lv in bake.levels), 1)
    done = 0
    levels = []
    for lv in bake.levels:
        P, N = lv.surface_position, lv.normal
        cos = N @ dirs.T  # (n_s, D)
        ii, dd = np.nonzero(cos > 0)
        parts = []
        for s in range(0, len(ii), RAY_CHUNK):
            a, d = ii[s:s + RAY_CHUNK], dd[s:s + RAY_CHUNK]
            _, tri, u, v = bvh.intersect(P[a] + 1e-4 * diag * N[a], dirs[d])
            hit = tri >= 0
            a, d, tri, u, v = a[hit], d[hit], tri[hit], u[hit], v[hit]
            parts.append((a.astype(np.int32), d.astype(np.int32), cos[a, d], F[tri].astype(np.int32),
                          np.stack([1.0 - u - v, u, v], axis=1)))
            frac = (done + min(s + RAY_CHUNK, len(ii)) / max(len(ii), 1) * lv.n_surface) / total
            if progress is not None and progress(frac) is False:
                raise BakeCancelled("sky visibility cancelled")
        done += lv.n_surface
        empty = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0), np.zeros((0, 3), np.int32),
                 np.zeros((0, 3)))
        cat = [np.concatenate([p[k] for p in parts]) for k in range(5)] if parts else list(empty)
        levels.append(LevelSky(lv.n_surface, *cat))
    return SkyVisibility(dirs, levels)
