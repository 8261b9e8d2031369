"""Versioned bake cache: one ``.npz`` per object, read with ``allow_pickle=False``.

Layout: numeric arrays only.  Metadata (format version, key, settings,
statistics) is JSON stored as a ``uint8`` array, never a pickled object, so a
cache file that a .blend points to can never execute code.  Writes go to a
temporary file that is renamed into place (:func:`write_files`, also every
output of the command line), so a crash or a cancelled bake never leaves a
half-written cache under the real name; the file gets the umask's permissions,
as any file Blender writes (0644 under the usual umask 022), not
``mkstemp``'s 0600, so a farm worker running as another user, or a copy made
with ``cp -p`` or ``rsync -a``, can read it.

Errors (missing, truncated, corrupt, wrong version, stale key) raise
:class:`CacheError` with a message naming the file and the problem.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
import zlib

import numpy as np

from . import __version__
from .quadgraph.bake import Bake, BakeSettings
from .errors import CacheError
from .quadgraph.levels import GraphLevel

CACHE_FORMAT = 2  # 2: each level's tetrahedral mesh (deformation.py) is stored too
READABLE_FORMATS = (1, 2)  # a format-1 cache still solves; deforming it asks for a re-bake
MAGIC = "translucency-cache"


def _json_array(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj, sort_keys=True, default=_json_default).encode("utf-8"), dtype=np.uint8)


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _read_json(arr) -> dict:
    return json.loads(np.asarray(arr, dtype=np.uint8).tobytes().decode("utf-8"))


def bake_to_arrays(bake: Bake) -> dict:
    d: dict[str, np.ndarray] = {}
    for i, lv in enumerate(bake.levels):
        d.update(lv.to_arrays(f"L{i}/"))
    for i, (idx, w) in enumerate(bake.shepard):
        d[f"T{i}/idx"] = idx
        d[f"T{i}/w"] = w
    d["vmap/idx"], d["vmap/w"] = bake.vertex_map
    d["mesh/V"] = bake.mesh_vertices
    d["mesh/F"] = bake.mesh_faces
    if getattr(bake, "mesh_bvh_order", None) is not None:
        d["mesh/bvh_order"] = np.asarray(bake.mesh_bvh_order, dtype=np.int32)
    if getattr(bake, "surface_thickness", None) is not None:
        d["planner/thickness"] = np.asarray(bake.surface_thickness.values, dtype=np.float64)
        d["planner/thickness_digest"] = np.frombuffer(bake.surface_thickness.digest.encode(), dtype=np.uint8)
    d["mesh/N"] = bake.mesh_normals
    d["shadow/V"] = bake.shadow_vertices
    d["shadow/F"] = bake.shadow_faces
    meta = {
        "magic": MAGIC,
        "format": CACHE_FORMAT,
        "extension_version": __version__,  # who wrote it: named when another version cannot read it
        "key": bake.key,
        "mm_per_unit": bake.mm_per_unit,
        "settings": bake.settings.__dict__,
        "stats": bake.stats,
        "level_stats": [lv.stats for lv in bake.levels],
        "n_levels": len(bake.levels),
        "single_scattering": bake.single_scattering is not None,
        "sky": bake.sky is not None,
        "voxel_number_map": bake.voxel_number_map is not None,
        "composite": bake.composite is not None,
    }
    if bake.single_scattering is not None:
        d.update(bake.single_scattering.to_arrays(prefix="ss/"))
    if bake.sky is not None:
        d.update(bake.sky.to_arrays(prefix="sky/"))
    if bake.voxel_number_map is not None:
        d.update(bake.voxel_number_map.to_arrays(prefix="vnm/"))
    if bake.composite is not None:
        d.update(bake.composite.to_arrays(prefix="composite/"))
    if getattr(bake, "spectral_bounds", None):
        d.update({f"spectral/{k}": v for k, v in bake.spectral_bounds.items()})
    d["meta"] = _json_array(meta)
    return d


def save_bake(path, bake: Bake, etas=()) -> str:
    """Write ``bake`` to ``path`` atomically (its folder is created); returns the path.

    ``etas``: the indices of refraction whose half-space transport tables the cache keeps
    (``diffusion.split.transport_tables``; the material's, at bake time), so a cold frame of that
    eta -- every frame on a farm -- does not solve them again."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    arrays = bake_to_arrays(bake)
    if etas:
        from .diffusion.split import transport_tables

        for i, eta in enumerate(sorted({float(e) for e in etas})):
            arrays.update({f"split/{i}/{k}": v for k, v in transport_tables(eta).items()})
    write_files({path: lambda fh: write_npz(fh, arrays)})
    return path


def write_npz(fh, arrays: dict) -> None:
    """``np.savez_compressed`` at deflate level 1 (numpy's is zlib's default, 6): the same .npz format,
    read by ``np.load``; a 655 k-vertex bake writes in 1.4 s instead of 3.8 s for 4 % more bytes.
    Never pickles (``allow_pickle=False``: an object array is refused here, as on load)."""
    import zipfile

    with zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, a in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as out:
                np.lib.format.write_array(out, np.asanyarray(a), allow_pickle=False)


def umask_mode() -> int:
    """The mode a new file gets from the umask, ``0o666 & ~umask`` (0o644 under umask 022).

    The umask can only be read by setting it; it is set back at once (the
    process's umask is not changed by another thread in this add-on)."""
    old = os.umask(0)
    os.umask(old)
    return 0o666 & ~old


def write_files(writers: dict) -> list[str]:
    """Write several files all or nothing: ``{path: write(binary file object)}``.

    Each file is written to a temporary file in its own folder, flushed to
    disk, and only when every one of them is written are they renamed to their
    names and given the umask's mode (:func:`umask_mode`); if any write fails,
    the temporary files are removed and no file of the set is created or
    replaced.  Returns the paths."""
    mode = umask_mode()
    done: list[tuple[str, str]] = []
    try:
        for path, write in writers.items():
            path = os.fspath(path)
            folder = os.path.dirname(os.path.abspath(path))
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=os.path.splitext(path)[1], dir=folder)
            done.append((tmp, path))
            with os.fdopen(fd, "wb") as fh:
                write(fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, mode)
        for tmp, path in done:
            os.replace(tmp, path)
    except BaseException:  # any failure, Ctrl-C too: remove the temporary files, then re-raise
        for tmp, _ in done:
            if os.path.exists(tmp):
                os.remove(tmp)
        raise
    return [path for _, path in done]


def read_meta(path) -> dict:
    """Only the metadata of a cache (cheap; used to show stats and detect staleness)."""
    with _open(path) as z:
        return _meta(z, path)


def read_mesh_topology(path) -> tuple[int, np.ndarray]:
    """``(vertex count, triangles)`` of the baked mesh, without loading the graph: whether a mesh
    with other vertex positions is this bake deformed (the Blender side's staleness after a load)."""
    with _open(path) as z:
        _meta(z, path)
        try:
            return int(_member(z, "mesh/V", path).shape[0]), np.asarray(_member(z, "mesh/F", path), dtype=np.int64)
        except KeyError as exc:  # every damaged byte is _member's CacheError already
            raise CacheError(f"bake cache {path!r} is corrupt or truncated: {exc}") from exc


def _open(path):
    path = os.fspath(path)
    if not os.path.exists(path):
        raise CacheError(f"bake cache {path!r} does not exist (re-bake the object)")
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise CacheError(f"bake cache {path!r} cannot be read: {exc.strerror or exc}") from None
    if head != b"PK\x03\x04" and len(head) == 4:  # a zip's local header; shorter: truncated, said below
        raise CacheError(f"bake cache {path!r} is corrupt or truncated, or not a cache at all: it is not an .npz "
                         "archive (a cache is written by a bake: 'python -m translucency_addon bake' or the "
                         "add-on's Bake)")
    try:
        return np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError) as exc:
        raise CacheError(f"bake cache {path!r} is corrupt or truncated: {exc}") from exc


def _member(z, key: str, path) -> np.ndarray:
    """One array of an open cache, its CRC checked before a byte of it is parsed.

    ``NpzFile[key]`` parses the ``.npy`` header while it streams the member and checks the zip's
    CRC only at the end, so flipped bytes in a header surface as whatever the header parser
    raises (``tokenize.TokenError``, ``SyntaxError``, a huge allocation) instead of a CRC error.
    Reading the whole member first (``ZipFile.read`` verifies the CRC) turns every damaged byte
    into ``BadZipFile``, said as a corrupt cache.  ``KeyError`` (no such member) passes through.
    """
    if key not in z.files:
        raise KeyError(key)
    return _array_member(z.zip, key, path)


def _array_member(zf, key: str, path) -> np.ndarray:
    """:func:`_member` from a ``zipfile.ZipFile`` of the cache, the key known to be listed."""
    name = key + ".npy"
    if name not in zf.NameToInfo:  # a member that is not an array: no cache writes one
        raise CacheError(f"bake cache {os.fspath(path)!r} is corrupt or truncated: its member {key!r} is not an array")
    try:
        raw = zf.read(name)
        return np.lib.format.read_array(io.BytesIO(raw), allow_pickle=False)
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError) as exc:
        raise CacheError(f"bake cache {os.fspath(path)!r} is corrupt or truncated: {exc}") from exc


def _members(z, keys, path) -> dict:
    """``{key: _member(z, key, path)}`` for every key, read by a few threads, each with its own handle on the
    file (one ``ZipFile`` shared by threads raced in its overlap check), the members dealt out largest first:
    zlib inflates and checks CRCs without the GIL, so a 655 k-vertex cache (112 MB of arrays) loads in
    0.24-0.35 s on two cores instead of 0.54-0.67 s -- a farm reads the cache at every frame.  The same
    arrays; a damaged member raises :class:`CacheError` as when read alone."""
    from concurrent.futures import ThreadPoolExecutor

    size = {i.filename: i.file_size for i in z.zip.infolist()}
    keys = sorted(keys, key=lambda k: -size.get(k + ".npy", 0))
    workers = max(1, min(4, os.cpu_count() or 1, len(keys)))
    if workers == 1 or sum(size.values()) < PARALLEL_LOAD_BYTES:
        return {k: _member(z, k, path) for k in keys}
    groups, load = [[] for _ in range(workers)], [0] * workers
    for k in keys:  # the largest first, each to the least loaded reader
        g = load.index(min(load))
        groups[g].append(k)
        load[g] += size.get(k + ".npy", 0)

    def read(group):
        try:
            with zipfile.ZipFile(os.fspath(path)) as zf:
                return {k: _array_member(zf, k, path) for k in group}
        except (zipfile.BadZipFile, OSError) as exc:
            raise CacheError(f"bake cache {os.fspath(path)!r} is corrupt or truncated: {exc}") from exc

    out = {}
    with ThreadPoolExecutor(workers, thread_name_prefix="translucency-cache") as ex:
        for part in ex.map(read, groups):
            out.update(part)
    return out


PARALLEL_LOAD_BYTES = 8 * 1024 * 1024  # _members: smaller caches are read by one thread (a thread's start costs more)


def _meta(z, path) -> dict:
    try:
        meta = _read_json(_member(z, "meta", path))
    except KeyError as exc:
        raise CacheError(f"{path!r} is not a Translucency bake cache (no metadata)") from exc
    except (zipfile.BadZipFile, zlib.error, OSError, ValueError, EOFError, UnicodeDecodeError) as exc:
        raise CacheError(f"bake cache {path!r} is corrupt or truncated: {exc}") from exc
    if meta.get("magic") != MAGIC:
        raise CacheError(f"{path!r} is not a Translucency bake cache")
    if meta.get("format") not in READABLE_FORMATS:
        writer = meta.get("extension_version")
        by = f"Translucency {writer}" if writer else "a Translucency older than 0.1.0"
        raise CacheError(
            f"bake cache {path!r} has format version {meta.get('format')}, written by {by}; this version "
            f"(Translucency {__version__}) reads {', '.join(str(f) for f in READABLE_FORMATS)}. Install the same "
            "extension version on every machine that renders the file, or re-bake the object with this one"
        )
    return meta


def load_bake(path, expected_key: str | None = None) -> Bake:
    """Read a bake back.  ``expected_key`` (from :func:`bake.mesh_key`) detects a stale cache."""
    with _open(path) as z:
        meta = _meta(z, path)
        if expected_key is not None and meta["key"] != expected_key:
            raise CacheError(
                f"bake cache {os.fspath(path)!r} is stale: the mesh or the bake settings changed since it was "
                "written; re-bake the object"
            )
        arrays = _members(z, z.files, path)
    try:
        n = int(meta["n_levels"])
        levels = [GraphLevel.from_arrays(arrays, f"L{i}/", stats=meta["level_stats"][i]) for i in range(n)]
        shepard = [(arrays[f"T{i}/idx"], arrays[f"T{i}/w"]) for i in range(n - 1)]
        settings = BakeSettings(**meta["settings"])
        ss = None
        if meta.get("single_scattering"):
            from .single_scattering import SingleScatteringData

            ss = SingleScatteringData.from_arrays(arrays, prefix="ss/")
        sky = None
        if meta.get("sky"):
            from .diffusion.sky_visibility import SkyVisibility

            sky = SkyVisibility.from_arrays(arrays, n, len(arrays["mesh/V"]), prefix="sky/")
        vnm = None
        if meta.get("voxel_number_map"):
            from .voxel_number_map import VoxelNumberMap

            vnm = VoxelNumberMap.from_arrays(arrays, prefix="vnm/")
        comp = None
        if meta.get("composite"):
            from .inner_parts.bake import CompositeInfo

            comp = CompositeInfo.from_arrays(arrays, levels, prefix="composite/")
        bake = Bake(
            levels=levels, shepard=shepard, vertex_map=(arrays["vmap/idx"], arrays["vmap/w"]),
            mesh_vertices=arrays["mesh/V"], mesh_faces=arrays["mesh/F"], mesh_normals=arrays["mesh/N"],
            shadow_vertices=arrays["shadow/V"], shadow_faces=arrays["shadow/F"], settings=settings,
            mm_per_unit=float(meta["mm_per_unit"]), key=meta["key"], stats=meta["stats"],
            single_scattering=ss, sky=sky, voxel_number_map=vnm, composite=comp,
            mesh_bvh_order=arrays.get("mesh/bvh_order"),  # absent in caches written before it was kept
            surface_thickness=_kept_thickness(arrays),  # likewise: the planner measures it then
            spectral_bounds=_kept_bounds(arrays, path),  # likewise: the first frame runs Lanczos then
        )
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CacheError(f"bake cache {os.fspath(path)!r} is incomplete or inconsistent: {exc}") from exc
    _check_consistency(bake, path)
    _adopt_split_tables(arrays, path)
    return bake


def _kept_thickness(arrays: dict):
    """The planner's surface thickness the bake kept (``raycast.KeptThickness``), or None (older caches)."""
    if "planner/thickness" not in arrays:
        return None
    from .geometry.raycast import KeptThickness

    digest = bytes(np.asarray(arrays.get("planner/thickness_digest", np.zeros(0, np.uint8)), dtype=np.uint8))
    return KeptThickness(np.asarray(arrays["planner/thickness"], dtype=np.float64), digest.decode("ascii", "replace"))


def _kept_bounds(arrays: dict, path) -> dict | None:
    """The baked material's spectral bounds (``diffusion.baked_bounds``), or None (a bake without a material,
    or written before they were kept); a malformed record is a corrupt cache."""
    record = {k[len("spectral/"):]: v for k, v in arrays.items() if k.startswith("spectral/")}
    if not record:
        return None
    from .diffusion.baked_bounds import check_record

    why = check_record(record)
    if why:
        raise CacheError(f"bake cache {os.fspath(path)!r}: its kept spectral bounds are corrupt ({why}); "
                         "re-bake the object")
    return record


def _adopt_split_tables(arrays: dict, path) -> None:
    """Hand the transport tables the cache carries to ``diffusion.split`` (ignored when written by code of
    another table format; a corrupt table is a corrupt cache)."""
    from .diffusion.split import adopt_transport_tables

    for name in sorted(k for k in arrays if k.startswith("split/") and k.endswith("/key")):
        base = name[: -len("key")]
        try:
            key = bytes(np.asarray(arrays[name], dtype=np.uint8)).decode("utf-8")
            adopt_transport_tables(key, arrays[base + "M"], arrays[base + "c"], arrays.get(base + "M_beam"),
                                   arrays.get(base + "c_beam"))
        except (KeyError, ValueError, UnicodeDecodeError, TypeError) as exc:
            raise CacheError(f"bake cache {os.fspath(path)!r}: its half-space transport tables are corrupt ({exc}); "
                             "re-bake the object") from None


def _check_consistency(bake: Bake, path) -> None:
    """Reject caches whose arrays disagree with each other (hand-edited or damaged files)."""
    for i, lv in enumerate(bake.levels):
        N = lv.n_nodes
        shapes = {
            "position": (N, 3), "neighbors": (N, 4), "edge_length": (N, 4), "face_area": (N, 4),
            "volume": (lv.n_inner,), "normal": (lv.n_surface, 3), "area": (lv.n_surface,),
        }
        for name, shape in shapes.items():
            if getattr(lv, name).shape != shape:
                raise CacheError(f"bake cache {os.fspath(path)!r}: level {i} {name} has shape "
                                 f"{getattr(lv, name).shape}, expected {shape}")
        nb = lv.neighbors
        if nb.size and (nb.max() >= N or nb.min() < -1):
            raise CacheError(f"bake cache {os.fspath(path)!r}: level {i} has neighbour indices out of range")
        for name in ("position", "edge_length", "face_area", "volume", "normal", "area"):
            if not np.all(np.isfinite(getattr(lv, name))):
                raise CacheError(f"bake cache {os.fspath(path)!r}: level {i} {name} contains NaN or Inf")
        if (lv.tets is None) != (lv.tet_vertices is None) or lv.tets is not None and not (
                lv.tets.shape == (lv.n_inner, 4) and lv.tet_vertices.ndim == 2 and lv.tet_vertices.shape[1] == 3
                and lv.tets.min() >= 0 and lv.tets.max() < len(lv.tet_vertices)
                and np.all(np.isfinite(lv.tet_vertices))):
            raise CacheError(f"bake cache {os.fspath(path)!r}: level {i} tetrahedral mesh does not match its graph")
        if lv.sweep_order is not None:
            from .diffusion.sweeps import check_sweep_order

            why = check_sweep_order(lv.sweep_order, N, lv.n_inner)
            if why:
                raise CacheError(f"bake cache {os.fspath(path)!r}: level {i}'s sweep order {why}; re-bake the object")
    idx, w = bake.vertex_map
    if len(idx) != len(bake.mesh_vertices) or (idx.size and idx.max() >= bake.levels[-1].n_surface):
        raise CacheError(f"bake cache {os.fspath(path)!r}: vertex mapping does not match the mesh")
    if bake.mesh_bvh_order is not None:
        from .geometry.raycast import check_order

        try:
            check_order(bake.mesh_bvh_order, len(bake.mesh_faces))
        except ValueError as exc:
            raise CacheError(f"bake cache {os.fspath(path)!r}: the mesh's triangle tree does not match the mesh "
                             f"({exc}); re-bake the object") from None
    t = None if bake.surface_thickness is None else np.asarray(bake.surface_thickness.values)
    if t is not None and (t.shape != (bake.levels[-1].n_surface,) or not np.all(np.isfinite(t)) or np.any(t < 0)):
        raise CacheError(f"bake cache {os.fspath(path)!r}: the kept surface thickness does not match the finest "
                         f"level ({t.shape[0] if t.ndim else 0} values for {bake.levels[-1].n_surface} surface "
                         "nodes, or not finite and >= 0); re-bake the object")
    if bake.sky is not None and [s.n_surface for s in bake.sky.levels] != [lv.n_surface for lv in bake.levels]:
        raise CacheError(f"bake cache {os.fspath(path)!r}: sky visibility does not match the graph")
