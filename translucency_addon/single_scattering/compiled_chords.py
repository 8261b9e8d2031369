"""Eq. 1 of :mod:`.chords` in compiled code (numba), one chord per thread.

Imported only by :func:`.chords._kernel`, inside a guard: importing this module needs numba.  The same
sums as :func:`.chords._numpy_depth`, in the same order (``tests/test_single_scattering_entry.py`` holds
the two paths to each other).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, parallel=True)
def segment_depth(flat, shape, origin, h, mm, a, b, out):
    """tau (m, 3) of the segments a -> b into ``out``: the midpoint rule on the voxels, at most one voxel a step."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    for r in numba.prange(a.shape[0]):
        dx, dy, dz = b[r, 0] - a[r, 0], b[r, 1] - a[r, 1], b[r, 2] - a[r, 2]
        L = np.sqrt(dx * dx + dy * dy + dz * dz)
        n = max(np.ceil(L / h), 1.0)
        s0, s1, s2 = 0.0, 0.0, 0.0
        for k in range(int(n)):
            t = (k + 0.5) / n
            i = int(np.floor((a[r, 0] + t * dx - origin[0]) / h))
            j = int(np.floor((a[r, 1] + t * dy - origin[1]) / h))
            q = int(np.floor((a[r, 2] + t * dz - origin[2]) / h))
            if 0 <= i < nx and 0 <= j < ny and 0 <= q < nz:
                v = (i * ny + j) * nz + q
                s0 += flat[v, 0]
                s1 += flat[v, 1]
                s2 += flat[v, 2]
        f = L * mm / n
        out[r, 0], out[r, 1], out[r, 2] = s0 * f, s1 * f, s2 * f
