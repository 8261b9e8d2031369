"""Single scattering inside inhomogeneous materials (Bernabei et al., "Real-time Single
Scattering Inside Inhomogeneous Materials"), bpy-free.

Bake (``bake_single_scattering``): voxelised sigma_t -> direction-dependent
optical depth for n uniform directions -> first moment T and rho = |div T| ->
weighted Poisson-disk samples -> Gaussian RBFs with partition-of-unity weights
-> psi_i = exp(-tau(b_i, .)) in real SH.  Run time (eq. 3): ``light_term``
per sample, ``view_term`` per sample (optional), ``integrate_view_rays`` per
ray through a uniform sample grid; ``render_vertices`` wraps them for mesh
vertices.  ``reference_radiance`` / ``reference_vertices`` are the
brute-force check (voxel marching, no RBFs, no SH).
"""

from .bake import STAGES, SingleScatteringSettings, bake_single_scattering
from .data import SampleGrid, SingleScatteringData
from .reference import march_optical_depth, reference_radiance, reference_vertices
from .runtime import (ViewRays, all_ray_sample_pairs, entry_transmittance, exit_factor, integrate_view_rays,
                      light_term, ray_sample_pairs, render_vertices, view_rays, view_term)
from .volume import QUALITY_RESOLUTION, VoxelVolume, voxelise

__all__ = [
    "STAGES", "SingleScatteringSettings", "bake_single_scattering", "SampleGrid", "SingleScatteringData",
    "march_optical_depth", "reference_radiance", "reference_vertices", "entry_transmittance", "exit_factor",
    "integrate_view_rays", "light_term", "ray_sample_pairs", "render_vertices", "view_term", "ViewRays",
    "all_ray_sample_pairs", "view_rays",
    "QUALITY_RESOLUTION", "VoxelVolume", "voxelise",
]
