"""Voxel Number Map bake: composite object -> voxels -> numbered surface voxels -> chord LUT.

Stages (``progress(fraction, stage)``; it may raise, e.g. ``BakeCancelled``):

``resolution``  choose the grid so the surface-voxel count meets the target (auto) or check the budget
``voxelise``    the voxeliser of the single-scattering pass, on the whole assembly
                (:func:`~translucency_addon.single_scattering.volume.voxelise_composite`)
``surface``     extract and number the surface voxels (:mod:`.surface`)
``lut``         chord lengths per component medium between every pair (:mod:`.lut`)
``visibility``  sky visibility of every surface voxel (environment light)

**Budget.**  The LUT grows with the square of the surface-voxel count n:
``n (n + 1)/2 x (2 C + 1/8)`` bytes stored (C component media), and the CPU
run time keeps a packed float32 kernel of ``6 n (n + 1)`` bytes per
material.  ``max_surface_voxels`` (default 4,096: a 34 MB LUT for two media
and a 100 MB kernel) bounds it: with ``resolution="auto"`` the grid is
coarsened until it fits and the bake says so (``stats["warnings"]``); an
explicit resolution beyond it is refused with the numbers
(:class:`~translucency_addon.errors.MeshError`).  ``bench/voxel_number_map.py``
measures memory, precompute and frame time against n.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import CacheError, MeshError
from ..single_scattering.volume import grid_for_mesh, resolution_for, voxelise_composite
from . import lut as lutmod
from .surface import SurfaceVoxels, extend_into_surface_voxels, extract_surface_voxels, sky_visibility, vertex_weights

FORMAT_VERSION = 1
QUALITY_SURFACE_VOXELS = {"draft": 800, "preview": 2000, "final": 3500}
MAX_SURFACE_VOXELS = 4096
# Component kinds: the outer material's medium A, its medium B (field-mixed), an inner medium part.
OUTER_A, OUTER_B, PART = 0, 1, 2


@dataclass(frozen=True)
class VNMSettings:
    quality: str = "preview"  # target surface-voxel count of "auto": draft 800, preview 2000, final 3500
    resolution: object = "auto"  # "auto" or voxels along the longest side (8..512)
    surface_voxels: int | None = None  # explicit target for "auto" (overrides quality)
    max_surface_voxels: int = MAX_SURFACE_VOXELS
    step: float = 0.5  # chord sampling step, voxels
    env_directions: int = 64  # sky-visibility directions per surface voxel (0: no environment term)
    vertex_map_k: int = 6

    def validated(self) -> "VNMSettings":
        if self.quality not in QUALITY_SURFACE_VOXELS:
            raise MeshError(f"unknown quality {self.quality!r}; choose one of {', '.join(QUALITY_SURFACE_VOXELS)}")
        if self.resolution != "auto":
            try:
                resolution_for(self.resolution)
            except (TypeError, ValueError) as exc:  # a refusal by name, as every other setting's (was a ValueError)
                raise MeshError(f"Voxel Number Map: {exc}") from None
        if not 0.05 <= float(self.step) <= 1.0:
            raise MeshError(f"the chord step must be in [0.05, 1] voxels, got {self.step}")
        if int(self.max_surface_voxels) < 16:
            raise MeshError(f"max_surface_voxels must be at least 16, got {self.max_surface_voxels}")
        if self.env_directions and not 8 <= int(self.env_directions) <= 1024:
            raise MeshError(f"env_directions must be 0 or in [8, 1024], got {self.env_directions}")
        return self

    @property
    def target(self) -> int:
        return int(self.surface_voxels or QUALITY_SURFACE_VOXELS[self.quality])


@dataclass
class VoxelNumberMap:
    """The baked map: numbered surface voxels, their chord LUT and the outer mesh's vertex mapping."""

    origin: np.ndarray  # (3,) grid origin, object units
    h: float  # voxel edge, object units
    shape: tuple
    surface: SurfaceVoxels
    lengths: np.ndarray  # (C, n(n+1)/2) float16, voxel units
    blocked: np.ndarray  # packbits of (n(n+1)/2,) bool
    component_names: tuple
    component_kind: np.ndarray  # (C,) OUTER_A / OUTER_B / PART
    component_sigma_a: np.ndarray  # (C, 3) per mm for PART components (NaN for the outer material's)
    component_sigma_s: np.ndarray
    mesh_vertices: np.ndarray  # the outer mesh (object units)
    mesh_faces: np.ndarray
    mesh_normals: np.ndarray
    vertex_map: tuple  # (idx (n_v, k), w (n_v, k)) into surface voxels
    env_directions: np.ndarray  # (D, 3)
    env_visible: np.ndarray  # packbits of (n, D) bool
    mm_per_unit: float
    key: str
    stats: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.surface.n

    @property
    def n_components(self) -> int:
        return int(len(self.component_kind))

    @property
    def lut_bytes(self) -> int:
        return int(self.lengths.nbytes + self.blocked.nbytes)

    def visible(self) -> np.ndarray:
        D = len(self.env_directions)
        return np.unpackbits(self.env_visible, count=self.n * D).reshape(self.n, D).astype(bool)

    def coefficients(self, material):
        """Per-component (sigma_a, sigma_s) (C, 3): the outer material's media, then the parts' own."""
        sa = np.array(self.component_sigma_a, dtype=np.float64)
        ss = np.array(self.component_sigma_s, dtype=np.float64)
        for kind, medium in ((OUTER_A, material.medium_a), (OUTER_B, material.medium_b)):
            sel = self.component_kind == kind
            if not sel.any():
                continue
            if medium is None:
                raise MeshError("this Voxel Number Map was baked for a field-mixed outer material (two media); "
                                "give a two-medium material or re-bake it")
            sa[sel], ss[sel] = (np.asarray(x, dtype=np.float64) for x in medium.arrays())
        if material.heterogeneous and not (self.component_kind == OUTER_B).any():
            raise MeshError("this Voxel Number Map was baked for a homogeneous outer material; re-bake it with "
                            "the field that mixes the two media")
        return sa, ss

    # ----------------------------------------------------------------- cache
    def to_arrays(self, prefix: str = "vnm/") -> dict:
        meta = {"h": float(self.h), "shape": [int(s) for s in self.shape], "names": list(self.component_names),
                "mm_per_unit": float(self.mm_per_unit), "key": self.key, "stats": self.stats}
        arrays = {
            "version": np.array([FORMAT_VERSION], dtype=np.int64),
            "meta_json": np.frombuffer(json.dumps(meta, sort_keys=True, default=float).encode("utf-8"), dtype=np.uint8),
            "origin": np.asarray(self.origin, dtype=np.float64),
            "voxel": self.surface.voxel.astype(np.int64), "position": self.surface.position,
            "normal": self.surface.normal, "area": self.surface.area,
            "lengths": self.lengths.astype(np.float16), "blocked": self.blocked.astype(np.uint8),
            "kind": self.component_kind.astype(np.int64), "sigma_a": self.component_sigma_a,
            "sigma_s": self.component_sigma_s, "mesh_V": self.mesh_vertices, "mesh_F": self.mesh_faces,
            "mesh_N": self.mesh_normals, "vmap_idx": self.vertex_map[0], "vmap_w": self.vertex_map[1],
            "env_dirs": self.env_directions, "env_visible": self.env_visible.astype(np.uint8),
        }
        return {prefix + k: v for k, v in arrays.items()}

    @classmethod
    def from_arrays(cls, d, prefix: str = "vnm/") -> "VoxelNumberMap":
        from ..single_scattering.data import read_prefixed

        get, meta = read_prefixed(d, prefix, "Voxel Number Map data", FORMAT_VERSION)
        pos = get("position").astype(np.float64)
        n = len(pos)
        kind = get("kind").astype(np.int64)
        C = len(kind)
        lengths = get("lengths")
        D = len(get("env_dirs"))
        V = get("mesh_V").astype(np.float64)
        idx = get("vmap_idx")
        want = {"voxel": (n,), "normal": (n, 3), "area": (n,), "lengths": (C, lutmod.n_pairs(n)),
                "blocked": ((lutmod.n_pairs(n) + 7) // 8,), "sigma_a": (C, 3), "sigma_s": (C, 3),
                "mesh_N": V.shape, "vmap_w": idx.shape, "env_visible": ((n * D + 7) // 8,)}
        for k, s in want.items():
            if get(k).shape != s:
                raise CacheError(f"Voxel Number Map array {prefix + k} has shape {get(k).shape}, expected {s}")
        if lengths.dtype != np.float16 or not np.all(np.isfinite(lengths)) or lengths.min(initial=0) < 0:
            raise CacheError("Voxel Number Map lengths are not finite non-negative float16 values")
        if idx.size and (idx.min() < 0 or idx.max() >= n) or len(idx) != len(V):
            raise CacheError("Voxel Number Map vertex mapping does not match its surface voxels")
        for k in ("position", "normal", "area", "mesh_V"):
            if not np.all(np.isfinite(get(k))):
                raise CacheError(f"Voxel Number Map array {prefix + k} contains NaN or Inf")
        surf = SurfaceVoxels(voxel=get("voxel").astype(np.int64), position=pos,
                             normal=get("normal").astype(np.float64), area=get("area").astype(np.float64))
        return cls(origin=get("origin").astype(np.float64), h=float(meta["h"]), shape=tuple(meta["shape"]),
                   surface=surf, lengths=lengths, blocked=get("blocked").astype(np.uint8),
                   component_names=tuple(meta["names"]), component_kind=kind,
                   component_sigma_a=get("sigma_a").astype(np.float64),
                   component_sigma_s=get("sigma_s").astype(np.float64), mesh_vertices=V,
                   mesh_faces=get("mesh_F").astype(np.int64), mesh_normals=get("mesh_N").astype(np.float64),
                   vertex_map=(idx.astype(np.int32), get("vmap_w").astype(np.float32)),
                   env_directions=get("env_dirs").astype(np.float64), env_visible=get("env_visible").astype(np.uint8),
                   mm_per_unit=float(meta["mm_per_unit"]), key=str(meta["key"]), stats=dict(meta.get("stats", {})))


def budget_message(n: int, C: int, limit: int) -> str:
    return (f"{n:,} surface voxels: the LUT would take {lutmod.lut_bytes(n, C) / 2**20:.0f} MiB ({C} media) and the "
            f"run-time kernel {lutmod.kernel_bytes(n) / 2**20:.0f} MiB, above the limit of {limit:,} surface voxels "
            f"({lutmod.lut_bytes(limit, C) / 2**20:.0f} MiB + {lutmod.kernel_bytes(limit) / 2**20:.0f} MiB)")


def choose_resolution(V, F, settings: VNMSettings, media: int = 2):
    """``(resolution, surface-voxel count, warnings)`` for the outer mesh (counts only; no voxelisation).

    ``media``: the object's component media, for the LUT size a refusal states (it said 2 whatever the object)."""
    s = settings
    warnings = []
    ext = float(np.ptp(np.asarray(V), axis=0).max())

    def count(res):
        origin, h, shape = grid_for_mesh(V, res)
        return extract_surface_voxels(V, F, origin, h, shape).n

    if s.resolution != "auto":
        res = resolution_for(s.resolution)
        n = count(res)
        if n > s.max_surface_voxels:
            fit = int(res * np.sqrt(s.max_surface_voxels / n))
            raise MeshError(f"Voxel Number Map at resolution {res}: {budget_message(n, media, s.max_surface_voxels)}; "
                            f"lower the resolution to about {fit} or use 'auto'")
        return res, n, warnings
    from ..geometry.meshio import triangle_areas

    area = float(triangle_areas(np.asarray(V), np.asarray(F)).sum())
    target = min(s.target, s.max_surface_voxels)
    res = int(np.clip(round(ext / np.sqrt(area / target)), 8, 512))
    n = count(res)
    for _ in range(4):  # the count is ~ area / h^2 times a shape factor: two corrections settle it
        new = int(np.clip(round(res * np.sqrt(target / max(n, 1))), 8, 512))
        if new == res:
            break
        res, n = new, count(new)
    while n > s.max_surface_voxels and res > 8:
        res = max(8, int(res * np.sqrt(s.max_surface_voxels / n) * 0.97))
        n = count(res)
        warnings.append(f"coarsened to resolution {res} ({n:,} surface voxels) to stay within the budget of "
                        f"{s.max_surface_voxels:,} surface voxels")
    if n > s.max_surface_voxels:
        raise MeshError(f"Voxel Number Map: {budget_message(n, media, s.max_surface_voxels)} even at resolution 8")
    return res, n, warnings


def map_key(composite, settings: VNMSettings, resolution: int, field_fingerprint: str = "") -> str:
    h = hashlib.sha256()
    h.update(f"translucency-vnm-{FORMAT_VERSION}|{resolution}|{settings.step}|{settings.env_directions}|"
             f"{settings.vertex_map_k}|{field_fingerprint}".encode())
    h.update(composite.key().encode())
    for p in composite.media_parts:
        h.update(json.dumps([list(p.medium.sigma_a), list(p.medium.sigma_s)]).encode())
    return h.hexdigest()


def bake_voxel_number_map(composite, settings: VNMSettings | None = None, *, mm_per_unit: float = 1.0,
                          progress=None, field_fingerprint: str = "") -> VoxelNumberMap:
    """Bake the Voxel Number Map of a :class:`~translucency_addon.scene.composite.CompositeObject`.

    Everything that can be refused (bad parts, overlaps, open cavities, the
    budget) is refused before the long stages; nothing is written here (the
    caller saves the result, atomically, with :func:`translucency_addon.cache.save_bake`).
    ``field_fingerprint``: identifies the outer material's mixing field (for a
    two-medium material), so a cache can tell when the field changed.
    """
    from ..geometry.meshio import vertex_normals
    from ..geometry.raycast import TriangleBVH
    from ..scene.sh import fibonacci_directions

    s = (settings or VNMSettings()).validated()
    t_all = time.perf_counter()
    times = {}

    def stage(name, frac=0.0):
        if progress is not None:
            progress(frac, name)

    V, F = composite.V, composite.F
    t0 = time.perf_counter()
    stage("resolution")
    media = (2 if composite.material.heterogeneous else 1) + len(composite.media_parts)  # the LUT's components
    res, n_est, warnings = choose_resolution(V, F, s, media)
    times["resolution"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stage("voxelise", 0.02)
    bvh = TriangleBVH(V, F)
    vol = voxelise_composite(composite, resolution=res, mm_per_unit=mm_per_unit, bvh=bvh)
    warnings += list(vol.labels.warnings)
    times["voxelise"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stage("surface", 0.1)
    surf = extract_surface_voxels(V, F, vol.origin, vol.h, vol.shape, bvh=bvh)
    comp = extend_into_surface_voxels(vol.components, vol.blocked, surf, vol.origin, vol.h)
    times["surface"] = time.perf_counter() - t0
    C = comp.shape[3]
    if surf.n > s.max_surface_voxels:  # the count is the one measured above; guard against drift anyway
        raise MeshError(f"Voxel Number Map: {budget_message(surf.n, C, s.max_surface_voxels)}")

    t0 = time.perf_counter()
    stage("lut", 0.12)
    U = (surf.position - vol.origin) / vol.h
    lengths, blocked = lutmod.build_lut(U, comp, vol.blocked, float(s.step),
                                        progress=lambda f: stage("lut", 0.12 + 0.78 * f))
    times["lut"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stage("visibility", 0.9)
    D = int(s.env_directions)
    dirs = fibonacci_directions(D) if D else np.zeros((0, 3))
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    vis = sky_visibility(surf, bvh, dirs, diag) if D else np.zeros((surf.n, 0), dtype=bool)
    normals = vertex_normals(V, F)
    vmap = vertex_weights(V, normals, surf, s.vertex_map_k)
    times["visibility"] = time.perf_counter() - t0

    mat = composite.material
    kind, sa, ss = [OUTER_A], [np.full(3, np.nan)], [np.full(3, np.nan)]
    if mat.heterogeneous:
        kind.append(OUTER_B)
        sa.append(np.full(3, np.nan))
        ss.append(np.full(3, np.nan))
    for p in composite.media_parts:
        kind.append(PART)
        sa.append(np.asarray(p.medium.sigma_a, dtype=np.float64))
        ss.append(np.asarray(p.medium.sigma_s, dtype=np.float64))
    stats = {
        "resolution": int(res), "voxels": [int(x) for x in vol.shape], "voxel_size": float(vol.h),
        "voxel_mm": float(vol.h * mm_per_unit), "surface_voxels": int(surf.n), "components": list(vol.component_names),
        "pairs": int(lutmod.n_pairs(surf.n)), "blocked_pairs": int(np.unpackbits(blocked).sum()),
        "lut_bytes": int(lengths.nbytes + blocked.nbytes), "kernel_bytes": int(lutmod.kernel_bytes(surf.n)),
        "time": {k: round(v, 4) for k, v in times.items()}, "seconds": round(time.perf_counter() - t_all, 4),
        "warnings": warnings, "settings": asdict(s), "parts": [[p.name, p.label] for p in composite.parts],
    }
    stage("done", 1.0)
    return VoxelNumberMap(origin=np.asarray(vol.origin, dtype=np.float64), h=float(vol.h), shape=tuple(vol.shape),
                          surface=surf, lengths=lengths, blocked=blocked, component_names=tuple(vol.component_names),
                          component_kind=np.asarray(kind, dtype=np.int64), component_sigma_a=np.asarray(sa),
                          component_sigma_s=np.asarray(ss), mesh_vertices=V, mesh_faces=F, mesh_normals=normals,
                          vertex_map=vmap, env_directions=dirs, env_visible=np.packbits(vis.reshape(-1)),
                          mm_per_unit=float(mm_per_unit), key=map_key(composite, s, res, field_fingerprint),
                          stats=stats)


def format_stats(vnm: VoxelNumberMap) -> str:
    st = vnm.stats
    t = st.get("time", {})
    lines = [f"Voxel Number Map: {vnm.n:,} surface voxels (grid {'x'.join(str(x) for x in st['voxels'])}, "
             f"voxel {st['voxel_mm']:.3g} mm), {vnm.n_components} media ({', '.join(vnm.component_names)}), "
             f"LUT {vnm.lut_bytes / 2**20:.1f} MiB, run-time kernel {st['kernel_bytes'] / 2**20:.1f} MiB, "
             f"{st['blocked_pairs']:,} of {st['pairs']:,} pairs blocked by opaque parts",
             "  seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in t.items()) + f"; total {st['seconds']:.2f}"]
    lines += [f"  warning: {w}" for w in st.get("warnings", [])]
    return "\n".join(lines)
