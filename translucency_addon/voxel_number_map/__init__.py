"""The Voxel Number Map (Mochida et al., "Real-time Rendering of Heterogeneous Translucent Objects
using Voxel Number Map"): cavities and several media inside one object, bpy-free.

Precomputation (:func:`bake_voxel_number_map`): voxelise the whole
:class:`~translucency_addon.scene.composite.CompositeObject` with the
single-scattering voxeliser (``voxelise_composite``), extract and number the
surface voxels (:mod:`.surface`), and march every chord between two surface
voxels through the voxels, storing its length in each component medium as a
packed symmetric fp16 LUT, plus one blocked bit where it crosses an opaque
part (:mod:`.lut`).  Run time (:class:`VoxelNumberMapEvaluator`): irradiance per
entry voxel from the project's lights with shadows, then the exit radiance by
the transport kernel derived in :mod:`.transport` (a radiance in
W/(m^2 sr) for the single-scattering-dominant media the method assumes), one
packed matrix-vector product per channel (BLAS here, the GLSL kernel
``gpu_shaders/voxel_number_map.glsl`` on a GPU).

API for the Blender side and the CLI::

    comp = CompositeObject(V, F, material, parts=[InnerPart("Wine", Vw, Fw, "medium", wine),
                                                   InnerPart("Air", Va, Fa, "cavity")])
    vnm = bake_voxel_number_map(comp, VNMSettings(quality="preview"), mm_per_unit=mm, progress=cb)
    ev = VoxelNumberMapEvaluator(vnm, material)          # material of the outer part
    L = ev.radiance(lights, environment, view)           # (n_outer_vertices, 3), W/(m^2 sr)
"""

from .bake import (MAX_SURFACE_VOXELS, QUALITY_SURFACE_VOXELS, VNMSettings, VoxelNumberMap,
                   bake_voxel_number_map, budget_message, format_stats)
from .lut import kernel_bytes, lut_bytes, n_pairs, packed_index
from .runtime import VoxelNumberMapEvaluator
from .surface import SurfaceVoxels, extract_surface_voxels
from .transport import MU_NODES, Coefficients, PreparedKernel, pair_kernel, prepare_kernel

__all__ = [
    "MAX_SURFACE_VOXELS", "QUALITY_SURFACE_VOXELS", "VNMSettings", "VoxelNumberMap", "bake_voxel_number_map",
    "budget_message", "format_stats", "kernel_bytes", "lut_bytes", "n_pairs", "packed_index",
    "VoxelNumberMapEvaluator", "SurfaceVoxels", "extract_surface_voxels", "MU_NODES", "Coefficients",
    "PreparedKernel", "pair_kernel", "prepare_kernel",
]
