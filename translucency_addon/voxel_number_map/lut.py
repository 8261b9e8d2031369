"""The optical-thickness look-up table between surface voxels (Mochida et al., precomputation 2-3).

The poster stores ``tau(x_in, x_out) = int sigma_t dx`` for every pair of
surface voxels.  We store what tau is made of: for each **component medium**
c (the outer material's medium -- two for a field-mixed material -- and each
inner medium part), the length of the chord from x_in to x_out that lies in
it, ``l_c(i, j) = int w_c(x) dx`` (``VoxelVolume.components``), in voxel
units.  Then for any coefficients chosen later::

    tau(i, j)   = h_mm sum_c sigma_t,c l_c(i, j)        (per RGB channel)
    tau_s(i, j) = h_mm sum_c sigma_s,c l_c(i, j)

so editing a medium's coefficients in the panel never needs a new LUT (the
geometry is baked, the material is not), and a bottle of wine needs two
tables (glass and wine), as in the poster.  Cavities contribute no length
(sigma_t = 0); a chord that crosses an opaque part is flagged **blocked**
(tau infinite): one bit per pair.

**Layout.**  The LUT is symmetric, so only the upper triangle *with* the
diagonal is kept, row by row: pair (i, j), i <= j, sits at
``k = i n - i (i - 1)/2 + (j - i)`` -- exactly BLAS's packed storage of a
symmetric matrix (``sspmv``), which the run time uses directly.  Lengths are
float16 (3 significant digits: tau to 5e-4 of itself), blocked bits are
``numpy.packbits``.  Memory: ``n (n + 1)/2 x (2 C + 1/8)`` bytes for n
surface voxels and C components (:func:`lut_bytes`).

**Marching (vectorised).**  Chords are processed in blocks of rows.  For a
block, every pair gets ``m = ceil(L / step)`` midpoint samples (``step``
half a voxel by default); all samples of the block are generated at once with
``np.repeat`` (no Python loop per pair), their voxels looked up in the
component-weight grid, and the per-pair sums taken with ``np.add.reduceat``
over the contiguous samples of each pair.  The grid is the voxeliser's
(:func:`~translucency_addon.single_scattering.volume.voxelise_composite`),
with the outer surface's voxels filled from just inside
(:func:`.surface.extend_into_surface_voxels`).
"""

from __future__ import annotations

import numpy as np

SAMPLES_PER_BLOCK = 4_000_000  # chord samples per vectorised block (memory: ~16 + 4 C bytes each)


def n_pairs(n: int) -> int:
    return n * (n + 1) // 2


def lut_bytes(n: int, n_components: int) -> int:
    """Bytes of the stored LUT: fp16 lengths per component plus one blocked bit per pair."""
    p = n_pairs(n)
    return int(p * 2 * n_components + (p + 7) // 8)


def kernel_bytes(n: int) -> int:
    """Bytes of the run-time kernel the CPU keeps per material: packed float32, three channels."""
    return int(n_pairs(n) * 4 * 3)


def packed_index(i, j, n: int):
    """Position of pair (i, j) (any order) in the packed upper triangle with the diagonal."""
    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    a, b = np.minimum(i, j), np.maximum(i, j)
    return a * n - a * (a - 1) // 2 + (b - a)


def row_block(n: int, i0: int, i1: int):
    """The pairs of rows i0 .. i1-1 in packed order: (I, J) and the packed offset of the first."""
    counts = n - np.arange(i0, i1)
    I = np.repeat(np.arange(i0, i1), counts)
    start = np.cumsum(counts) - counts
    J = np.arange(len(I)) - np.repeat(start, counts) + I
    return I, J, int(packed_index(i0, i0, n)) if i0 < n else n_pairs(n)


def row_blocks(n: int, pairs_per_block: int):
    """Row ranges ``(i0, i1)`` holding about ``pairs_per_block`` pairs each (rows shrink along the triangle)."""
    i0 = 0
    while i0 < n:
        i1 = i0 + 1
        total = n - i0
        while i1 < n and total + (n - i1) <= pairs_per_block:
            total += n - i1
            i1 += 1
        yield i0, i1
        i0 = i1


def march_block(U: np.ndarray, I: np.ndarray, J: np.ndarray, table: np.ndarray, shape, step: float):
    """Chord integrals of the columns of ``table`` for pairs (I, J): (m, C') in voxel units.

    ``U``: (n, 3) surface-voxel positions in voxel-index coordinates (voxel
    (0, 0, 0) spans [0, 1)^3, every position inside the grid); ``table``
    (C', n_voxels) per-voxel values (the component weights and an opaque
    flag).  Pairs with the same sample count are marched together as one
    (pairs x samples) array per axis: no per-sample index arrays are repeated
    (~30 ns per sample on one core).
    """
    a = U[I].astype(np.float32)
    d = U[J].astype(np.float32) - a
    L = np.sqrt(np.einsum("ij,ij->i", d, d))
    m = np.maximum(np.ceil(L / step).astype(np.int64), 1)
    out = np.zeros((len(I), table.shape[0]), dtype=np.float32)
    _, ny, nz = shape
    order = np.argsort(m, kind="stable")
    bounds = np.flatnonzero(np.diff(m[order])) + 1
    for grp in np.split(order, bounds):
        k = int(m[grp[0]])
        t = (np.arange(k, dtype=np.float32) + np.float32(0.5)) / np.float32(k)
        ag, dg = a[grp], d[grp]
        flat = (ag[:, 0, None] + t * dg[:, 0, None]).astype(np.int32) * (ny * nz)
        flat += (ag[:, 1, None] + t * dg[:, 1, None]).astype(np.int32) * nz
        flat += (ag[:, 2, None] + t * dg[:, 2, None]).astype(np.int32)
        ds = L[grp] / np.float32(k)
        for c in range(table.shape[0]):
            out[grp, c] = table[c][flat].sum(axis=1) * ds
    return out


def build_lut(U: np.ndarray, comp: np.ndarray, blocked_grid: np.ndarray, step: float = 0.5, progress=None):
    """``(lengths (C, n(n+1)/2) float16, blocked bits uint8)`` for surface voxels at ``U`` (voxel coordinates).

    ``progress(fraction)`` is called after every block (it may raise to cancel).
    """
    shape = comp.shape[:3]
    U = np.clip(np.asarray(U, dtype=np.float64), 0.0, np.asarray(shape) - 1e-3)
    n = len(U)
    C = comp.shape[3]
    table = np.ascontiguousarray(np.concatenate([comp.reshape(-1, C), blocked_grid.reshape(-1, 1)], axis=1).T,
                                 dtype=np.float32)
    P = n_pairs(n)
    lengths = np.zeros((C, P), dtype=np.float16)
    blocked = np.zeros(P, dtype=bool)
    # pairs per block from the mean chord length (samples per pair ~ L / step)
    span = float(np.linalg.norm(U.max(axis=0) - U.min(axis=0))) if n else 1.0
    per_pair = max(1.0, 0.5 * span / step)
    for i0, i1 in row_blocks(n, max(n, int(SAMPLES_PER_BLOCK / per_pair))):
        I, J, k0 = row_block(n, i0, i1)
        ln = march_block(U, I, J, table, shape, step)
        lengths[:, k0:k0 + len(I)] = ln[:, :C].T
        blocked[k0:k0 + len(I)] = ln[:, C] > 0
        if progress is not None:
            progress(float(k0 + len(I)) / P)
    return lengths, np.packbits(blocked)


def unpack_blocked(bits: np.ndarray, n: int) -> np.ndarray:
    return np.unpackbits(np.asarray(bits, dtype=np.uint8), count=n_pairs(n)).astype(bool)
