# SPDX-License-Identifier: GPL-3.0-or-later
"""Bake cache files next to the .blend: where they live, loading them into the state, staleness.

A render farm shares the folder: paths are stored blend-relative when the
.blend is saved; an unsaved .blend uses the temporary folder and says so.
Every worker finds the cache through the stored path or, when that is not
there, from the copy packed into the .blend (:func:`pack_cache`, for
single-file farms), or by its file name in the scene's Cache Directory (a
cache baked before the .blend was saved where it is now; :func:`find_cache`).  A render only
reads caches; a missing one raises :class:`CacheError` naming the file, the
stored path and what to copy (:func:`missing_message`); the render's policy
is the scene's ``missing_cache_in_render`` (``handlers``).  A bake refuses a
directory it cannot write (:func:`unwritable`) before it starts.

Staleness tells a **pose** from a change: an evaluated mesh with the baked
vertices and polygons at other positions (an armature, shape keys, a lattice,
simple/mesh/surface deform, any modifier stack that keeps them, or moved
vertices) is the bake deformed, solved on the deformed graph
(:mod:`.deformation`), and is not stale; another vertex count or other
polygons (a subdivision added after the bake) is, and asks for a re-bake.
"""

from __future__ import annotations

import os
import re
import tempfile

import bpy
import numpy as np

from . import inner_parts, scene_inputs
from . import state
from .state import ObjectState, drop_state, get_state, log

DEFAULT_CACHE_DIRECTORY = "//translucency_cache/"


def cache_directory(scene) -> tuple[str, str | None]:
    """``(absolute directory, note)``.  A blend-relative directory of an unsaved
    .blend resolves to a temporary folder, and ``note`` says so."""
    directory = scene.translucency.cache_directory or DEFAULT_CACHE_DIRECTORY
    if directory.startswith("//") and not bpy.data.filepath:
        tmp = os.path.join(tempfile.gettempdir(), "translucency_cache")
        return tmp, (f"the .blend file is not saved, so the cache was written to the temporary folder "
                     f"{tmp}; save the .blend and bake again to keep the cache next to it")
    return os.path.normpath(bpy.path.abspath(directory)), None


def cache_file_name(obj_name: str, key: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", obj_name).strip("._") or "object"
    return f"{safe}_{key[:16]}.npz"


def stored_cache_path(abs_path: str) -> str:
    """The path as stored in the .blend: blend-relative when the .blend is saved."""
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(abs_path)
        except ValueError:  # another drive on Windows
            return abs_path
    return abs_path


def resolve_cache_path(obj) -> str:
    path = obj.translucency.cache_filepath
    return os.path.normpath(bpy.path.abspath(path)) if path else ""


def find_cache(obj) -> tuple[str, str]:
    """``(path, note)``: the object's cache file on this machine.

    The stored path when the file is there; otherwise the same file name in a
    scene's Cache Directory (the .blend and its cache folder copied together,
    a cache baked while the .blend was unsaved or saved elsewhere), with a
    ``note`` saying where it was found; otherwise the stored path (which then
    does not exist) and no note.  The file's key is checked when it loads.
    """
    path = resolve_cache_path(obj)
    if path and not os.path.exists(path) and packed_text(obj) is not None:
        return _from_packed(obj), f"using the cache of '{obj.name}' packed into the .blend ({path} is not here)"
    if not path or os.path.exists(path):
        return path, ""
    name = os.path.basename(path)
    for scene in [bpy.context.scene] + list(bpy.data.scenes):
        if scene is None or not hasattr(scene, "translucency"):
            continue
        directory, unsaved = cache_directory(scene)
        candidate = os.path.join(directory, name)
        if unsaved is None and os.path.exists(candidate):
            return candidate, (f"the cache of '{obj.name}' is not at {path} (the path the .blend stores); "
                               f"using {candidate} from the scene's Cache Directory")
    return path, ""


def missing_message(obj, path: str) -> str:
    """Why a render or solve on this machine has no cache for ``obj``, and what to copy."""
    stored = obj.translucency.cache_filepath
    where = (f"the .blend stores '{stored}', relative to the .blend in "
             f"{os.path.dirname(bpy.data.filepath) or '(unsaved)'}" if stored.startswith("//")
             else f"the .blend stores the absolute path '{stored}'")
    return (f"the bake cache of '{obj.name}' is not on this machine: {path} does not exist ({where}). "
            "Copy the cache folder together with the .blend (README, Render farms), or bake again here; "
            "a render never bakes")


PACKED_PREFIX = ".translucency_cache "  # a hidden Text datablock per packed cache (leading dot: hidden)


def packed_text(obj):
    """The Text datablock holding ``obj``'s packed cache, or None."""
    name = obj.translucency.packed_cache
    return bpy.data.texts.get(name) if name else None


def pack_cache(obj) -> tuple[str, int]:
    """Pack the object's cache file into the .blend (a hidden Text datablock, base64 in lines of 76 characters:
    Blender has no packed-file slot for arbitrary files).  Returns ``(text name, bytes packed)``; raises
    :class:`CacheError` when the cache is not on this machine."""
    import base64

    from ..translucency_addon.errors import CacheError

    path, _note = find_cache(obj)
    if not path or not os.path.isfile(path):
        raise CacheError(missing_message(obj, path) if path else f"'{obj.name}' is not baked yet: press Bake first")
    with open(path, "rb") as fh:
        data = fh.read()
    unpack_cache(obj)
    text = bpy.data.texts.new(PACKED_PREFIX + os.path.basename(path))
    text.from_string(base64.encodebytes(data).decode("ascii"))
    text.use_fake_user = True
    obj.translucency.packed_cache = text.name
    return text.name, len(data)


def unpack_cache(obj) -> bool:
    """Remove the object's packed cache from the .blend (the cache file is not touched)."""
    text = packed_text(obj)
    obj.translucency.packed_cache = ""
    if text is None:
        return False
    bpy.data.texts.remove(text)
    return True


def _from_packed(obj) -> str:
    """The packed cache written to this machine's temporary folder (once per content), or '' when not packed.

    A worker rendering a single .blend has no cache folder; the temporary folder is where a render may write.
    The bytes are checked like any cache file when they load (format, key, ``allow_pickle=False``)."""
    import base64
    import hashlib

    text = packed_text(obj)
    if text is None:
        return ""
    data = base64.decodebytes(text.as_string().encode("ascii"))
    folder = os.path.join(tempfile.gettempdir(), "translucency_packed")
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, hashlib.sha1(data).hexdigest()[:16] + "_" + text.name[len(PACKED_PREFIX):])
    if not os.path.isfile(path) or os.path.getsize(path) != len(data):
        from ..translucency_addon.cache import write_files

        write_files({path: lambda fh: fh.write(data)})  # all or nothing, with the umask's mode (not mkstemp's 0600)
    return path


def unwritable(directory: str) -> str:
    """Why a bake cannot write into ``directory`` ('' when it can): it, or the nearest existing folder
    above it that would hold it, is read-only for this user (file permissions or a read-only mount)."""
    probe = os.path.abspath(directory)
    while not os.path.isdir(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if os.access(probe, os.W_OK | os.X_OK):
        return ""
    what = (f"the cache directory {directory} is read-only" if probe == os.path.abspath(directory) else
            f"{probe} is read-only, so the cache directory {directory} cannot be created there")
    return (f"cannot write the bake cache: {what} for this user. Choose a writable Cache Directory "
            "(Scene > Translucency > Cache Directory; // means next to the .blend) or make it writable, then "
            "bake again; nothing was written")


def ensure_state(obj, retry: bool = False) -> ObjectState:
    """The object's state, loading its bake from the cache file when needed.

    Raises :class:`CacheError` (missing, truncated, stale, ...) with a message
    naming the file.  A failed load is remembered and not retried until the
    file, the key or ``retry`` changes.
    """
    from ..translucency_addon.cache import load_bake
    from ..translucency_addon.errors import CacheError

    with state.lock():
        st = get_state(obj)
        if st is not None:
            return st
        drop_state(obj.name)
        settings = obj.translucency
        path, found_note = find_cache(obj)
        if not path or not settings.bake_key:
            raise CacheError(f"'{obj.name}' is not baked yet: press Bake in the Translucency panel")
        try:
            mtime = os.path.getmtime(path)
        except OSError:
            mtime = None
        inputs = (path, settings.bake_key, mtime)
        failed = state.failed_load(obj.name)
        if failed is not None and failed[0] == inputs and not retry:
            raise CacheError(failed[1])
        try:
            if mtime is None:
                raise CacheError(missing_message(obj, path))
            bake = load_bake(path, expected_key=settings.bake_key)
        except CacheError as ex:
            state.remember_failed_load(obj.name, inputs, str(ex))
            raise
        state.count("loads")
        st = state.install_state(obj, bake, path)
        if found_note:
            log(f"'{obj.name}': {found_note}")
        log(f"loaded the bake of '{obj.name}' from {path}")
        return st


def check_cache(obj, depsgraph=None) -> str:
    """Look for the object's cache without loading it all; returns a status line.

    Used after a file load: reports a missing, unreadable or stale cache.
    """
    from ..translucency_addon.cache import read_meta
    from ..translucency_addon.errors import TranslucencyError

    settings = obj.translucency
    path, _note = find_cache(obj)
    if not path:
        return "Not baked"
    if not os.path.exists(path):
        return f"Cache problem: {missing_message(obj, path)}"
    try:
        meta = read_meta(path)
    except TranslucencyError as ex:
        return f"Cache problem: {ex}"
    if settings.bake_key and meta.get("key") != settings.bake_key:
        return (f"Stale cache: {path} holds another bake than this object's (key "
                f"{str(meta.get('key'))[:12]} != {settings.bake_key[:12]}); re-bake")
    if depsgraph is not None:
        from ..translucency_addon.quadgraph.bake import BakeSettings
        from ..translucency_addon.cache import read_mesh_topology

        try:
            baked = BakeSettings(**meta["settings"])
            stats = meta.get("stats") or {}
            message, _pose = _staleness(obj, depsgraph, stats.get("graph_key") or meta["key"], baked,
                                        read_mesh_topology(path), stats.get(inner_parts.RECORD))
        except Exception as ex:  # noqa: BLE001 - a status line must not raise
            message = f"could not compare the mesh with the bake ({type(ex).__name__}: {ex})"
        if message:
            return f"Stale: {message}"
    return f"Baked (cache found: {os.path.basename(path)})"


def same_polygons(baked_faces, faces) -> bool:
    """Whether two triangulations of meshes with the same vertices have the same polygons.

    Blender re-splits a polygon as it bends (a quad that turns concave takes its other diagonal),
    so a pose may triangulate differently from the bake.  A polygon's triangles are consecutive
    in both lists: every run of triangles that differ must cover the same vertices in both.
    """
    A, B = np.asarray(baked_faces), np.asarray(faces)
    if A.shape != B.shape:
        return False
    differ = np.any(A != B, axis=1)
    if not differ.any():
        return True
    edges = np.diff(np.concatenate([[0], differ.astype(np.int8), [0]]))
    for start, stop in zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]):
        if not np.array_equal(np.unique(A[start:stop]), np.unique(B[start:stop])):
            return False
    return True


def _staleness(obj, depsgraph, key: str, baked_settings, baked_mesh=None,
               composite: dict | None = None) -> tuple[str, np.ndarray | None]:
    """``(why the bake no longer matches the object ('' when it still does), the pose)``.

    ``key``: the QuadGraph key (``single_scattering.graph_key``: a bake holding
    single scattering has a combined key of its own).  ``baked_mesh``: the
    baked ``(vertex count, triangles)``; an evaluated mesh with those vertices
    and polygons (:func:`same_polygons`) at other positions is a pose, returned
    as its positions (object space, the baked order), and not stale.
    ``composite``: what a bake with inner parts recorded of them
    (``bake.stats["composite"]``): its outer mesh, parts and map are compared by
    :func:`.inner_parts.staleness` instead of the key (such a bake has no poses).
    """
    from dataclasses import replace

    from ..translucency_addon.quadgraph.bake import mesh_key

    V, F = scene_inputs.evaluated_triangles(obj, depsgraph)
    pose = None
    if composite is None and mesh_key(V, F, baked_settings) != key:
        if baked_mesh is None:
            return "the mesh changed since it was baked (modifiers included); re-bake to update the graph", None
        if len(V) != baked_mesh[0] or not same_polygons(baked_mesh[1], F):
            what = (f"{baked_mesh[0]:,} vertices baked, {len(V):,} now" if len(V) != baked_mesh[0] else
                    f"the same {len(V):,} vertices in other polygons ({len(baked_mesh[1]):,} triangles baked, "
                    f"{len(F):,} now)")
            return (f"the mesh changed since it was baked (modifiers included): {what}. A deformation (armature, "
                    "shape keys, lattice, deform modifiers) keeps the vertices and polygons and needs no re-bake; "
                    "this change of topology does: re-bake to update the graph"), None
        pose = V
    message = inner_parts.staleness(obj, depsgraph, composite, V, F)
    if message:
        return message, None
    s = obj.translucency
    wanted = replace(baked_settings, quality=s.quality.lower(), levels=int(s.levels))
    if (wanted.quality, wanted.levels) != (baked_settings.quality, baked_settings.levels):
        return (f"the bake settings changed (baked: {baked_settings.quality}, {baked_settings.levels} levels); "
                "re-bake to apply them"), pose
    return "", pose


def update_staleness(obj, st: ObjectState, depsgraph) -> str:
    """Re-check staleness when the evaluated geometry changed; cheap otherwise."""
    positions = scene_inputs.evaluated_positions(obj, depsgraph)
    digest = scene_inputs.array_digest(positions) + f"|{obj.translucency.quality}|{obj.translucency.levels}"
    if inner_parts.listed(obj) or st.bake.composite is not None:
        digest += "|" + inner_parts.parts_digest(obj, depsgraph)
    if digest != st.geometry_digest:
        st.geometry_digest = digest
        try:
            from ..translucency_addon.single_scattering import graph_key

            st.stale_message, st.pose = _staleness(obj, depsgraph, graph_key(st.bake), st.bake.settings,
                                                   (len(st.bake.mesh_vertices), st.bake.mesh_faces),
                                                   (st.bake.stats or {}).get(inner_parts.RECORD))
        except Exception as ex:  # noqa: BLE001 - a staleness check must not break the frame: it is reported as stale
            st.stale_message = f"could not compare the mesh with the bake ({type(ex).__name__}: {ex})"
            st.pose = None
        if st.stale_message:
            log(f"'{obj.name}': {st.stale_message}", once_key=("stale", obj.name, st.stale_message))
    return st.stale_message
