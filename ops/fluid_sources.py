# SPDX-License-Identifier: GPL-3.0-or-later
"""A Fluid source's particles and the geometry its radiance goes onto, read from Blender (Kang & Kim 2013).

A fluid object (``object.translucency.source == 'FLUID'``) is the *target*:
the mesh or point cloud whose vertices or points get the radiance.  Its
particles come from the *source object* (``fluid_object``; empty: the target
itself), by ``fluid_kind``:

* ``PARTICLES``: a particle system of an emitter.  Read from the **evaluated**
  object (the original's ``particles`` is empty), alive and dying particles
  only; positions are in world space; the particle's index in the system is
  its id (it keeps the warm start).  Particles exist only inside the point
  cache's frame range and only once playback or a bake has run from its
  start frame: :func:`read_particles` says which, with the numbers, instead
  of failing.
* ``MANTAFLOW``: the FLIP particle system a liquid domain keeps (Physics >
  Fluid > Liquid), read like the above; Mantaflow renumbers its particles
  every step, so there are no ids (the engine warm-starts from the nearest
  previous particle).
* ``POINT_CLOUD``: a point-cloud object's evaluated points (object space).
* ``GEOMETRY_NODES``: the point-cloud component a Geometry Nodes object
  outputs (:func:`.compat.read_evaluated_pointcloud`).
  Both read an ``id`` point attribute as particle ids when there is one.

Everything is returned in the **target's object space** (the engine's space,
``docs/architecture.md``).  Problems the user can fix raise
:class:`ParticleError` naming the object and what to change; a source with
no particles at this frame is not an error (the fluid is not there: zero
radiance is right) and comes back with ``empty`` saying why.

:func:`read_output` reads the target's evaluated vertices (and triangles) or
points: what the radiance is interpolated onto.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import compat, scene_inputs

ALIVE_STATES = (3, 4)  # Particle.alive_state: DEAD 1, UNBORN 2, ALIVE 3, DYING 4


@dataclass(frozen=True)
class Particles:
    """One frame of a fluid's particles, in the target's object space."""

    points: np.ndarray  # (N, 3)
    ids: np.ndarray | None  # (N,) int64, or None when the source has none
    field: np.ndarray | None  # (N,) the mixing field's point attribute (ATTRIBUTE field), else None
    source: str  # what they are, for messages: "particle system 'P' of 'Emitter'"
    source_name: str  # the source object (left out of the occluders: an emitter must not shadow its fluid)
    empty: str = ""  # why there are no particles ('' when there are)

    @property
    def n(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class Output:
    """What the radiance goes onto: the target's evaluated vertices (with triangles) or points."""

    positions: np.ndarray  # (n, 3) object space
    faces: np.ndarray | None  # (m, 3) of a mesh; None for points
    kind: str  # "vertices" or "points"


def _error(message: str):
    from ..translucency_addon.errors import ParticleError

    return ParticleError(message)


def source_object(target):
    """The object the particles come from: the Source Object, or the target itself when it is empty."""
    return target.translucency.fluid_object or target


def _unset_note(target) -> str:
    if target.translucency.fluid_object is None:
        return (f" (the Source Object is empty, so '{target.name}' itself was used; if it was set, its object "
                "was deleted)")
    return ""


# ------------------------------------------------------------------ particles


def read_particles(target, scene, depsgraph, field_attribute: str | None = None) -> Particles:
    """The fluid's particles at the depsgraph's frame, in ``target``'s object space.

    ``field_attribute``: a point attribute to read as the mixing field (point-cloud sources only).
    Raises :class:`ParticleError` for a source of the wrong kind (naming what to pick instead).
    """
    settings = target.translucency
    src = source_object(target)
    kind = settings.fluid_kind
    to_target = np.linalg.inv(scene_inputs.matrix_to_numpy(target.evaluated_get(depsgraph).matrix_world))
    if kind in ('PARTICLES', 'MANTAFLOW'):
        if field_attribute:
            from ..translucency_addon.errors import MaterialError

            raise MaterialError("particle systems carry no point attributes for the heterogeneity field; use a "
                                "texture field, or a point-cloud source")
        psys, label, frames, ids_ok = (_particle_system(target, src) if kind == 'PARTICLES'
                                       else _liquid_particles(target, src))
        world, ids, empty = _legacy_particles(src, psys, depsgraph, scene.frame_current, label, frames)
        points = _transform(world, to_target)
        return Particles(points, ids if ids_ok else None, None, label, src.name, empty)
    if kind == 'POINT_CLOUD' and src.type != 'POINTCLOUD':
        raise _error(f"'{src.name}' is a {src.type.lower()} object, not a point cloud: choose a point-cloud object "
                     f"as the Fluid's Source Object, or another Particles kind{_unset_note(target)}")
    if kind == 'GEOMETRY_NODES' and src.type != 'POINTCLOUD' and not any(m.type == 'NODES' for m in src.modifiers):
        raise _error(f"'{src.name}' has no Geometry Nodes modifier: choose the object whose Geometry Nodes output "
                     f"the fluid's points{_unset_note(target)}")
    found = compat.read_evaluated_pointcloud(
        src.evaluated_get(depsgraph), depsgraph,
        lambda pc, matrix: (*_pointcloud_arrays(pc, field_attribute, src.name), matrix))
    label = f"points of '{src.name}'"
    if found is None:
        raise _error(f"'{src.name}' outputs no points: its Geometry Nodes must output a point cloud (e.g. Mesh to "
                     "Points, Distribute Points on Faces) for a Fluid source")
    local, ids, field, matrix = found
    points = _transform(local, to_target @ scene_inputs.matrix_to_numpy(matrix))
    empty = "" if len(points) else f"'{src.name}' has no points at frame {scene.frame_current}"
    return Particles(points, ids, field, label, src.name, empty)


def _transform(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _particle_system(target, src):
    """(evaluated-to-be particle system index, label, cache frames, ids usable) of a PARTICLES source."""
    systems = src.particle_systems
    if len(systems) == 0:
        raise _error(f"'{src.name}' has no particle system: choose the emitter as the Fluid's Source Object"
                     f"{_unset_note(target)}")
    wanted = target.translucency.fluid_particle_system
    index = systems.find(wanted) if wanted else 0
    if index < 0:
        names = ", ".join(f"'{p.name}'" for p in systems)
        raise _error(f"'{src.name}' has no particle system '{wanted}' (it has {names})")
    psys = systems[index]
    if psys.settings.type == 'HAIR':
        raise _error(f"particle system '{psys.name}' of '{src.name}' is hair, not an emitter: a fluid needs "
                     "emitted particles")
    cache = psys.point_cache
    return index, f"particle system '{psys.name}' of '{src.name}'", (cache.frame_start, cache.frame_end), True


def _liquid_particles(target, src):
    """The FLIP particle system of a Mantaflow liquid domain (index, label, cache frames, no ids)."""
    domain = next((m for m in src.modifiers if m.type == 'FLUID' and m.fluid_type == 'DOMAIN'), None)
    if domain is None:
        raise _error(f"'{src.name}' is not a Mantaflow domain: choose the liquid's domain object (the one with the "
                     f"Fluid modifier of type Domain){_unset_note(target)}")
    d = domain.domain_settings
    if d.domain_type != 'LIQUID':
        raise _error(f"'{src.name}' is a {d.domain_type.lower()} domain; a Fluid source needs a liquid domain")
    index = next((i for i, p in enumerate(src.particle_systems) if p.settings.type == 'FLIP'), -1)
    if index < 0:
        raise _error(f"the liquid domain '{src.name}' keeps no FLIP particles: turn on Physics > Fluid > Liquid > "
                     "Particles (FLIP) and bake the liquid again")
    return index, f"FLIP particles of the liquid domain '{src.name}'", (d.cache_frame_start, d.cache_frame_end), False


def _legacy_particles(src, index, depsgraph, frame, label, frames):
    """World positions and indices of the alive particles of ``src``'s ``index``-th system (evaluated)."""
    psys = src.evaluated_get(depsgraph).particle_systems[index]
    particles = psys.particles
    n = len(particles)
    none = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    first, last = (int(round(f)) for f in frames)
    if not first <= frame <= last:
        return (*none, f"no particles at frame {frame}: the cache of the {label} covers frames {first}-{last}, and "
                       "particles exist only there")
    if n == 0:
        if getattr(depsgraph, "mode", "VIEWPORT") == 'RENDER' and src.hide_render:
            raise _error(f"'{src.name}' is disabled in renders, so its particles are not evaluated there: enable it "
                         "in renders and hide the emitter itself with Object > Instancing > Show Instancer: Render")
        if getattr(depsgraph, "mode", "VIEWPORT") != 'RENDER' and src.hide_viewport:
            raise _error(f"'{src.name}' is disabled in viewports, so its particles are not evaluated there: enable it "
                         "and hide the emitter itself with Object > Instancing > Show Instancer: Viewport")
        return (*none, f"no particles at frame {frame}: the {label} has not been simulated up to this frame: play "
                       f"the animation from frame {first} (or bake its cache)")
    loc = np.empty(3 * n, dtype=np.float32)
    particles.foreach_get("location", loc)
    alive = np.empty(n, dtype=np.int32)
    particles.foreach_get("alive_state", alive)
    keep = np.isin(alive, ALIVE_STATES)
    if not keep.any():
        s = psys.settings
        return (*none, f"no particle of the {label} is alive at frame {frame} (it emits from frame "
                       f"{s.frame_start:g} to {s.frame_end:g}, each particle living {s.lifetime:g} frames)")
    return loc.reshape(-1, 3)[keep].astype(np.float64), np.nonzero(keep)[0].astype(np.int64), ""


def _pointcloud_arrays(pc, field_attribute, name):
    """Positions (object space), ``id`` and the field attribute of a (evaluated) point cloud."""
    n = len(pc.points)
    co = np.empty(3 * n, dtype=np.float32)
    pc.attributes["position"].data.foreach_get("vector", co)
    ids = None
    attr = pc.attributes.get("id")
    if attr is not None and attr.domain == 'POINT' and attr.data_type == 'INT' and n:
        raw = np.empty(n, dtype=np.int32)
        attr.data.foreach_get("value", raw)
        ids = raw.astype(np.int64)
    field = None
    if field_attribute:
        field = _point_attribute(pc, field_attribute, name)
    return co.reshape(-1, 3).astype(np.float64), ids, field


def _point_attribute(pc, attribute: str, name: str) -> np.ndarray:
    from ..translucency_addon.errors import MaterialError

    attr = pc.attributes.get(attribute)
    if attr is None or attr.domain != 'POINT':
        raise MaterialError(f"'{name}' has no point attribute {attribute!r} for the heterogeneity field")
    values = scene_inputs.attribute_values(attr, f"point attribute {attribute!r} of '{name}'")
    return np.clip(np.nan_to_num(values, nan=0.0), 0.0, 1.0)


def particle_field(settings, particles: Particles) -> np.ndarray | None:
    """The mixing weight (0..1) at every particle, or None for a homogeneous material.

    A texture is evaluated at the particles (target object space x Texture Scale), as at a mesh's graph
    nodes; an attribute field is the source's point attribute; a fluid has no vertex groups.
    """
    from ..translucency_addon.errors import MaterialError

    if not settings.use_heterogeneity:
        return None
    if settings.field_source == 'TEXTURE':
        tex = settings.field_texture
        if tex is None:
            raise MaterialError("Heterogeneous is on but no texture is chosen for the field")
        return scene_inputs.evaluate_texture(tex, particles.points * float(settings.field_scale))
    if settings.field_source == 'ATTRIBUTE':
        return particles.field
    raise MaterialError("a fluid's particles have no vertex groups; use a texture or a point attribute for the "
                        "heterogeneity field")


# ------------------------------------------------------------------ the geometry the radiance goes onto


def read_output(target, depsgraph) -> Output:
    """The target's evaluated vertices and triangles (a mesh, e.g. Mantaflow's liquid mesh), or its points.

    Raises :class:`ParticleError` when it has neither (nothing to carry the radiance).
    """
    ev = target.evaluated_get(depsgraph)
    if target.type == 'MESH':
        mesh = ev.to_mesh()
        try:
            V, F = scene_inputs.mesh_arrays(mesh)
        finally:
            ev.to_mesh_clear()
        if len(V):
            return Output(V, F, "vertices")
    found = compat.read_evaluated_pointcloud(ev, depsgraph,
                                             lambda pc, matrix: (_pointcloud_arrays(pc, None, target.name)[0], matrix))
    if found is not None and len(found[0]):
        local, matrix = found
        rel = np.linalg.inv(scene_inputs.matrix_to_numpy(ev.matrix_world)) @ scene_inputs.matrix_to_numpy(matrix)
        return Output(_transform(local, rel), None, "points")
    raise _error(f"'{target.name}' has no vertices or points at this frame to carry the fluid's radiance: point the "
                 "Fluid source at a mesh (e.g. the liquid's mesh) or a point cloud")
