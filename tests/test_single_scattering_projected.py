"""Image-plane bins (``single_scattering.projected``) against the grid walk and the triangle BVH.

The bins only choose which (ray, sample) and (ray, triangle) pairs to test; the tests are the
same functions as before, so the expected values are the independent paths' own outputs: the
3D DDA through the sample grid (``ray_sample_pairs``, itself checked against brute force in
``test_single_scattering.py``) and ``TriangleBVH.intersect``.
"""

from __future__ import annotations

import numpy as np
import pytest

from translucency_addon.geometry import meshio
from translucency_addon.scene.materials import Material, Medium
from translucency_addon.geometry.raycast import TriangleBVH
from translucency_addon.single_scattering import (SingleScatteringSettings, all_ray_sample_pairs,
                                                  bake_single_scattering, integrate_view_rays, shapes, view_rays,
                                                  view_term)
from translucency_addon.single_scattering.projected import ImageBins, exit_distances
from translucency_addon.single_scattering.ray_pairs import projected_pairs


@pytest.fixture(scope="module")
def torus():
    V, F = shapes.torus(5.0, 2.0, 48, 16)
    return V, F, meshio.vertex_normals(V, F), TriangleBVH(V, F)


def _bvh_exit(bvh, V, rays):
    t, tri, _, _ = bvh.intersect(rays.origins, rays.dirs, tmin=1e-7 * np.linalg.norm(V.max(0) - V.min(0)))
    return np.where(tri >= 0, t, 0.0)


@pytest.mark.parametrize("view", [("PERSP", (3.0, 20.0, 8.0)), ("PERSP", (7.5, 0.5, 0.3)), ("PERSP", (0.0, 0.0, 3.0)),
                                  ("ORTHO", (0.2, -1.0, 0.6))])
def test_far_side_exits_are_the_bvh_hits(torus, view):
    """Rays from the front-facing vertices of a torus (concave: most rays leave and re-enter)."""
    V, F, N, bvh = torus
    kw = {"camera_position": view[1]} if view[0] == "PERSP" else {"view_dir": view[1]}
    rays = view_rays(V, F, N, bvh=bvh, **kw)
    expect = _bvh_exit(bvh, V, rays)
    assert np.count_nonzero(expect) > 0.8 * len(expect)
    np.testing.assert_array_equal(rays.t_exit, expect)  # same Moller-Trumbore arithmetic: bit-equal


def test_far_side_exits_with_triangles_behind_the_nearest_origin(torus):
    """Only the farther rays: the triangles nearer than every origin (partly behind the eye plane
    of the bins) are clipped, not lost."""
    V, F, N, bvh = torus
    cam = np.array([7.5, 0.5, 0.3])
    rays = view_rays(V, F, N, camera_position=cam, far_clip=False)
    far = np.linalg.norm(rays.origins - cam, axis=1) > np.median(np.linalg.norm(rays.origins - cam, axis=1))
    o, d = rays.origins[far], rays.dirs[far]
    bins = ImageBins.build(o, camera_position=cam)
    P = (V - bins.eye) @ bins.M.T
    assert ((P[:, 2] < bins.z_lo)[F].any(axis=1) & (P[:, 2] >= bins.z_lo)[F].any(axis=1)).sum() > 50
    tmin = 1e-7 * np.linalg.norm(V.max(0) - V.min(0))
    t, tri, _, _ = bvh.intersect(o, d, tmin=tmin)
    np.testing.assert_array_equal(exit_distances(bins, V, F, o, d, tmin), np.where(tri >= 0, t, np.inf))


@pytest.fixture(scope="module")
def sphere_data():
    V, F = shapes.uv_sphere(10.0, 16, 32)
    mat = Material(Medium((0.02, 0.04, 0.06), (0.2, 0.25, 0.3)), eta=1.3)
    s = SingleScatteringSettings(quality=24, n_dirs=32, n_samples=2500, sh_order=3, seed=0)
    return V, F, meshio.vertex_normals(V, F), bake_single_scattering(V, F, mat, None, s, mm_per_unit=1.0)


def _as_dict(pairs):
    r, s, g = pairs
    return dict(zip(zip(r.tolist(), s.tolist()), g.tolist()))


@pytest.mark.parametrize("view", [("PERSP", (30.0, 5.0, -8.0)), ("PERSP", (12.0, 2.0, 3.0)),
                                  ("ORTHO", (1.0, 0.3, -0.2))])
def test_projected_pairs_are_the_grid_walk_pairs(sphere_data, view):
    V, F, N, data = sphere_data
    kw = {"camera_position": view[1]} if view[0] == "PERSP" else {"view_dir": view[1]}
    rays = view_rays(V, F, N, **kw)
    walk = _as_dict(all_ray_sample_pairs(data, rays.origins, rays.dirs, rays.t_exit))
    bins = _as_dict(all_ray_sample_pairs(data, rays.origins, rays.dirs, rays.t_exit, **kw))
    assert len(walk) > 20 * len(rays.origins)
    assert bins.keys() == walk.keys()
    np.testing.assert_array_equal(np.array([bins[k] for k in walk]), np.array(list(walk.values())))
    lt = np.random.default_rng(1).random((data.n_samples, 3))
    for vt in (view_term(data, **kw), None):  # per-sample and per-ray psi
        a = integrate_view_rays(data, lt, rays.origins, rays.dirs, rays.t_exit, 1.0, view_term=vt)
        b = integrate_view_rays(data, lt, rays.origins, rays.dirs, rays.t_exit, 1.0, view_term=vt, **kw)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-15 * np.abs(a).max())


def test_origins_behind_the_eye_fall_back_to_the_grid_walk(sphere_data):
    """Rays from points around the eye (here: the sphere's centre) cannot be binned in one image."""
    V, F, N, data = sphere_data
    rays = view_rays(V, F, -N, camera_position=(0.0, 0.0, 0.0), far_clip=False)
    assert len(rays.origins) == len(V)
    assert projected_pairs(data, rays.origins, rays.dirs, rays.t_exit, camera_position=(0.0, 0.0, 0.0)) is None
    lt = np.ones((data.n_samples, 3))
    a = integrate_view_rays(data, lt, rays.origins, rays.dirs, rays.t_exit, 1.0)
    b = integrate_view_rays(data, lt, rays.origins, rays.dirs, rays.t_exit, 1.0, camera_position=(0.0, 0.0, 0.0))
    np.testing.assert_array_equal(a, b)
