"""Spectral bounds a bake keeps, so that a cold frame of the baked material runs no Lanczos.

Chebyshev needs each level's interval ``[lambda_min, lambda_max]`` of ``D^-1 A`` (:mod:`.spectral`), and a
first frame pays for it: on the Final marble bunny (422k nodes on the finest level) 1.5 s of Lanczos and
0.4 s of the deflation check, of a first frame of ~6 s, once per material.  A farm renders every frame as a
first frame (one process per frame, nothing carried over), so every frame paid it.  When the bake knows the
material (``bake --material``, the add-on's bake), :func:`bounds_record` computes the bounds once and the
cache keeps them; :func:`adopt_bounds` hands them to a frame's systems.

Keyed by content: each level's record carries the digest of the system it was computed for (the graph's
links and the assembled coefficients, :func:`system_digest`), and a frame adopts it only for a system with
the same digest -- the same numbers bit for bit, so the frame runs exactly what it would have computed
(Lanczos is seeded: the same system gives the same bounds).  Another material, field, scale, scheme or a
pose of the bake assembles another system, and that frame computes its own bounds as before.  A level whose
deflation check found a leak-dominated graph (:func:`.spectral.deflation` not None) keeps only its bounds;
the frame builds the deflation itself.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import replace

import numpy as np

from .assembly import LevelSystem
from .spectral import deflation, spectral_bounds

FIELDS = ("digest", "lam_min", "lam_max", "no_deflation")


def system_digest(system: LevelSystem) -> bytes:
    """16-byte BLAKE2b of what the spectrum of ``D^-1 A`` depends on: the scheme, the link slots and the
    assembled diagonal and off-diagonal coefficients (fp64; ~50 ms for a 422k-node level)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(system.scheme.encode())
    for a in (system.nbr, system.diag, system.off):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.data)
    return h.digest()


def bounds_record(systems: list) -> dict:
    """The arrays a cache keeps for ``systems`` (coarse to fine): per level ``i``, ``{i}/digest`` (uint8),
    ``{i}/lam_min`` and ``{i}/lam_max`` (per channel) and ``{i}/no_deflation`` (the deflation check said no).
    Computes what a first frame would (:func:`.spectral.spectral_bounds`, :func:`.spectral.deflation`)."""
    out = {}
    for i, system in enumerate(systems):
        lam_min, lam_max = spectral_bounds(system)
        out[f"{i}/digest"] = np.frombuffer(system_digest(system), dtype=np.uint8).copy()
        out[f"{i}/lam_min"] = np.array(lam_min, dtype=np.float64)
        out[f"{i}/lam_max"] = np.array(lam_max, dtype=np.float64)
        out[f"{i}/no_deflation"] = np.array(deflation(system) is None)
    return out


def check_record(record: dict) -> str:
    """Why ``record`` (as read from a cache) is malformed, or ''."""
    levels = {k.split("/", 1)[0] for k in record}
    for i in sorted(levels):
        missing = [f for f in FIELDS if f"{i}/{f}" not in record]
        if missing:
            return f"level {i} lacks {', '.join(missing)}"
        lo, hi = (np.asarray(record[f"{i}/{f}"]) for f in ("lam_min", "lam_max"))
        if (lo.ndim != 1 or lo.shape != hi.shape or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi))
                or np.any(lo <= 0) or np.any(hi < lo) or np.asarray(record[f"{i}/digest"]).size != 16):
            return f"level {i}'s bounds are not 16-byte digest, 0 < lambda_min <= lambda_max"
    return ""


def adopt_bounds(systems: list, record: dict | None) -> int:
    """Set the kept bounds (and a 'no' of the deflation check) on each system whose digest matches its
    level's record; returns how many levels adopted them.  Systems that already have bounds are left as
    they are (a caller carried them, :func:`.deformation.frames.carry_spectral_bounds`)."""
    if not record:
        return 0
    adopted = 0
    for i, system in enumerate(systems):
        key = f"{i}/digest"
        if key not in record or system.lam_max is not None:
            continue
        lam_min = np.asarray(record[f"{i}/lam_min"], dtype=np.float64)
        if lam_min.shape != (system.diag.shape[1],):
            continue
        if bytes(np.asarray(record[key], dtype=np.uint8)) != system_digest(system):
            continue
        system.lam_min = lam_min.copy()
        system.lam_max = np.asarray(record[f"{i}/lam_max"], dtype=np.float64).copy()
        if bool(np.asarray(record[f"{i}/no_deflation"])):
            system.cache["deflation"] = None
        adopted += 1
    return adopted


def with_kept_bounds(bake, material, options=None):
    """``bake`` with the bounds of ``material``'s systems kept (:func:`bounds_record`; the bake command's and
    the add-on's bake).  Only where a frame assembles the same systems from the material alone: not for a
    heterogeneous material (a field's values at the nodes are the frame's to sample) nor for a bake with
    inner parts (its frames solve a medium per part), which are returned as they are.  The seconds it took
    join the bake's timings as "spectral bounds" (and its total)."""
    from .solver import DiffusionSolver  # the solver adopts kept bounds (this module): imported when called

    if material.heterogeneous or getattr(bake, "composite", None) is not None:
        return bake
    t0 = time.perf_counter()
    record = bounds_record(DiffusionSolver(bake, material, None, options).systems)
    stats = dict(bake.stats)
    seconds = time.perf_counter() - t0
    stats["timings"] = {**stats.get("timings", {}), "spectral bounds": round(seconds, 4)}
    stats["seconds"] = stats.get("seconds", 0.0) + seconds
    return replace(bake, spectral_bounds=record, stats=stats)
