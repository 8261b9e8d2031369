r"""Optical depth along chords between two points of the voxel field: the reflected chords of eq. 3 of
:mod:`.entry` (light reflected inside the object before it scatters).

For a segment from a to b, of length L (object units), with ``n = max(1, ceil(L / h))`` steps of at
most one voxel::

    tau(a, b) = (L s / n) sum_{k=0}^{n-1} sigma_t(v(a + (k + 1/2)/n (b - a)))                   (1)

per channel, in optical depths (``s`` mm per object unit), where ``v(x)`` is the voxel that holds x
(sigma_t 0 outside the grid): the midpoint rule on the voxel model, as piecewise constant as it is stored.

Why not the sheared lattice of :mod:`.optical_depth`: that gives tau from every point towards one
direction for all points at once; a reflected chord's direction is the mirror image of the light's at
the facet where it was reflected, so every chord has its own.  Why hand-written: no library in the
bundle integrates a voxel field along arbitrary segments.  Where numba runs, :func:`segment_depth`
runs eq. 1 compiled (:mod:`.compiled_chords`, one chord per thread); elsewhere (macOS x86-64, or a
failed compile) the same sums in numpy, one step for every chord at a time.  Measured on the hollow
cube of the inner-parts bench (50^3 voxels, 20,000 random chords): numpy 43 ms.
"""

from __future__ import annotations

import os

import numpy as np

from ..compiled import load_kernels

_KERNEL = {}  # {"depth": fn, "first_call_s": float} or {"error": "why not"}


class ChordField:
    """The voxel field of eq. 1 in the layout both paths read: sigma_t (n_voxels, 3) float64, C-ordered
    (x, y, z), with the grid's origin, voxel edge and mm per object unit."""

    def __init__(self, sigma_t, origin, h: float, mm_per_unit: float):
        sigma_t = np.asarray(sigma_t)
        self.flat = np.ascontiguousarray(sigma_t.reshape(-1, 3), dtype=np.float64)
        self.shape = np.asarray(sigma_t.shape[:3], dtype=np.int64)
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.h = float(h)
        self.mm = float(mm_per_unit)

    @classmethod
    def of_volume(cls, volume) -> "ChordField":
        """The field of a :class:`.volume.VoxelVolume` (the bake's)."""
        return cls(volume.sigma_t, volume.origin, volume.h, volume.mm_per_unit)

    @classmethod
    def of_data(cls, data) -> "ChordField | None":
        """The field a :class:`.data.SingleScatteringData` keeps (``extinction``), or None where it has none."""
        ext = getattr(data, "extinction", None)
        if ext is None:
            return None
        return cls(ext, data.voxel_origin, data.voxel_size, data.mm_per_unit)


def available() -> str:
    """'' where eq. 1 runs compiled, else why not (numba missing, a failed compile, or
    ``TRANSLUCENCY_NUMPY_CHORDS=1``, the tests' switch)."""
    if os.environ.get("TRANSLUCENCY_NUMPY_CHORDS") == "1":
        return "TRANSLUCENCY_NUMPY_CHORDS=1 is set"
    return _kernel().get("error", "")


def segment_depth(field: ChordField, a, b) -> np.ndarray:
    """Eq. 1 for the segments ``a[i] -> b[i]`` ((m, 3) each, object units): tau (m, 3)."""
    a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)
    b = np.ascontiguousarray(b, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(a), 3))
    if not len(a):
        return out
    if not available():  # '' : the compiled kernel runs
        _kernel()["depth"](field.flat, field.shape, field.origin, field.h, field.mm, a, b, out)
        return out
    return _numpy_depth(field, a, b)


def _numpy_depth(field: ChordField, a, b) -> np.ndarray:
    """Eq. 1 in numpy: step k of every chord with more than k steps at once (the chords sorted by their
    step count, so each step's chords are a prefix); the same sums in the same order as the compiled
    kernel."""
    d = b - a
    L = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    n = np.maximum(np.ceil(L / field.h), 1.0).astype(np.int64)
    order = np.argsort(-n, kind="stable")
    a_, d_, n_ = a[order], d[order], n[order]
    nf = n_.astype(np.float64)
    nx, ny, nz = (int(v) for v in field.shape)
    acc = np.zeros((len(a), 3))
    for k in range(int(n_[0])):
        m = int(np.count_nonzero(n_ > k))
        t = (k + 0.5) / nf[:m]
        ijk = np.floor((a_[:m] + t[:, None] * d_[:m] - field.origin) / field.h).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < field.shape), axis=1)
        lin = (ijk[:, 0] * ny + ijk[:, 1]) * nz + ijk[:, 2]
        acc[:m] += np.where(inside[:, None], field.flat[np.where(inside, lin, 0)], 0.0)
    out = np.empty_like(acc)
    out[order] = acc * (L[order] * field.mm / nf)[:, None]
    return out


def _kernel() -> dict:
    def load():
        from . import compiled_chords as k

        f = ChordField(np.ones((2, 2, 2, 3)), np.zeros(3), 1.0, 1.0)
        k.segment_depth(f.flat, f.shape, f.origin, f.h, f.mm, np.full((1, 3), 0.5), np.full((1, 3), 1.5),
                        np.zeros((1, 3)))
        return {"depth": k.segment_depth}

    return load_kernels(_KERNEL, load, "the chords' optical depth")
