# SPDX-License-Identifier: GPL-3.0-or-later
"""Objects made of several parts on the Blender side: the list -> the engine's ``CompositeObject`` and back.

An object's Translucency settings list **inner parts** (``object.translucency.inner_parts``,
:class:`~.properties.TranslucencyInnerPart`): mesh objects, typically children, each a
medium (its own preset or coefficients), a cavity or opaque (Mochida et al.; the engine's
``translucency_addon.scene.composite``).  This module is what the bake operator, the cache check
and a frame's path call for them:

* **Bake** (main thread, before the job starts): :func:`gather_composite` reads every part's
  evaluated mesh and moves it into the outer object's space (outer ``matrix_world``
  inverted times the part's, evaluated; a mirroring transform flips the triangles so they
  stay outward), refusing an empty entry, a non-mesh, the object itself and an object
  listed twice (two roles) with a message naming them.  :func:`bake_key` is the key of the
  whole composite bake (the QuadGraph of the outer surface with the cavities carved, plus
  :meth:`CompositeObject.key` -- which the QuadGraph key alone misses for medium and opaque
  parts -- plus the Voxel Number Map's settings); :func:`record` is what the bake keeps in
  ``bake.stats["composite"]`` to say later *what* changed.
* **Staleness** (:func:`staleness`, :func:`parts_digest`): the evaluated outer mesh is
  compared with the outer vertices only (the bake's ``mesh_vertices`` continue with the
  cavity walls), the list with the baked names and roles, each part's mesh (in the outer
  object's space) with its baked digest: a moved or edited part makes the bake stale, with
  the part's name.
* **Run time**: the parts' media are read every frame (:func:`part_media`; a material change
  re-solves without a re-bake, as the outer material's does): :func:`diffusion_inputs` gives
  the diffusion solver its per-node media (``composite_bake.diffusion_material``),
  :func:`vnm_radiance` runs the Voxel Number Map (its transport placed by
  :func:`.backend.make_transmission`).  :func:`outer_mesh` and :func:`n_outer_vertices` are
  the outer mesh inside a composite bake (what the attribute, single scattering and the
  Voxel Number Map live on).

Nothing here keeps a ``bpy`` reference: parts are found through the object pointers of the
list each time, and the runtime state (:class:`~.state.ObjectState`) keeps only engine values.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, replace

import numpy as np

from . import backend, scene_inputs, state

ROLE_OF = {"MEDIUM": "medium", "CAVITY": "cavity", "OPAQUE": "opaque"}
RECORD = "composite"  # the key of bake.stats that holds :func:`record`
# The map's bake stages as the status bar shows them (the QuadGraph's and "cavity exchange" keep their names).
STAGE_NAMES = {"resolution": "Voxel Number Map: grid", "voxelise": "Voxel Number Map: voxelise",
               "surface": "Voxel Number Map: surface voxels", "lut": "Voxel Number Map: chord table",
               "visibility": "Voxel Number Map: sky visibility"}
FIELD_GRID = 64  # voxels along the longest side of the grid a mixing field is sampled on for the map


# ------------------------------------------------------------------ the list


def listed(obj) -> bool:
    """Whether the object lists inner parts (an object with parts bakes as a composite)."""
    return len(obj.translucency.inner_parts) > 0


def _entries(obj) -> list:
    """``[(item, part object, role)]`` of the list, refusing what cannot be a part (``TranslucencyError``)."""
    from ..translucency_addon.errors import MeshError, TranslucencyError

    out, seen = [], {}
    for i, item in enumerate(obj.translucency.inner_parts):
        part = item.object
        if part is None:
            raise MeshError(f"inner part {i + 1} of '{obj.name}' has no object: pick a mesh object or remove the "
                            "entry")
        if part.type != 'MESH':
            raise MeshError(f"inner part '{part.name}' of '{obj.name}' is not a mesh ({part.type.lower()})")
        if part.name == obj.name:
            raise MeshError(f"'{obj.name}' is listed as an inner part of itself; remove that entry")
        if not part.users_scene:
            raise MeshError(f"inner part '{part.name}' of '{obj.name}' is in no scene (deleted from it?): link it "
                            "back or remove the entry")
        role = ROLE_OF[item.role]
        if part.name in seen:
            other = seen[part.name]
            how = f"as {other} and as {role}" if other != role else f"twice as {role}"
            raise TranslucencyError(f"'{part.name}' is listed twice among the inner parts of '{obj.name}' ({how}): a "
                                    "part is one medium, a cavity or opaque; remove one entry")
        seen[part.name] = role
        out.append((item, part, role))
    return out


def _relative(obj, part, depsgraph) -> np.ndarray:
    """The part's object space -> the outer object's (4x4): outer ``matrix_world``^-1 @ the part's (evaluated)."""
    outer = scene_inputs.matrix_to_numpy(obj.evaluated_get(depsgraph).matrix_world)
    inner = scene_inputs.matrix_to_numpy(part.evaluated_get(depsgraph).matrix_world)
    return np.linalg.solve(outer, inner)


def part_mesh(obj, part, depsgraph) -> tuple[np.ndarray, np.ndarray]:
    """The part's evaluated mesh (modifiers applied, triangulated) in the outer object's space."""
    V, F = scene_inputs.evaluated_triangles(part, depsgraph)
    rel = _relative(obj, part, depsgraph)
    if np.linalg.det(rel[:3, :3]) < 0:  # a mirroring transform turns the triangles inside out
        F = F[:, [0, 2, 1]]
    return V @ rel[:3, :3].T + rel[:3, 3], F


def _mesh_digest(V, F) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(V, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(F, dtype=np.int64).tobytes())
    return h.hexdigest()


def gather_composite(obj, depsgraph, V, F, material, field=None):
    """The engine's ``CompositeObject`` of ``obj`` (its evaluated mesh ``(V, F)``) and its listed parts.

    Main thread.  ``field``: the outer material's mixing field (a sampled ``GridField``) when it
    mixes two media.  Raises ``TranslucencyError`` subclasses naming the part.
    """
    from ..translucency_addon.scene.composite import CompositeObject, InnerPart
    from ..translucency_addon.errors import MaterialError

    parts = []
    for item, part, role in _entries(obj):
        Vp, Fp = part_mesh(obj, part, depsgraph)
        medium = scene_inputs.build_medium(item, part.name) if role == "medium" else None
        parts.append(InnerPart(part.name, Vp, Fp, role, medium))
    solid = [p.name for p in parts if p.role != "cavity"]
    if material.heterogeneous and solid and obj.translucency.use_multiple_scattering:
        raise MaterialError(f"'{obj.name}' mixes two media and has medium or opaque inner parts "
                            f"({', '.join(solid)}): the diffusion pass cannot do both; use a homogeneous material, "
                            "turn Multiple Scattering off, or keep only cavities")
    return CompositeObject(V, F, material, parts, field=field)


def vnm_settings(settings):
    """The Voxel Number Map's ``VNMSettings`` of the object's settings (None when it is off)."""
    from ..translucency_addon.voxel_number_map import VNMSettings

    from ..translucency_addon.errors import MeshError

    if not settings.use_voxel_number_map:
        return None
    resolution = int(settings.vnm_resolution) or "auto"
    try:
        return VNMSettings(quality=settings.vnm_quality.lower(), resolution=resolution).validated()
    except ValueError as ex:
        raise MeshError(f"Voxel Number Map: {ex} (Map Resolution; 0 chooses it)") from None


def _vnm_record(vnm) -> dict | None:
    return None if vnm is None else {"quality": vnm.quality, "resolution": vnm.resolution}


def record(composite, vnm, field_fp=None) -> dict:
    """What a composite bake keeps in ``bake.stats["composite"]``: the outer mesh's digest, each part's
    name, role and mesh digest (outer object space), the map's settings, the field it was baked with."""
    return {"outer": _mesh_digest(composite.V, composite.F),
            "parts": [[p.name, p.role, _mesh_digest(p.V, p.F)] for p in composite.parts],
            "vnm": _vnm_record(vnm), "field": field_fp}


def bake_key(composite, settings, vnm, field_fp=None) -> str:
    """The key of a composite bake: the QuadGraph's (outer surface with the cavities carved), the
    composite's (every part's geometry and role: medium and opaque parts change no QuadGraph) and the
    map's settings.  The parts' media are not in it: they are read every frame."""
    from ..translucency_addon.quadgraph.bake import mesh_key

    V, F, _ = composite.diffusion_mesh()
    h = hashlib.sha256()
    h.update(f"translucency-composite|{mesh_key(V, F, settings)}|{composite.key()}|".encode())
    h.update(json.dumps(record(composite, vnm, field_fp), sort_keys=True).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class BakeInputs:
    """What a bake of an object with inner parts needs, gathered on the main thread (:func:`bake_inputs`)."""

    composite: object  # translucency_addon.scene.composite.CompositeObject
    vnm: object  # VNMSettings, or None without the map
    key: str  # :func:`bake_key`
    record: dict  # :func:`record`
    field_fp: str | None  # the mixing field's fingerprint, when the map depends on it


def bake_inputs(obj, depsgraph, V, F, settings) -> BakeInputs:
    """The composite, the map's settings and the key of a bake of ``obj`` (main thread; ``(V, F)`` its
    evaluated mesh, ``settings`` the ``BakeSettings``).  A mixing field is sampled here, on a grid of
    :data:`FIELD_GRID` voxels (Blender textures are read on the main thread only)."""
    s = obj.translucency
    material = scene_inputs.build_material(s)
    field = field_fp = None
    if material.heterogeneous:
        field_fp = scene_inputs.ss_field_fingerprint(obj, s, depsgraph)
        field = scene_inputs.ss_field_sampler(obj, s, depsgraph, V, FIELD_GRID)
    composite = gather_composite(obj, depsgraph, V, F, material, field)
    vnm = vnm_settings(s)
    fp = field_fp if vnm is not None else None
    return BakeInputs(composite, vnm, bake_key(composite, settings, vnm, fp), record(composite, vnm, fp), fp)


def bake(inputs: BakeInputs, settings, progress=None):
    """The engine's ``bake_composite`` (QuadGraph with the cavities carved, cavity exchange, node labels, the
    Voxel Number Map) under :func:`bake_key`, with :func:`record` in its stats.  Any thread."""
    from ..translucency_addon.inner_parts.bake import bake_composite
    from ..translucency_addon.errors import MeshError

    named = None if progress is None else (lambda f, stage: progress(f, STAGE_NAMES.get(stage, stage)))
    try:
        baked = bake_composite(inputs.composite, settings, inputs.vnm, progress=named,
                               field_fingerprint=inputs.field_fp or "")
    except MeshError as ex:  # the engine's 'auto' is the panel's Map Resolution 0
        raise MeshError(str(ex).replace("or use 'auto'", "or set Map Resolution to 0 (auto)")) from None
    return replace(baked, key=inputs.key, stats={**(baked.stats or {}), RECORD: inputs.record})


def bake_summary(bake) -> tuple[str, list]:
    """``(line, warnings)`` of a bake's inner parts and map for the bake status ('' and [] without parts)."""
    info = getattr(bake, "composite", None)
    if info is None:
        return "", []
    line = "Inner parts: " + ", ".join(f"{n} ({r})" for n, r in zip(info.names, info.roles))
    if info.exchange is not None:
        line += f"; cavity exchange between {info.exchange.m:,} wall nodes"
    vnm = getattr(bake, "voxel_number_map", None)
    warnings = []
    if vnm is not None:
        st = vnm.stats
        line += (f"; Voxel Number Map {vnm.n:,} surface voxels (voxel {st.get('voxel_mm', 0.0):.3g} mm), "
                 f"{vnm.n_components} media, LUT {vnm.lut_bytes / 2**20:.1f} MiB, {st.get('seconds', 0.0):.1f} s")
        warnings = [f"Voxel Number Map: {w}" for w in st.get("warnings", [])]
    return line, warnings


# ------------------------------------------------------------------ staleness


def _describe(parts) -> str:
    return ", ".join(f"{name} ({role})" for name, role in parts) or "none"


def staleness(obj, depsgraph, rec: dict | None, V, F) -> str:
    """Why the composite bake recorded as ``rec`` no longer matches the object ('' when it does).

    ``(V, F)``: the object's evaluated mesh now.  ``rec`` None: a bake without inner parts, stale
    only when parts were listed since.
    """
    from ..translucency_addon.errors import TranslucencyError

    if rec is None:
        if listed(obj):
            return "inner parts were added to the list since the bake; re-bake to include them"
        return ""
    if _mesh_digest(V, F) != rec["outer"]:
        return "the mesh changed since it was baked (modifiers included); re-bake to update the graph"
    try:
        entries = _entries(obj)
    except TranslucencyError as ex:
        return f"the inner parts cannot be baked as listed now ({ex})"
    baked = [(name, role) for name, role, _ in rec["parts"]]
    now = [(part.name, role) for _, part, role in entries]
    if baked != now:
        return f"the inner parts changed since the bake (baked: {_describe(baked)}; now: {_describe(now)}); re-bake"
    moved = [part.name for (_, _, digest), (_, part, _) in zip(rec["parts"], entries)
             if _mesh_digest(*part_mesh(obj, part, depsgraph)) != digest]
    if moved:
        names = ", ".join(f"'{n}'" for n in moved)
        return (f"inner part {names} moved or changed shape since the bake (relative to '{obj.name}'); re-bake to "
                "update the graph")
    want = _vnm_record(vnm_settings(obj.translucency))
    if want is not None and rec.get("vnm") is None:
        return "the Voxel Number Map is on but was not baked; re-bake to add it"
    if want is not None and want != rec["vnm"]:
        return (f"the Voxel Number Map settings changed (baked: {rec['vnm']['quality']}, resolution "
                f"{rec['vnm']['resolution']}); re-bake to apply them")
    return ""


def parts_digest(obj, depsgraph) -> str:
    """A cheap digest of what the parts' staleness depends on (positions, transforms, roles, the map's
    settings): :func:`.cache_files.update_staleness` re-checks only when it changes."""
    s = obj.translucency
    items = []
    for item in s.inner_parts:
        part = item.object
        if part is None or part.type != 'MESH':
            items.append((None, item.role))
            continue
        positions = scene_inputs.evaluated_positions(part, depsgraph)
        items.append((part.name, item.role, scene_inputs.array_digest(positions),
                      scene_inputs.array_digest(_relative(obj, part, depsgraph))))
    return repr((items, s.use_voxel_number_map, s.vnm_quality, int(s.vnm_resolution)))


def part_objects(obj) -> set:
    """Names of the listed parts' objects (they are inside the object: never its occluders)."""
    return {item.object.name for item in obj.translucency.inner_parts if item.object is not None}


# ------------------------------------------------------------------ run time


def n_outer_vertices(bake) -> int:
    """Vertices of the outer mesh (:func:`translucency_addon.frame.n_outer_vertices`)."""
    from ..translucency_addon.frame import n_outer_vertices as outer

    return outer(bake)


def outer_mesh(bake) -> tuple:
    """``(V, F, N)`` of the outer mesh of a bake (:func:`translucency_addon.frame.outer_mesh`)."""
    from ..translucency_addon.frame import outer_mesh as outer

    return outer(bake)


def part_media(obj) -> tuple | None:
    """The listed parts' roles and media now, ``((name, role, sigma_a, sigma_s), ...)`` (hashable;
    None for media of cavities and opaque parts); None when the object lists no part."""
    if not listed(obj):
        return None
    out = []
    for item in obj.translucency.inner_parts:
        if item.object is None:
            continue
        role = ROLE_OF[item.role]
        if role != "medium":
            out.append((item.object.name, role, None, None))
            continue
        m = scene_inputs.build_medium(item, item.object.name)
        out.append((item.object.name, role, tuple(map(float, m.sigma_a)), tuple(map(float, m.sigma_s))))
    return tuple(out)


def ss_inputs(media_now) -> dict:
    """What single scattering baked with the parts records of them (``extra_inputs`` of
    ``bake_single_scattering_for``): each part's role and medium, since its optical depth is made of them."""
    return {"parts": [[name, role, None if sa is None else list(sa), None if ss is None else list(ss)]
                      for name, role, sa, ss in media_now or ()]}


def ss_parts_staleness(data, media_now) -> list:
    """Why single scattering baked with the parts no longer matches their media (``[]`` when it does)."""
    baked = ((data.stats or {}).get("inputs") or {}).get("parts")
    if baked is None or media_now is None:
        return []
    now = ss_inputs(media_now)["parts"]
    if baked == now:
        return []
    changed = sorted({row[0] for row in baked if row not in now} | {row[0] for row in now if row not in baked})
    return [f"the inner parts' media changed ({', '.join(changed)})"]


def _media(bake, media_now) -> tuple:
    """Per baked part: ``(sigma_a, sigma_s)`` of a medium -- the settings' now, by part name (the baked
    ones for a part no longer listed as a medium) -- or None.  Raises ``MaterialError`` for absurd values."""
    from ..translucency_addon.errors import MaterialError
    from ..translucency_addon.scene.materials import Medium, check_medium

    info = bake.composite
    now = {name: (sa, ss) for name, role, sa, ss in media_now or () if role == "medium"}
    out = []
    for name, role, baked in zip(info.names, info.roles, info.media):
        if role != "medium":
            out.append(None)
            continue
        sa, ss = now.get(name, baked)
        try:
            check_medium(Medium(tuple(sa), tuple(ss), name))
        except MaterialError as ex:
            raise MaterialError(f"inner part '{name}': {ex}") from None
        out.append((tuple(sa), tuple(ss)))
    return tuple(out)


def diffusion_inputs(bake, material, field_values, media_now):
    """``(material, field_values)`` for the object's diffusion solver: for a composite bake the per-node
    media (``composite_bake.diffusion_material``) with the parts' media now; unchanged otherwise."""
    if getattr(bake, "composite", None) is None:
        return material, field_values
    from ..translucency_addon.inner_parts.bake import diffusion_material

    return diffusion_material(material, replace(bake.composite, media=_media(bake, media_now)), field_values)


def _map_with_media(bake, media_now):
    """The baked Voxel Number Map with the parts' media now (its LUT holds lengths per medium part)."""
    from ..translucency_addon.voxel_number_map.bake import PART

    vnm = bake.voxel_number_map
    sa, ss = np.array(vnm.component_sigma_a, dtype=np.float64), np.array(vnm.component_sigma_s, dtype=np.float64)
    rows = np.flatnonzero(np.asarray(vnm.component_kind) == PART)  # the medium parts, in the list's order
    for row, medium in zip(rows, [m for m in _media(bake, media_now) if m is not None]):
        sa[row], ss[row] = medium
    return replace(vnm, component_sigma_a=sa, component_sigma_s=ss)


def vnm_radiance(st, frame) -> np.ndarray:
    """The Voxel Number Map's radiance at ``obj.data``'s vertices, (n, 3) W/(m^2 sr) (Mochida et al.).

    The evaluator is kept in ``st`` per bake, scale and Solver setting and told about material changes;
    its transport runs where :func:`.backend.make_transmission` places it.  Off the main thread (a render
    job) a GPU transport gives way to BLAS for that frame; a GPU transport that fails is dropped for BLAS,
    with the reason in the log and the panel.
    """
    from ..translucency_addon.errors import TranslucencyError
    from ..translucency_addon.voxel_number_map import VoxelNumberMapEvaluator

    bake = st.bake
    key = (bake.key, round(frame.mm, 9), (frame.prefer or "AUTO").upper())
    inputs = (frame.material, frame.part_media)
    if st.vnm is None or st.vnm_key != key:
        if st.vnm is not None:
            backend.free_solver(st.vnm)
            st.vnm = None
        transmission, name, message = backend.make_transmission(bake.voxel_number_map, frame.prefer,
                                                                off_main=frame.off_main)
        st.vnm = VoxelNumberMapEvaluator(_map_with_media(bake, frame.part_media), frame.material,
                                         mm_per_unit=frame.mm, transmission=transmission)
        st.vnm_key, st.vnm_inputs, st.vnm_backend_message = key, inputs, message
        state.log(f"'{frame.name}': Voxel Number Map on the {name}" + (f" ({message})" if message else ""),
                  once_key=("vnm-backend", frame.name, name, message))
    elif st.vnm_inputs != inputs:
        ev = st.vnm
        ev.vnm = _map_with_media(bake, frame.part_media)
        transmission = ev.transmission
        if frame.off_main:  # no GPU context here: the coefficients reach a GPU transport on a later frame
            ev.transmission = None
        try:
            ev.set_material(frame.material)
        finally:
            ev.transmission = transmission
        st.vnm_inputs = None if frame.off_main and transmission is not None else inputs
    m = frame.mapping
    points = None if m.same else (m.positions, m.normals)
    t0 = time.perf_counter()
    rgb, st.vnm_backend = _evaluate(st, frame, points)
    st.vnm_seconds = time.perf_counter() - t0
    if not np.all(np.isfinite(rgb)):
        raise TranslucencyError(f"'{frame.name}': the Voxel Number Map produced NaN or Inf radiance")
    return rgb


def _evaluate(st, frame, points) -> tuple:
    """``(radiance, backend)`` of one frame of the map; the GPU transport only where it may run now."""
    from ..translucency_addon.errors import TranslucencyError

    ev = st.vnm
    transmission = ev.transmission
    args = (list(frame.lights), frame.environment, frame.view)
    kw = {"occluders": frame.occluders, "points": points}
    if transmission is not None and not frame.off_main:
        try:
            return np.asarray(ev.radiance(*args, **kw)), "GPU"
        except TranslucencyError:
            raise
        except Exception as ex:  # noqa: BLE001 - a driver or context failure: BLAS from now on
            st.vnm_backend_message = (f"the Voxel Number Map GPU transport failed ({type(ex).__name__}: {ex}); "
                                      "using BLAS")
            state.log(f"'{frame.name}': {st.vnm_backend_message}")
            backend.free_solver(transmission)
            ev.transmission = transmission = None
    ev.transmission = None  # off the main thread the GPU context is not current: BLAS for this frame
    try:
        return np.asarray(ev.radiance(*args, **kw)), "CPU"
    finally:
        ev.transmission = transmission
