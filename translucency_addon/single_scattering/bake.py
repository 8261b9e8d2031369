"""Single-scattering bake (Bernabei et al. sec. 4.2): voxels -> tau(x, w) -> T, rho -> samples -> RBFs, SH.

Stages (names passed to ``progress(fraction, stage)`` and keys of ``stats["time"]``):

``voxelise``  sigma_t, sigma_s inside the mesh, blockers opaque
``ddod``      direction-dependent optical depth for n directions -> first moment T (eq. 4) per voxel
``div``       rho = |div T|
``pds``       weighted Poisson-disk sampling (radii r/2 .. 2r)
``rbf``       Gaussian widths and partition-of-unity weights
``sh``        tau recomputed per direction at the samples -> psi_i SH coefficients; sigma_s
``grid``      uniform sample grid (CSR cell lists) for the view rays

The progress callback may raise (e.g. :class:`~translucency_addon.errors.BakeCancelled`)
to cancel; it is called between stages and inside the long loops (every batch
of directions, every sampling round), and the exception propagates unchanged.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ..scene import sh as shmod
from ..errors import MaterialError
from . import optical_depth as od
from .entry import WorldEntry
from .data import SampleGrid, SingleScatteringData
from .sampling import SUPPORT_SIGMAS, fit_partition_of_unity, gaussian_matrix, poisson_disk
from .volume import resolution_for, trilinear, voxelise

STAGES = (("voxelise", 0.05), ("ddod", 0.40), ("div", 0.02), ("pds", 0.10), ("rbf", 0.08), ("sh", 0.33), ("grid", 0.02))


@dataclass(frozen=True)
class SingleScatteringSettings:
    quality: object = "preview"  # "draft" | "preview" | "final" (32/48/64 voxels on the longest side) or an int
    n_dirs: int = 128  # directions of the optical depth (paper: 32, 128, 512)
    n_samples: int = 20000  # target N_s of the Poisson-disk sampling
    sh_order: int = 4  # 2..4 -> 9..25 coefficients
    width_factor: float = 0.8  # Gaussian standard deviation / Poisson radius
    oversample: float = 6.0  # dart-throwing candidates per requested sample
    pou_iterations: int = 40
    cell_factor: float = 1.0  # sample-grid cell size / median support radius
    seed: int = 0

    def validated(self) -> "SingleScatteringSettings":
        resolution_for(self.quality)
        if int(self.n_dirs) < 6:
            raise ValueError(f"n_dirs must be at least 6, got {self.n_dirs}")
        if int(self.n_samples) < 8:
            raise ValueError(f"n_samples must be at least 8, got {self.n_samples}")
        if int(self.sh_order) not in (1, 2, 3, 4):
            raise ValueError(f"sh_order must be 1..4 (paper: 2..4), got {self.sh_order}")
        if not (0.1 <= float(self.width_factor) <= 2.0):
            raise ValueError(f"width_factor must be in [0.1, 2], got {self.width_factor}")
        if float(self.oversample) < 1.5:
            raise ValueError(f"oversample must be >= 1.5, got {self.oversample}")
        return self


class _Progress:
    def __init__(self, cb):
        self.cb = cb
        self.base = 0.0
        self.span = 0.0
        self.name = ""
        self.t0 = 0.0
        self.times = {}

    def begin(self, name):
        w = dict(STAGES)[name]
        self.name, self.span = name, w
        self.t0 = time.perf_counter()
        self(0.0)

    def __call__(self, frac):
        if self.cb is not None:
            self.cb(min(1.0, self.base + self.span * float(frac)), self.name)

    def end(self):
        self.times[self.name] = time.perf_counter() - self.t0
        self.base += self.span
        if self.cb is not None:
            self.cb(min(1.0, self.base), self.name)


def bake_single_scattering(V, F, material, field=None, settings: SingleScatteringSettings | None = None, *,
                           mm_per_unit: float = 1.0, blockers=(), progress=None, volume=None, bvh=None,
                           keep_volume: bool = False) -> SingleScatteringData:
    """Bake single-scattering samples for the closed mesh ``(V, F)`` (object space).

    ``material``: :class:`~translucency_addon.scene.materials.Material` (or anything
    with ``.coefficients(field_values, n=...)`` and ``.heterogeneous``).
    ``field(points) -> values in [0, 1]`` mixes a two-medium material (a
    Blender texture sampler, or ``lambda p: evaluate_field(spec, p)``).
    ``blockers``: ``[(V, F), ...]`` closed meshes whose inside is opaque.
    ``volume``: a precomputed :class:`~.volume.VoxelVolume` (skips voxelisation).
    ``keep_volume``: attach the voxel volume as ``data.volume`` (not stored by ``to_arrays``).
    Raises :class:`MeshError` / :class:`MaterialError` for bad input.
    """
    from ..geometry.meshio import validate_mesh
    from ..geometry.raycast import TriangleBVH

    s = (settings or SingleScatteringSettings()).validated()
    rng = np.random.default_rng(int(s.seed))
    P = _Progress(progress)
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)

    P.begin("voxelise")
    if volume is None:
        validate_mesh(V, F)
        bvh = bvh if bvh is not None else TriangleBVH(V, F)
        volume = voxelise(V, F, material, field, resolution=s.quality, mm_per_unit=mm_per_unit,
                          blockers=blockers, bvh=bvh)
    P.end()

    P.begin("ddod")
    dirs = shmod.fibonacci_directions(int(s.n_dirs))
    order = int(s.sh_order)
    T = od.first_moment(volume, dirs, progress=P)
    P.end()

    P.begin("div")
    rho = od.divergence_density(T, volume.h)
    P.end()

    P.begin("pds")
    centers, delta, candidates, pinfo = poisson_disk(volume, rho, int(s.n_samples), rng, oversample=float(s.oversample),
                                                     progress=P)
    P.end()

    P.begin("rbf")
    sigma = float(s.width_factor) * delta
    support = SUPPORT_SIGMAS * sigma
    med_idx = np.flatnonzero(volume.medium)
    fit_pts = np.vstack([candidates, volume.centres(med_idx)])
    G = gaussian_matrix(fit_pts, centers, sigma)
    P(0.5)
    weight, fit_rms, fit_max = fit_partition_of_unity(G, int(s.pou_iterations))
    P.end()

    P.begin("sh")
    eta = float(getattr(material, "eta", 1.0))
    sh_env = None
    if eta != 1.0:  # the world's light enters through the critical cone (entry.py eq. 2)
        sh, sh_env = od.sample_sh(volume, dirs, centers, order, progress=P, entry=WorldEntry(V, F, centers, eta, bvh))
    else:
        sh = od.sample_sh(volume, dirs, centers, order, progress=P)
    sig_s = trilinear(volume.sigma_s, volume.origin, volume.h, centers)
    sig_t = trilinear(volume.sigma_t, volume.origin, volume.h, centers)
    # which medium scattered: sigma_s / sigma_t of the same interpolation (a homogeneous medium's own albedo
    # wherever sigma_t > 0, the voxel model's boundary ramp included)
    albedo = np.clip(sig_s / np.maximum(sig_t, 1e-30), 0.0, 1.0) * (sig_t > 0)
    P.end()

    P.begin("grid")
    grid = SampleGrid.build(centers, support, float(s.cell_factor) * float(np.median(support)))
    P.end()

    for name, arr in (("sh", sh), ("sh_env", sh_env), ("sigma_s", sig_s), ("weight", weight)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise MaterialError(f"the bake produced non-finite {name}: check the material coefficients")
    stats = {
        "time": P.times,
        "settings": {k: (v if not isinstance(v, np.generic) else v.item()) for k, v in asdict(s).items()},
        "voxels": list(volume.shape),
        "voxel_size": volume.h,
        # Single scattering lives within a few mean free paths of the surface; when the shortest one is far
        # below a voxel (marble at the scale of a bunny) the voxels and RBFs cannot resolve it and the result
        # is too dark (see bench/single_scattering.py).  Callers can warn on mean_free_path_voxels < ~1.
        "mean_free_path_mm": 1.0 / max(float(volume.sigma_t[volume.medium].max()), 1e-30),
        "mean_free_path_voxels": 1.0 / max(float(volume.sigma_t[volume.medium].max()), 1e-30)
        / (volume.h * volume.mm_per_unit),
        "medium_voxels": int(volume.medium.sum()),
        # baked from a composite volume (voxelise_composite): the samples know the object's inner parts
        "inner_parts": bool(getattr(volume, "labels", None) is not None and volume.labels.order),
        "n_samples": int(len(centers)),
        "poisson": pinfo,
        "pou_rms": fit_rms,
        "pou_max": fit_max,
        "grid_entries": int(len(grid.cell_items)),
        "grid_dims": [int(x) for x in grid.dims],
    }
    data = SingleScatteringData(centers=centers, sigma=sigma, weight=weight, support=support, poisson_radius=delta,
                                sigma_s=sig_s, sh=sh, sh_env=sh_env, entry_eta=eta, order=order, albedo=albedo,
                                extinction=None if eta == 1.0 else np.asarray(volume.sigma_t, dtype=np.float32), n_dirs=int(s.n_dirs), mm_per_unit=float(volume.mm_per_unit),
                                grid=grid, voxel_origin=np.asarray(volume.origin), voxel_size=float(volume.h),
                                voxel_shape=np.asarray(volume.shape, dtype=np.int64), stats=stats)
    if keep_volume:
        data.volume = volume
    return data

