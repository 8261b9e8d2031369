# SPDX-License-Identifier: GPL-3.0-or-later
"""Error metrics between our image and the reference, and scan lines for plots.

**Relative RMS error** (``docs/reference.md``).  Let ``P`` be the set of pixels
inside *both* masks, eroded by one pixel (3 x 3 structuring element, so every
pixel of ``P`` has all eight neighbours on the object: silhouette pixels,
which mix object and background in the reference's box filter, drop out).
Then, per channel ``c``::

    e_c = sqrt( sum_P (ours_c - ref_c)^2 ) / sqrt( sum_P ref_c^2 )

and over all channels together::

    e = sqrt( sum_P sum_c (ours_c - ref_c)^2 ) / sqrt( sum_P sum_c ref_c^2 )

So ``e = 0`` for identical images and ``e = |k|`` for ``ours = (1 + k) ref``.

**Noise floor.**  The reference carries its own noise (``RefResult.stderr``).
For a perfect ``ours`` the expected squared error is ``sum_P stderr^2``, so
:func:`noise_floor` reports ``sqrt(sum_P stderr^2) / sqrt(sum_P ref^2)``; a
measured error near it is not resolved by the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


def comparison_mask(mask_ours, mask_ref=None, erode: int = 1) -> np.ndarray:
    """Pixels in both masks, eroded ``erode`` times with a 3 x 3 square."""
    m = np.asarray(mask_ours, dtype=bool)
    if mask_ref is not None:
        m = m & np.asarray(mask_ref, dtype=bool)
    if erode > 0:
        m = ndimage.binary_erosion(m, structure=np.ones((3, 3), dtype=bool), iterations=int(erode), border_value=0)
    return m


@dataclass
class ErrorReport:
    rel_rms: float  # all channels together
    rel_rms_rgb: tuple  # per channel
    pixels: int  # |P|
    noise_floor: float | None = None  # the reference's own noise on the same scale
    noise_floor_rgb: tuple | None = None

    def __str__(self) -> str:
        rgb = ", ".join(f"{v:.4f}" for v in self.rel_rms_rgb)
        s = f"rel RMS {self.rel_rms:.4f} (RGB {rgb}) over {self.pixels} px"
        if self.noise_floor is not None:
            s += f"; reference noise floor {self.noise_floor:.4f}"
        return s


def _as3(img) -> np.ndarray:
    a = np.asarray(img, dtype=np.float64)
    return a[..., None] if a.ndim == 2 else a


def relative_rms(ours, ref, mask_ours, mask_ref=None, *, erode: int = 1, stderr=None) -> ErrorReport:
    """Relative RMS error of ``ours`` against ``ref`` (both (H, W) or (H, W, C)), see the module doc."""
    o, r = _as3(ours), _as3(ref)
    if o.shape != r.shape:
        raise ValueError(f"image shapes differ: {o.shape} vs {r.shape}")
    P = comparison_mask(mask_ours, mask_ref, erode)
    if not P.any():
        raise ValueError("no pixel left to compare (masks disjoint or eroded away)")
    d2 = ((o[P] - r[P]) ** 2).sum(axis=0)
    r2 = (r[P] ** 2).sum(axis=0)
    if not np.all(r2 > 0):
        raise ValueError("the reference is zero over the compared pixels in some channel")
    rep = ErrorReport(float(np.sqrt(d2.sum() / r2.sum())), tuple(float(v) for v in np.sqrt(d2 / r2)), int(P.sum()))
    if stderr is not None:
        s2 = (_as3(stderr)[P] ** 2).sum(axis=0)
        rep.noise_floor = float(np.sqrt(s2.sum() / r2.sum()))
        rep.noise_floor_rgb = tuple(float(v) for v in np.sqrt(s2 / r2))
    return rep


def noise_floor(ref, stderr, mask_ours, mask_ref=None, *, erode: int = 1) -> float:
    """``sqrt(sum_P stderr^2) / sqrt(sum_P ref^2)``: the error a perfect result would show."""
    P = comparison_mask(mask_ours, mask_ref, erode)
    s, r = _as3(stderr)[P], _as3(ref)[P]
    return float(np.sqrt((s**2).sum() / (r**2).sum()))


def scanline(image, mask=None, *, row: int | None = None, col: int | None = None, stderr=None):
    """One row (default: the middle row) or column of an image for a Fig. 11-style plot.

    Returns ``(index, values, errors)``: pixel indices along the line, values
    (n,) or (n, C) with NaN where ``mask`` is False (so plots break at the
    silhouette), and the matching ``stderr`` slice or None.
    """
    a = np.asarray(image, dtype=np.float64)
    H, W = a.shape[:2]
    if row is not None and col is not None:
        raise ValueError("give row or col, not both")
    if col is None:
        row = H // 2 if row is None else int(row)
        sl = (row, slice(None))
    else:
        sl = (slice(None), int(col))
    vals = a[sl].copy()
    err = None if stderr is None else np.asarray(stderr, dtype=np.float64)[sl].copy()
    if mask is not None:
        m = np.asarray(mask, dtype=bool)[sl]
        vals[~m] = np.nan
        if err is not None:
            err[~m] = np.nan
    return np.arange(len(vals)), vals, err
