"""Particle fluids (Kang & Kim 2013): Voronoi-fluid cells rebuilt every frame, diffusion on them.

The engine side of issue 14, bpy-free.  Per frame::

    from translucency_addon.fluid import FluidSolver
    res = FluidSolver(material, radius, mm_per_unit).solve(points, lights=..., environment=...,
                                                             surface=(V, F), warm_start=prev_state)

Modules: :mod:`.particles` (input checks, radius), :mod:`.disk_faces` (exact
clipped faces), :mod:`.cells` (Voronoi-fluid cells), :mod:`.cellgraph` (the
cells as a graph of the solver's contract), :mod:`.occluder` (shadow rays),
:mod:`.surface_map` (radiance onto a mesh or points), :mod:`.solver` (the
frame), :mod:`.cli` (``python -m translucency_addon fluid``).
"""

from .cellgraph import FluidGraph, build_graph
from .cells import VoronoiCells, build_cells
from .particles import ParticleSet, prepare_particles, suggest_radius
from .solver import FluidDiffusionSolver, FluidFrame, FluidOptions, FluidResult, FluidSolver, FluidState

__all__ = ["FluidDiffusionSolver", "FluidFrame", "FluidGraph", "FluidOptions", "FluidResult", "FluidSolver",
           "FluidState", "ParticleSet", "VoronoiCells", "build_cells", "build_graph", "prepare_particles",
           "suggest_radius"]
