"""Baked single-scattering data and the uniform sample grid (fixed-size arrays only).

Everything is a plain numeric array so that it can be stored beside the
QuadGraph in the same versioned ``.npz`` (``to_arrays`` / ``from_arrays``,
``allow_pickle=False``) and packed into 2D textures for a GLSL kernel
(``kernel_arrays``): per-sample rows of floats, and the sample grid as CSR
cell lists (``cell_start`` offsets + ``cell_items`` sample indices).

Sample grid: each sample is listed in every cell that its truncated Gaussian
(a ball of radius ``support``) touches.  A view ray walks the cells it crosses
(3D DDA) and evaluates a sample only in the cell that contains the ray
segment's point closest to the sample centre, so every (ray, sample) pair is
counted exactly once without any de-duplication (see ``runtime``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from ..errors import CacheError

# 2: sh_env (entry.py eq. 2, the critical cone); 3: sh_env with the world's light reflected inside (eq. 3), and
# the extinction voxels the view rays' reflections inside are attenuated along (view_reflection.py); 4: the
# samples' albedo (the orders after the first of each medium, frame.orders_after_the_first).
# Versions 1 to 3 are read and render (their world term as it was baked, the orders at the surface's albedo),
# and their key is stale.
FORMAT_VERSION = 4
READABLE_VERSIONS = (1, 2, 3, 4)


def read_prefixed(d, prefix: str, what: str, version):
    """``(get, meta)`` for a versioned block of cache arrays under ``prefix`` (``version`` and ``meta_json``
    entries): ``get(name)`` returns the array or raises :class:`CacheError` naming what is missing; a
    wrong version or corrupt metadata raises too.  Shared by the data sets stored beside a bake."""

    def get(name):
        key = prefix + name
        if key not in d:
            raise CacheError(f"{what} is incomplete: {key!r} is missing")
        return np.asarray(d[key])

    found = int(get("version").reshape(-1)[0])
    versions = tuple(version) if isinstance(version, (tuple, list)) else (int(version),)
    if found not in versions:
        raise CacheError(f"{what} has format version {found}; this build reads "
                         f"{', '.join(str(v) for v in versions)}")
    try:
        meta = json.loads(bytes(get("meta_json").astype(np.uint8)).decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as e:
        raise CacheError(f"{what}: metadata is corrupt: {e}") from None
    return get, meta


@dataclass
class SampleGrid:
    origin: np.ndarray  # (3,) object units
    cell_size: float
    dims: np.ndarray  # (3,) int64
    cell_start: np.ndarray  # (n_cells + 1,) int64 offsets into cell_items
    cell_items: np.ndarray  # (n_entries,) int32 sample indices

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.dims))

    @classmethod
    def build(cls, centers: np.ndarray, support: np.ndarray, cell_size: float, max_cells: int = 128**3) -> "SampleGrid":
        centers = np.asarray(centers, dtype=np.float64)
        support = np.asarray(support, dtype=np.float64)
        lo = (centers - support[:, None]).min(axis=0)
        hi = (centers + support[:, None]).max(axis=0)
        cell_size = float(cell_size)
        ext = hi - lo
        while np.prod(np.ceil(ext / cell_size) + 1) > max_cells:
            cell_size *= 1.25
        dims = np.maximum(np.ceil(ext / cell_size).astype(np.int64), 1)
        origin = lo - 0.5 * (dims * cell_size - ext)  # centre the box
        eps = 1e-7 * cell_size
        c0 = np.clip(np.floor((centers - support[:, None] - eps - origin) / cell_size).astype(np.int64), 0, dims - 1)
        c1 = np.clip(np.floor((centers + support[:, None] + eps - origin) / cell_size).astype(np.int64), 0, dims - 1)
        span = c1 - c0 + 1
        count = span.prod(axis=1)
        sid = np.repeat(np.arange(len(centers)), count)
        local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
        sy, sz = span[sid, 1], span[sid, 2]
        ix = c0[sid, 0] + local // (sy * sz)
        iy = c0[sid, 1] + (local // sz) % sy
        iz = c0[sid, 2] + local % sz
        # keep cells that the support ball actually touches
        cell_lo = origin + np.stack([ix, iy, iz], axis=1) * cell_size
        q = np.clip(centers[sid], cell_lo, cell_lo + cell_size)
        touch = ((q - centers[sid]) ** 2).sum(axis=1) <= (support[sid] + eps) ** 2
        lin = (ix * dims[1] + iy) * dims[2] + iz
        lin, sid = lin[touch], sid[touch]
        order = np.lexsort((sid, lin))
        lin, sid = lin[order], sid[order]
        start = np.zeros(int(np.prod(dims)) + 1, dtype=np.int64)
        np.add.at(start, lin + 1, 1)
        start = np.cumsum(start)
        return cls(origin=origin, cell_size=cell_size, dims=dims, cell_start=start, cell_items=sid.astype(np.int32))


@dataclass
class SingleScatteringData:
    """Samples b_i with Gaussian RBFs and SH-compressed psi_i(w) = exp(-tau(b_i, w)).

    Units: ``centers``, ``sigma``, ``support``, ``poisson_radius`` in object
    units; ``sigma_s`` per mm (RGB); ``sh`` dimensionless, ``(N, K, 3)`` with
    K = (order+1)^2 real orthonormal SH (``translucency_addon.scene.sh`` order and
    signs).  The RBF of sample i is ``weight_i * exp(-a_i |x - b_i|^2)``,
    ``a_i = 1 / (2 sigma_i^2)``, zero beyond ``support_i`` (= 2.5 sigma_i).
    """

    centers: np.ndarray  # (N, 3) float64
    sigma: np.ndarray  # (N,) Gaussian standard deviation
    weight: np.ndarray  # (N,) partition-of-unity weight
    support: np.ndarray  # (N,) truncation radius
    poisson_radius: np.ndarray  # (N,) delta_i of the Poisson-disk sampling
    sigma_s: np.ndarray  # (N, 3) per mm
    sh: np.ndarray  # (N, K, 3) float32
    order: int
    n_dirs: int
    mm_per_unit: float
    grid: SampleGrid
    voxel_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    voxel_size: float = 0.0
    voxel_shape: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.int64))
    stats: dict = field(default_factory=dict)
    # SH of g_i psi_i, the world's light through the critical cone (entry.py eq. 2), baked for ``entry_eta``;
    # None where that is 1 (no interface) or in data of format 1 (the straight model: runtime.light_term)
    sh_env: np.ndarray | None = None  # (N, K, 3) float32
    entry_eta: float = 1.0
    # sigma_t per mm on the bake's voxels, (nx, ny, nz, 3) float32, where eta is not 1: the view rays' reflections
    # inside (view_reflection.py) are attenuated along it; None without an interface or in data of formats 1-2
    extinction: np.ndarray | None = None
    # sigma_s / sigma_t at each sample, (N, 3): which medium scattered the light, where an object holds several
    # (frame.orders_after_the_first); None in data of formats 1-3
    albedo: np.ndarray | None = None
    # Arrays the ray-pair loops derive from the samples once (``ray_pairs._cache``: cell-ordered centres, the
    # Gaussians' constants), keyed by the arrays they came from; never saved, not part of equality.
    ray_cache: dict = field(default_factory=dict, compare=False, repr=False)
    # The voxel volume the samples were baked from, when the bake kept it (``keep_volume``: the brute-force
    # references of the tests and benches march it); never saved, not part of equality.
    volume: object = field(default=None, compare=False, repr=False)

    @property
    def n_samples(self) -> int:
        return int(len(self.centers))

    @property
    def alpha(self) -> np.ndarray:
        """Gaussian exponent a_i = 1 / (2 sigma_i^2) (object units^-2)."""
        return 0.5 / self.sigma**2

    def with_order(self, order: int) -> "SingleScatteringData":
        """A copy whose SH is truncated to a lower order (the projection is nested)."""
        if order > self.order or order < 1:
            raise ValueError(f"can truncate SH order {self.order} to 1..{self.order}, not {order}")
        K = (order + 1) ** 2
        import dataclasses

        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "ray_cache"}
        kw.update(sh=np.ascontiguousarray(self.sh[:, :K]), order=order)
        return SingleScatteringData(**kw)

    # ----------------------------------------------------------------- cache
    def to_arrays(self, prefix: str = "ss/") -> dict:
        meta = {"order": int(self.order), "n_dirs": int(self.n_dirs), "mm_per_unit": float(self.mm_per_unit),
                "entry_eta": float(self.entry_eta),
                "voxel_size": float(self.voxel_size), "cell_size": float(self.grid.cell_size), "stats": self.stats}
        arrays = {
            "version": np.array([FORMAT_VERSION], dtype=np.int64),
            "meta_json": np.frombuffer(json.dumps(meta, sort_keys=True, default=float).encode("utf-8"), dtype=np.uint8),
            "centers": np.asarray(self.centers, dtype=np.float64),
            "sigma": np.asarray(self.sigma, dtype=np.float64),
            "weight": np.asarray(self.weight, dtype=np.float64),
            "support": np.asarray(self.support, dtype=np.float64),
            "poisson_radius": np.asarray(self.poisson_radius, dtype=np.float64),
            "sigma_s": np.asarray(self.sigma_s, dtype=np.float64),
            "sh": np.asarray(self.sh, dtype=np.float32),
            "voxel_origin": np.asarray(self.voxel_origin, dtype=np.float64),
            "voxel_shape": np.asarray(self.voxel_shape, dtype=np.int64),
            "grid_origin": np.asarray(self.grid.origin, dtype=np.float64),
            "grid_dims": np.asarray(self.grid.dims, dtype=np.int64),
            "cell_start": np.asarray(self.grid.cell_start, dtype=np.int64),
            "cell_items": np.asarray(self.grid.cell_items, dtype=np.int32),
        }
        if self.sh_env is not None:
            arrays["sh_env"] = np.asarray(self.sh_env, dtype=np.float32)
        if self.extinction is not None:
            arrays["extinction"] = np.asarray(self.extinction, dtype=np.float32)
        if self.albedo is not None:
            arrays["albedo"] = np.asarray(self.albedo, dtype=np.float32)
        return {prefix + k: v for k, v in arrays.items()}

    @classmethod
    def from_arrays(cls, d, prefix: str = "ss/") -> "SingleScatteringData":
        get, meta = read_prefixed(d, prefix, "single-scattering data", READABLE_VERSIONS)
        centers = get("centers").astype(np.float64)
        n = len(centers)
        order = int(meta["order"])
        K = (order + 1) ** 2
        shapes = {"sigma": (n,), "weight": (n,), "support": (n,), "poisson_radius": (n,), "sigma_s": (n, 3),
                  "sh": (n, K, 3), "grid_origin": (3,), "grid_dims": (3,), "voxel_origin": (3,), "voxel_shape": (3,)}
        arr = {k: get(k) for k in shapes}
        for k, s in shapes.items():
            if arr[k].shape != s:
                raise CacheError(f"single-scattering array {prefix + k} has shape {arr[k].shape}, expected {s}")
        if centers.ndim != 2 or centers.shape[1] != 3:
            raise CacheError(f"single-scattering centres have shape {centers.shape}")
        start = get("cell_start").astype(np.int64)
        items = get("cell_items").astype(np.int32)
        dims = arr["grid_dims"].astype(np.int64)
        if start.shape != (int(np.prod(dims)) + 1,) or start[-1] != len(items) or np.any(np.diff(start) < 0):
            raise CacheError("single-scattering cell lists are inconsistent with the grid")
        if len(items) and (items.min() < 0 or items.max() >= n):
            raise CacheError("single-scattering cell lists index missing samples")
        if prefix + "sh_env" in d:
            arr["sh_env"] = get("sh_env")
            if arr["sh_env"].shape != shapes["sh"]:
                raise CacheError(f"single-scattering array {prefix}sh_env has shape {arr['sh_env'].shape}, "
                                 f"expected {shapes['sh']}")
        if prefix + "extinction" in d:
            arr["extinction"] = get("extinction")
            want = tuple(int(v) for v in arr["voxel_shape"]) + (3,)
            if arr["extinction"].shape != want:
                raise CacheError(f"single-scattering array {prefix}extinction has shape {arr['extinction'].shape}, "
                                 f"expected {want}")
        if prefix + "albedo" in d:
            arr["albedo"] = get("albedo")
            if arr["albedo"].shape != (n, 3):
                raise CacheError(f"single-scattering array {prefix}albedo has shape {arr['albedo'].shape}, "
                                 f"expected {(n, 3)}")
        for k in ("centers", "sigma", "weight", "support", "sigma_s", "sh", "sh_env", "extinction", "albedo"):
            if k not in arr and k != "centers":
                continue
            a = centers if k == "centers" else arr[k]
            if not np.all(np.isfinite(a)):
                raise CacheError(f"single-scattering array {prefix + k} contains NaN or Inf")
        if "extinction" in arr and np.any(arr["extinction"] < 0):
            raise CacheError(f"single-scattering array {prefix}extinction is negative")
        if "albedo" in arr and (np.any(arr["albedo"] < 0) or np.any(arr["albedo"] > 1)):
            raise CacheError(f"single-scattering array {prefix}albedo is outside [0, 1]")
        grid = SampleGrid(origin=arr["grid_origin"].astype(np.float64), cell_size=float(meta["cell_size"]), dims=dims,
                          cell_start=start, cell_items=items)
        return cls(centers=centers, sigma=arr["sigma"].astype(np.float64), weight=arr["weight"].astype(np.float64),
                   support=arr["support"].astype(np.float64), poisson_radius=arr["poisson_radius"].astype(np.float64),
                   sigma_s=arr["sigma_s"].astype(np.float64), sh=arr["sh"].astype(np.float32), order=order,
                   n_dirs=int(meta["n_dirs"]), mm_per_unit=float(meta["mm_per_unit"]), grid=grid,
                   voxel_origin=arr["voxel_origin"].astype(np.float64), voxel_size=float(meta["voxel_size"]),
                   voxel_shape=arr["voxel_shape"].astype(np.int64), stats=dict(meta.get("stats", {})),
                   sh_env=arr["sh_env"].astype(np.float32) if "sh_env" in arr else None,
                   entry_eta=float(meta.get("entry_eta", 1.0)),
                   extinction=arr["extinction"].astype(np.float32) if "extinction" in arr else None,
                   albedo=arr["albedo"].astype(np.float64) if "albedo" in arr else None)

    # ------------------------------------------------------------------ GPU
    def kernel_arrays(self) -> dict:
        """float32/uint32 arrays in the layout a GLSL kernel reads from 2D textures.

        * ``samples`` (N, 8): centre xyz, a_i, weight_i, support_i, 0, 0 (two RGBA texels per sample)
        * ``sigma_s`` (N, 4): RGB, 0
        * ``sh`` (N, K, 4): RGB coefficient k, 0 (K RGBA texels per sample)
        * ``cell_start`` (n_cells + 1,) uint32, ``cell_items`` (n_entries,) uint32
        * ``grid`` (8,): origin xyz, cell size, dims xyz, 0
        """
        n = self.n_samples
        samples = np.zeros((n, 8), dtype=np.float32)
        samples[:, :3] = self.centers
        samples[:, 3] = self.alpha
        samples[:, 4] = self.weight
        samples[:, 5] = self.support
        ss = np.zeros((n, 4), dtype=np.float32)
        ss[:, :3] = self.sigma_s
        sh = np.zeros((n, self.sh.shape[1], 4), dtype=np.float32)
        sh[..., :3] = self.sh
        g = np.zeros(8, dtype=np.float32)
        g[:3] = self.grid.origin
        g[3] = self.grid.cell_size
        g[4:7] = self.grid.dims
        return {"samples": samples, "sigma_s": ss, "sh": sh, "grid": g,
                "cell_start": self.grid.cell_start.astype(np.uint32), "cell_items": self.grid.cell_items.astype(np.uint32)}
