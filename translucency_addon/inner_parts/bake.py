"""Bake and solve an object made of several parts: the glue between composite, QuadGraph, cavities and VNM.

:func:`bake_composite` is the one call the CLI and the Blender side make for
an object with inner parts:

1. the QuadGraph bake of ``CompositeObject.diffusion_mesh()`` -- the outer
   surface plus every cavity turned inside out, so each hollow is carved out
   of the graph (``cavity.py``);
2. the cavity exchange between each hollow's wall nodes (``cavity.py``);
3. the part of every node of every level (0: the outer medium, 1 + k: inner
   part k; ``raycast.inside_mesh``, innermost part winning as in
   ``composite.label_voxels``), for the per-node coefficients of
   :class:`CompositeMaterial`;
4. optionally the Voxel Number Map (``voxel_number_map``).

The result is an ordinary :class:`~.bake.Bake` with ``bake.composite``
(:class:`CompositeInfo`) and ``bake.voxel_number_map`` set; ``cache.py``
stores both.  :class:`CompositeMaterial` gives the diffusion solver each
node's coefficients: the outer material, a medium part's own, a strong
absorber inside an opaque part (``OPAQUE_SIGMA_A``: phi ~ 0 there, the stone
casts its shadow in the diffusion too).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from ..errors import CacheError, MaterialError

PARTS_CHECK_RESOLUTION = 48  # voxels along the longest side for the parts' checks of a bake without the VNM
OPAQUE_SIGMA_A = 1.0e3  # per mm: a mean free path of 1 um, phi vanishes within the first node of an opaque part


@dataclass
class CompositeInfo:
    """What a bake keeps of its inner parts: names, roles, media, node labels, the cavity exchange."""

    names: tuple
    roles: tuple  # "medium" | "cavity" | "opaque"
    media: tuple  # ((sigma_a, sigma_s) or None) per part
    labels: list  # per level (N_l,) int16: 0 outer medium, 1 + k part k
    n_outer_vertices: int
    exchange: object | None = None  # cavity.CavityExchange

    def to_arrays(self, prefix: str = "composite/") -> dict:
        meta = {"names": list(self.names), "roles": list(self.roles),
                "media": [None if m is None else [list(map(float, m[0])), list(map(float, m[1]))] for m in self.media],
                "n_outer_vertices": int(self.n_outer_vertices), "levels": len(self.labels),
                "exchange": self.exchange is not None}
        d = {f"{prefix}meta": np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)}
        for i, lab in enumerate(self.labels):
            d[f"{prefix}labels{i}"] = np.asarray(lab, dtype=np.int16)
        if self.exchange is not None:
            d.update(self.exchange.to_arrays(prefix=f"{prefix}cavity/"))
        return d

    @classmethod
    def from_arrays(cls, d, levels, prefix: str = "composite/") -> "CompositeInfo":
        from .cavity import CavityExchange

        try:
            meta = json.loads(bytes(np.asarray(d[f"{prefix}meta"], dtype=np.uint8)).decode("utf-8"))
            labels = [np.asarray(d[f"{prefix}labels{i}"], dtype=np.int16) for i in range(int(meta["levels"]))]
        except (KeyError, ValueError, UnicodeDecodeError) as exc:
            raise CacheError(f"the inner-part data is incomplete or corrupt: {exc}") from None
        n_parts = len(meta["names"])
        if len(labels) != len(levels) or any(lab.shape != (lv.n_nodes,) for lab, lv in zip(labels, levels)) or \
                any(lab.size and (lab.min() < 0 or lab.max() > n_parts) for lab in labels):
            raise CacheError("the inner-part labels do not match the graph")
        ex = CavityExchange.from_arrays(d, levels[-1].n_surface, prefix=f"{prefix}cavity/") if meta["exchange"] else None
        media = tuple(None if m is None else (tuple(m[0]), tuple(m[1])) for m in meta["media"])
        return cls(tuple(meta["names"]), tuple(meta["roles"]), media, labels, int(meta["n_outer_vertices"]), ex)

    def describe(self) -> str:
        return ", ".join(f"{n} ({r if m is None or r != 'medium' else 'medium'})"
                         for n, r, m in zip(self.names, self.roles, self.media)) or "none"


class CompositeMaterial:
    """Per-node coefficients of an object with inner parts, in the interface the diffusion solver uses
    (``coefficients(field_values, n)``, ``eta``): ``field_values`` are the node labels of
    :class:`CompositeInfo`."""

    heterogeneous = True

    def __init__(self, outer, info: CompositeInfo):
        if outer.heterogeneous and any(r != "cavity" for r in info.roles):
            raise MaterialError("a field-mixed outer material with medium or opaque inner parts is not supported by "
                                "the diffusion pass; use a homogeneous outer material (cavities alone are fine)")
        self.outer = outer
        self.info = info
        self.eta = outer.eta
        self.name = getattr(outer, "name", "")

    @property
    def medium_a(self):
        return self.outer.medium_a

    def bulk(self):
        return self.outer.bulk()

    def coefficients(self, field_values=None, n: int | None = None):
        lab = np.asarray(field_values, dtype=np.int64).reshape(-1)
        n = len(lab)
        sa, ss = (np.broadcast_to(a, (n, 3)).copy() for a in self.outer.medium_a.arrays())
        for k, (role, medium) in enumerate(zip(self.info.roles, self.info.media)):
            sel = lab == k + 1
            if not sel.any():
                continue
            if role == "medium":
                sa[sel], ss[sel] = np.asarray(medium[0]), np.asarray(medium[1])
            elif role == "opaque":
                sa[sel], ss[sel] = OPAQUE_SIGMA_A, 0.0
        return sa, ss


def diffusion_material(material, info: CompositeInfo | None, field_values=None):
    """``(material, field_values)`` for a ``DiffusionSolver`` of a bake with inner parts: the per-node media
    of :class:`CompositeMaterial` with the node labels when the object has medium or opaque parts, the
    material and its own field unchanged otherwise (cavities are carved out of the graph)."""
    if info is None or not any(r in ("medium", "opaque") for r in info.roles):
        return material, field_values
    return CompositeMaterial(material, info), info.labels


def node_labels(composite, points) -> np.ndarray:
    """0 for the outer medium, 1 + k inside part k (the innermost part containing the point wins)."""
    from ..geometry.raycast import TriangleBVH, inside_mesh

    P = np.asarray(points, dtype=np.float64)
    lab = np.zeros(len(P), dtype=np.int16)
    depth = np.full(len(P), -1)
    bvhs = [TriangleBVH(np.asarray(p.V, dtype=np.float64), np.asarray(p.F, dtype=np.int64)) for p in composite.parts]
    inside = [inside_mesh(b, P) for b in bvhs]
    for k in range(len(bvhs)):
        d = np.zeros(len(P), dtype=np.int64)  # how many other parts contain this point too: deeper wins
        for j in range(len(bvhs)):
            if j != k:
                d += inside[j] & inside[k]
        take = inside[k] & (d > depth)
        lab[take] = k + 1
        depth = np.where(take, d, depth)
    return lab


def bake_composite(composite, settings, vnm_settings=None, *, progress=None, field_fingerprint: str = ""):
    """QuadGraph + cavity exchange + node labels (+ Voxel Number Map) for a composite object (module docstring)."""
    from ..quadgraph.bake import bake_mesh
    from .cavity import build_cavity_exchange

    def sub(lo, hi):
        return None if progress is None else (lambda f, stage: progress(lo + (hi - lo) * float(f), stage))

    V, F, n_outer = composite.diffusion_mesh()
    vnm = None
    # Refusals (parts outside or overlapping, open cavities, the budget) come before the long QuadGraph bake.
    if vnm_settings is not None:
        from ..voxel_number_map import bake_voxel_number_map

        vnm = bake_voxel_number_map(composite, vnm_settings, mm_per_unit=settings.mm_per_unit,
                                    progress=sub(0.0, 0.3), field_fingerprint=field_fingerprint)
    elif composite.parts:
        from ..single_scattering.volume import voxelise_composite

        voxelise_composite(composite, resolution=PARTS_CHECK_RESOLUTION, mm_per_unit=settings.mm_per_unit,
                           walls=False)
    base = 0.3 if vnm is not None else 0.0
    bake = bake_mesh(V, F, settings, progress=sub(base, 0.9))
    exchange = None
    if composite.cavities:
        exchange = build_cavity_exchange(bake, composite, progress=None if progress is None
                                         else (lambda f: progress(0.9 + 0.05 * f, "cavity exchange")))
    labels = [node_labels(composite, lv.position) if composite.parts else np.zeros(lv.n_nodes, dtype=np.int16)
              for lv in bake.levels]
    media = tuple((tuple(p.medium.sigma_a), tuple(p.medium.sigma_s)) if p.role == "medium" else None
                  for p in composite.parts)
    bake.composite = CompositeInfo(tuple(p.name for p in composite.parts), tuple(p.role for p in composite.parts),
                                   media, labels, n_outer, exchange)
    bake.voxel_number_map = vnm
    if progress is not None:
        progress(1.0, "done")
    return bake


# -- command-line glue (kept here so __main__.py stays a list of options) ---------------------------------------

def composite_from_files(V, F, material, inner_specs, field=None):
    """A :class:`~.composite.CompositeObject` from the outer mesh and ``PART.obj:ROLE`` strings."""
    import os

    from ..scene.composite import CompositeObject, InnerPart, parse_role
    from ..errors import TranslucencyError
    from ..geometry.meshio import load_obj

    parts = []
    for spec in inner_specs or ():
        path, sep, role_text = str(spec).rpartition(":")
        if not sep or not path:
            raise TranslucencyError(f"--inner: expected PART.obj:ROLE (ROLE a preset name, cavity or opaque), "
                                    f"got {spec!r}")
        name = os.path.splitext(os.path.basename(path))[0]
        role, medium = parse_role(role_text, name)
        Vp, Fp = load_obj(path)
        parts.append(InnerPart(name, Vp, Fp, role, medium))
    return CompositeObject(V, F, material, parts, field=field)


class _OnBakeVertices:
    """A Voxel Number Map evaluator's orders-after-the-first queries (``rest_media``, ``weighted_radiance``)
    at the bake's vertices, as :func:`solve_voxel_number_map` returns its radiance."""

    def __init__(self, ev, n: int):
        self.ev, self.n = ev, int(n)

    def rest_media(self):
        return self.ev.rest_media()

    def weighted_radiance(self, weights):
        L_outer = self.ev.weighted_radiance(weights)
        L = np.zeros((self.n, 3))
        L[: len(L_outer)] = L_outer
        return L


def solve_voxel_number_map(bake, material, lights, environment, view=None, *, shadows=True, keep=None):
    """The Voxel Number Map's radiance at the bake's vertices (outer mesh first, 0 on cavity walls) and
    its statistics, for ``python -m translucency_addon solve``.  ``keep`` (a dict): its
    ``"voxel_number_map"`` entry becomes the evaluator at those vertices, for the frame's orders after the
    first (``frame.orders_after_the_first``)."""
    import time

    from ..voxel_number_map import VoxelNumberMapEvaluator

    vnm = bake.voxel_number_map
    t0 = time.perf_counter()
    ev = VoxelNumberMapEvaluator(vnm, material, mm_per_unit=bake.mm_per_unit)
    t1 = time.perf_counter()
    L_outer = ev.radiance(lights, environment, view, shadows=shadows)
    L = np.zeros((len(bake.mesh_vertices), 3))
    L[: len(L_outer)] = L_outer
    if keep is not None:
        keep["voxel_number_map"] = _OnBakeVertices(ev, len(L))
    seconds = {"prepare": t1 - t0, "frame": dict(ev.seconds), "total": time.perf_counter() - t0}
    seconds["frame"].pop("prepare", None)
    return L, {"enabled": True, "backend": ev.backend + " (BLAS)", "surface_voxels": vnm.n,
               "media": list(vnm.component_names), "lut_bytes": vnm.lut_bytes, "kernel_bytes": ev.kernel.nbytes,
               "seconds": seconds, "radiance_mean": L_outer.mean(axis=0).tolist()}
