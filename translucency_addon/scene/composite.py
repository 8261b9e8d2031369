"""Objects made of more than one thing: an outer mesh plus inner parts with roles (bpy-free).

Mochida et al. render translucent objects with **cavities and different
media inside** (wine in a bottle, a hollow in marble).  A
:class:`CompositeObject` is what the engine takes for such an object:

* the **outer mesh** ``(V, F)`` with its :class:`~.materials.Material`
  (the medium everywhere inside it that no inner part claims);
* **inner parts** (:class:`InnerPart`), each a closed mesh with one role:
  ``"medium"`` (another :class:`~.materials.Medium`: wine, a jade core),
  ``"cavity"`` (air: extinction 0) or ``"opaque"`` (a stone in jelly:
  extinction infinite).  :func:`parse_role` turns the CLI's / panel's
  text (a preset name, ``cavity`` or ``opaque``) into a role.

Defined behaviour (checked on the voxels of the bake by :func:`label_voxels`):

* **Nested parts**: a part that lies inside another (up to one voxel at
  their common boundary, so parts that *touch* from inside count as nested)
  wins where they overlap -- wine inside the bottle's air, a stone inside a
  jade core.  Any depth of nesting.
* **Touching parts**: parts that share only boundary voxels (their surfaces
  touch, the inside tests disagree within a voxel) keep their own voxels; the
  few shared ones go to the part listed first.
* **Overlapping parts** (they share interior voxels and neither contains the
  other): refused, :class:`~.errors.MeshError` naming both and the overlap.
* **Parts sticking out of the outer mesh**: the outer mesh bounds the object;
  a medium or opaque part is clipped to it and the number of voxels dropped
  is reported in :attr:`VoxelLabels.warnings`.  A part entirely outside is
  refused.  A **cavity** that reaches the outer surface (sticks out, or
  leaves no wall between itself and the outside at the voxel size) would be
  an open hole into the object, which the surface-to-surface transport
  cannot represent: refused, saying how to model it (a hole in the outer
  mesh) or what resolution would give its wall a voxel.
* **Bad part meshes** (NaN coordinates, flat, no triangles): the mesh check of
  :func:`.meshio.validate_mesh`, its message prefixed with the part's name.
* **Open or self-intersecting parts** (holes, triangles crossing each other):
  refused by :func:`check_part_closed` with the hole count and each boundary
  loop's edges, or the number of crossing triangle pairs; a part's inside
  would be undefined (an outer mesh with holes still bakes, closed by the
  tetrahedralizer).
* **A part given two roles** (listed twice, e.g. as cavity and as opaque, or
  a cavity that names a medium): refused before any work is done.

Nothing is written by this module; every refusal happens before a bake
starts writing, so a refused object leaves caches and scenes as they were.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from ..errors import MaterialError, MeshError, TranslucencyError
from .materials import Material, Medium, check_medium

ROLES = ("medium", "cavity", "opaque")


@dataclass(frozen=True)
class InnerPart:
    """One inner part: a closed mesh (object space of the outer mesh) and its role."""

    name: str
    V: np.ndarray
    F: np.ndarray
    role: str  # "medium" | "cavity" | "opaque"
    medium: Medium | None = None  # the part's medium when role == "medium"

    def __post_init__(self):
        if self.role not in ROLES:
            raise TranslucencyError(f"inner part {self.name!r}: unknown role {self.role!r}; "
                                    f"choose one of {', '.join(ROLES)}")
        if self.role == "medium":
            if self.medium is None:
                raise MaterialError(f"inner part {self.name!r} is a medium but has no coefficients")
            try:
                check_medium(self.medium)
            except MaterialError as exc:
                raise MaterialError(f"inner part {self.name!r}: {exc}") from None
        elif self.medium is not None:
            raise TranslucencyError(
                f"inner part {self.name!r} is given two roles: {self.role} and the medium "
                f"{self.medium.name!r}; a part is one medium, a cavity or opaque")

    @property
    def label(self) -> str:
        return self.medium.name if self.role == "medium" else self.role

    def geometry_hash(self) -> str:
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.V, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.F, dtype=np.int64).tobytes())
        return h.hexdigest()


def parse_role(text: str, name: str = "part"):
    """``(role, medium)`` from ``"cavity"``, ``"opaque"`` or a preset name (``"marble"``).

    Two roles at once (``"cavity+opaque"``, ``"opaque,marble"``) are refused.
    """
    from .materials import preset

    raw = str(text).strip()
    tokens = [t for t in raw.replace("+", ",").replace("/", ",").split(",") if t.strip()]
    if len(tokens) != 1:
        raise TranslucencyError(
            f"inner part {name!r}: {len(tokens)} roles given ({raw!r}); a part is exactly one medium "
            "(a preset name), 'cavity' or 'opaque'")
    role = tokens[0].strip().lower()
    if role in ("cavity", "opaque"):
        return role, None
    try:
        return "medium", preset(role)
    except MaterialError as exc:
        raise MaterialError(f"inner part {name!r}: {exc}; or use 'cavity' / 'opaque'") from None


@dataclass
class CompositeObject:
    """The outer mesh, its material and the inner parts (validated on construction).

    ``field``: for a heterogeneous outer material, ``field(points) -> [0, 1]``
    (object space) mixing its two media, as everywhere else in the engine.
    """

    V: np.ndarray
    F: np.ndarray
    material: Material
    parts: tuple = ()
    field: object = None

    def __post_init__(self):
        from ..geometry.meshio import validate_mesh

        self.V = np.asarray(self.V, dtype=np.float64)
        self.F = np.asarray(self.F, dtype=np.int64)
        try:
            validate_mesh(self.V, self.F)
        except MeshError as exc:
            raise MeshError(f"outer mesh: {exc}") from None
        self.parts = tuple(self.parts or ())
        names, seen = set(), {}
        for p in self.parts:
            if not isinstance(p, InnerPart):
                raise TranslucencyError(f"inner parts must be InnerPart, got {type(p).__name__}")
            key = p.geometry_hash()
            if key in seen:
                other = seen[key]
                what = (f"two roles ({other.label} as {other.name!r} and {p.label} as {p.name!r})"
                        if other.label != p.label else f"twice (as {other.name!r} and {p.name!r})")
                raise TranslucencyError(f"the same mesh is given {what}: a part is one medium, a cavity or "
                                        "opaque; remove one of them")
            seen[key] = p
            if p.name in names:
                raise TranslucencyError(f"two inner parts are named {p.name!r}; give each part its own name")
            names.add(p.name)
            try:
                report = validate_mesh(np.asarray(p.V), np.asarray(p.F))
            except MeshError as exc:
                raise MeshError(f"inner part {p.name!r}: {exc}") from None
            check_part_closed(p, report)
        if self.material.heterogeneous and self.field is None:
            raise MaterialError("the outer material mixes two media and needs a field to mix them")

    @property
    def cavities(self) -> list:
        return [p for p in self.parts if p.role == "cavity"]

    @property
    def opaque(self) -> list:
        return [p for p in self.parts if p.role == "opaque"]

    @property
    def media_parts(self) -> list:
        return [p for p in self.parts if p.role == "medium"]

    def key(self) -> str:
        """Hash of the geometry and the roles (what a Voxel Number Map or a bake depends on)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.V).tobytes())
        h.update(np.ascontiguousarray(self.F).tobytes())
        for p in self.parts:
            h.update(f"{p.name}|{p.role}|".encode())
            h.update(p.geometry_hash().encode())
        return h.hexdigest()

    def diffusion_mesh(self):
        """The mesh a QuadGraph bake tetrahedralises: the outer surface plus every cavity's surface
        turned inside out (fTetWild fills by winding number, so the hollow stays empty).

        Returns ``(V, F, n_outer_vertices)``; the outer mesh's vertices come first, unchanged.
        """
        Vs, Fs, off = [self.V], [self.F], len(self.V)
        for p in self.cavities:
            Vs.append(np.asarray(p.V, dtype=np.float64))
            Fs.append(np.asarray(p.F, dtype=np.int64)[:, [0, 2, 1]] + off)
            off += len(p.V)
        return np.concatenate(Vs), np.concatenate(Fs), len(self.V)

    def describe(self) -> str:
        parts = ", ".join(f"{p.name} ({p.label})" for p in self.parts) or "none"
        return f"outer mesh {len(self.V)} vertices, inner parts: {parts}"


def check_part_closed(part, report=None) -> None:
    """Refuse an inner part that does not bound a volume: open (holes) or crossing itself.

    An outer mesh with holes still bakes (fTetWild closes it by winding number),
    but a part's inside decides which voxels and graph nodes are its medium, a
    hollow or a stone, and an open or self-crossing surface has no inside: its
    labels would follow the rays that happen to leak.  Holes: the boundary loops
    of the welded mesh (``report.hole_edges``, :func:`.meshio.hole_loops`, the
    outer mesh's check).  Crossings: :func:`.meshio.self_intersections` (each
    edge cast against the part's own BVH; the docstring says what it misses).
    """
    from ..geometry.meshio import hole_loops, self_intersections

    loops = list(report.hole_edges) if report is not None else hole_loops(part.V, part.F)
    if loops:
        sizes = " and ".join([", ".join(str(k) for k in loops[:-1]), str(loops[-1])] if len(loops) > 1
                             else [str(loops[0])])
        raise MeshError(
            f"inner part {part.name!r} is open: {len(loops)} hole{'s' if len(loops) != 1 else ''} (boundary "
            f"loop{'s' if len(loops) != 1 else ''} of {sizes} edges); an inner part must be closed to have an "
            "inside: close it (in Blender: Mesh > Clean Up > Fill Holes) or remove it from the inner parts")
    pairs, point = self_intersections(part.V, part.F)
    if pairs:
        where = ", ".join(f"{x:.4g}" for x in point)
        raise MeshError(
            f"inner part {part.name!r} intersects itself: {pairs} pair{'s' if pairs != 1 else ''} of its triangles "
            f"cross (one crossing at ({where}) in the outer object's space), so its inside is not defined: "
            "separate or join the crossing pieces (in Blender: a Remesh modifier in Voxel mode, or the 3D-Print "
            "Toolbox's Intersections check to find them) or remove it from the inner parts")


def check_parts_against_outer(outer_bvh, parts, tol: float) -> list:
    """Where each part's vertices lie relative to the outer mesh: refusals and clipping warnings.

    A vertex counts as outside when it is outside the outer mesh by more than
    ``tol`` (object units; parts that touch the outer surface from inside are
    inside).  All outside: refused (or, if the part surrounds the outer mesh,
    refused as enclosing it).  Some outside: a cavity is an open hole
    (refused); a medium or opaque part is clipped (a warning with the share).
    """
    from ..geometry.raycast import inside_mesh

    warnings = []
    for p in parts:
        V = np.asarray(p.V, dtype=np.float64)
        dist = outer_bvh.closest_point(V)[2]
        out = ~inside_mesh(outer_bvh, V) & (dist > tol)
        n_out = int(out.sum())
        if n_out == 0:
            continue
        if n_out == len(V):
            lo, hi = outer_bvh.lo[0], outer_bvh.hi[0]
            if np.all(V.min(axis=0) <= lo) and np.all(V.max(axis=0) >= hi):
                raise MeshError(f"inner part {p.name!r} surrounds the outer mesh instead of lying inside it; "
                                "swap them (the outer mesh is the object's surface)")
            raise MeshError(f"inner part {p.name!r} lies entirely outside the outer mesh; "
                            "move it inside or remove it from the list")
        share = 100.0 * n_out / len(V)
        if p.role == "cavity":
            raise MeshError(
                f"cavity {p.name!r} sticks out of the outer mesh ({n_out} of its {len(V)} vertices, {share:.0f} %, "
                "lie outside): the hollow would be open to the air; cut the opening into the outer mesh instead, "
                "or move the cavity inside")
        warnings.append(f"inner part {p.name!r} sticks out of the outer mesh ({n_out} of its {len(V)} vertices, "
                        f"{share:.0f} %, lie outside): the part outside is ignored (clipped to the outer surface)")
    return warnings


@dataclass
class VoxelLabels:
    """Which part every voxel belongs to: 0 outside, 1 the outer medium, 2 + k inner part k."""

    label: np.ndarray  # (nx, ny, nz) int16
    order: list  # part indices in painting order (containers first)
    nested_in: dict  # part index -> index of the innermost part containing it (-1: the outer medium)
    warnings: list = field(default_factory=list)

    def mask(self, part: int) -> np.ndarray:
        return self.label == 2 + part


def label_voxels(outer_inside: np.ndarray, part_inside: list, parts, h_mm: float | None = None,
                 warnings=None, walls: bool = True) -> VoxelLabels:
    """Resolve nesting, touching, overlap and clipping into one label per voxel (module docstring).

    ``outer_inside``: bool grid, voxel centres inside the outer mesh;
    ``part_inside[k]``: the same for inner part ``parts[k]``;
    ``warnings``: those of :func:`check_parts_against_outer` (kept first).
    ``walls``: refuse a cavity without a voxel of wall to the outside (what
    the Voxel Number Map needs; a QuadGraph resolves thinner walls).
    Raises :class:`~.errors.MeshError` for the refused cases.
    """
    from scipy.ndimage import binary_dilation, binary_erosion

    outer = np.asarray(outer_inside, dtype=bool)
    ball = np.ones((3, 3, 3), dtype=bool)
    outer_grown = binary_dilation(outer, ball)
    warnings = list(warnings or ())
    inside = []
    where = f" (voxel {h_mm:.3g} mm)" if h_mm else ""
    for p, m in zip(parts, part_inside):
        m = np.asarray(m, dtype=bool)
        n = int(m.sum())
        if n == 0:
            raise MeshError(f"inner part {p.name!r} holds no voxel centre at this resolution{where}: it is "
                            "smaller than a voxel; raise the resolution or leave it out")
        out = m & ~outer
        n_out = int(out.sum())
        if n_out == n:
            raise MeshError(f"inner part {p.name!r} lies entirely outside the outer mesh; "
                            "move it inside or remove it from the list")
        beyond = int((m & ~outer_grown).sum())  # beyond the one-voxel tolerance of a shared surface
        if beyond and p.role == "cavity":
            raise MeshError(
                f"cavity {p.name!r} sticks out of the outer mesh ({beyond} of its {n} voxels outside): the "
                "hollow would be open to the air; cut the opening into the outer mesh instead, or move it inside")
        if beyond and not any(repr(p.name) in w for w in warnings):
            warnings.append(f"inner part {p.name!r} sticks out of the outer mesh: {n_out} of its {n} voxels "
                            f"({100.0 * n_out / n:.1f} %) lie outside and are ignored (clipped to the outer surface)")
        inside.append(m & outer)

    K = len(inside)
    core = [binary_erosion(m, ball) for m in inside]
    grown = [binary_dilation(m, ball) for m in inside]
    contains = np.zeros((K, K), dtype=bool)  # contains[a, b]: part b lies inside part a
    for a in range(K):
        for b in range(K):
            if a == b or not (inside[a] & inside[b]).any():
                continue
            if not (inside[b] & ~grown[a]).any() and inside[b].sum() <= inside[a].sum():
                contains[a, b] = True
    for a in range(K):
        for b in range(a + 1, K):
            both = inside[a] & inside[b]
            if not both.any() or contains[a, b] or contains[b, a]:
                continue
            if (core[a] & inside[b]).any() and (inside[a] & core[b]).any():
                n_both = int(both.sum())
                raise MeshError(
                    f"inner parts {parts[a].name!r} and {parts[b].name!r} overlap ({n_both} voxels, "
                    f"{100.0 * n_both / min(inside[a].sum(), inside[b].sum()):.0f} % of the smaller) and neither "
                    "contains the other: make one lie inside the other, or separate them")
    depth = contains.sum(axis=0)  # how many parts contain each part
    # Containers first, contents over them; at equal depth the part listed first is painted last, so it
    # keeps the voxels it shares with a part it merely touches.
    order = sorted(range(K), key=lambda k: (depth[k], -k))
    label = np.where(outer, 1, 0).astype(np.int16)
    for k in order:
        label[inside[k]] = 2 + k
    nested_in = {}
    for k in range(K):
        holders = [a for a in range(K) if contains[a, k]]
        nested_in[k] = max(holders, key=lambda a: depth[a]) if holders else -1

    # a cavity needs a wall: no cavity voxel may touch a voxel outside the object
    outside_grown = binary_dilation(label == 0, np.array([[[0, 0, 0], [0, 1, 0], [0, 0, 0]],
                                                          [[0, 1, 0], [1, 1, 1], [0, 1, 0]],
                                                          [[0, 0, 0], [0, 1, 0], [0, 0, 0]]], dtype=bool))
    for k, p in enumerate(parts):
        if p.role != "cavity" or not walls:
            continue
        touching = int(((label == 2 + k) & outside_grown).sum())
        if touching:
            raise MeshError(
                f"cavity {p.name!r} touches the outer surface: {touching} of its voxels have no wall between "
                f"them and the outside{where}.  If the hollow is meant to be closed, its wall is thinner than a "
                "voxel: raise the resolution; if it is open, cut the opening into the outer mesh")
    return VoxelLabels(label=label, order=order, nested_in=nested_in, warnings=warnings)
