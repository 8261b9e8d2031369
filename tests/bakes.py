"""Shared, memoised bakes for engine tests (a bake costs seconds; tests reuse them)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from data import mesh_path
from translucency_addon.geometry import meshio, primitives
from translucency_addon.quadgraph.bake import BakeSettings, bake_mesh, resample_surface



@lru_cache(maxsize=None)
def mesh(name: str):
    """A test mesh by name: the project's own meshes (data/meshes, through data.mesh_path), or 'bunny-decimated', or primitives."""
    if name == "bunny-decimated":
        V, F = meshio.load_obj(mesh_path("stanford-bunny"))
        return resample_surface(V, F, 6000)
    if name == "sphere":
        return primitives.icosphere(1.0, 3)
    if name == "cube":
        return primitives.box((1.0, 1.0, 1.0), subdivisions=2)
    return meshio.load_obj(mesh_path(name))


@lru_cache(maxsize=None)
def baked(name: str, quality: str = "draft", levels: int | None = None, mm_per_unit: float = 1.0,
          base_triangles: int | None = None, optimize: bool = True):
    V, F = mesh(name)
    s = BakeSettings(quality=quality, levels=levels, mm_per_unit=mm_per_unit,
                     base_triangles=base_triangles, optimize=optimize)
    return bake_mesh(np.asarray(V), np.asarray(F), s)
