"""Single scattering inside inhomogeneous materials (Bernabei et al., "Real-time Single
Scattering Inside Inhomogeneous Materials"), bpy-free.

Bake (``bake_single_scattering``): voxelised sigma_t -> direction-dependent
optical depth for n uniform directions -> first moment T and rho = |div T| ->
weighted Poisson-disk samples -> Gaussian RBFs with partition-of-unity weights
-> psi_i = exp(-tau(b_i, .)) in real SH.  ``bake_single_scattering_for`` bakes
for a QuadGraph ``Bake`` (its mesh and scale) and records what the optical
depth was baked from; ``attach`` stores it in the bake under a combined key;
``staleness`` says what changed since (``cached``).  Run time (eq. 3):
``light_term`` per sample, ``view_term`` per sample (optional),
``integrate_view_rays`` per ray through a uniform sample grid (the numpy twin
of ``gpu_shaders/single_scattering.glsl``), or, for the rays of one camera, with
the pairs found in the image plane (``projected``: same pairs, same sums, and the
far-side exits of the BVH without its per-ray walk); ``render_vertices`` wraps them for
mesh vertices; ``FrameEvaluator`` caches view rays per view and runs the ray
pass through the numpy ``CPUIntegrator`` or the GPU dispatcher.
``reference_radiance`` / ``reference_vertices`` are the brute-force check
(voxel marching, no RBFs, no SH).
"""

from .bake import STAGES, SingleScatteringSettings, bake_single_scattering
from .cached import (GridField, attach, bake_single_scattering_for, combined_key, expected_key, fingerprint_field,
                     graph_key, material_fingerprint, stale_message, staleness)
from .data import SampleGrid, SingleScatteringData
from .frame import FrameEvaluator
from .reference import march_optical_depth, reference_radiance, reference_vertices
from .ray_pairs import all_ray_sample_pairs, ray_sample_pairs
from .runtime import (CPUIntegrator, ViewRays, entry_transmittance, exit_factor, integrate_view_rays, light_term,
                      rays_from_points, render_vertices, view_rays, view_term)
from .volume import QUALITY_RESOLUTION, VoxelVolume, voxelise

__all__ = [
    "STAGES", "SingleScatteringSettings", "bake_single_scattering", "SampleGrid", "SingleScatteringData",
    "march_optical_depth", "reference_radiance", "reference_vertices", "entry_transmittance", "exit_factor",
    "integrate_view_rays", "light_term", "ray_sample_pairs", "render_vertices", "view_term", "ViewRays",
    "all_ray_sample_pairs", "view_rays", "rays_from_points", "CPUIntegrator", "FrameEvaluator",
    "bake_single_scattering_for", "attach", "graph_key", "combined_key", "expected_key", "fingerprint_field",
    "material_fingerprint", "staleness", "stale_message", "GridField",
    "QUALITY_RESOLUTION", "VoxelVolume", "voxelise",
]
