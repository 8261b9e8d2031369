"""The per-axis bounds of a point set, in the form a frame's hot paths need them.

numpy reduces an (N, 3) array over axis 0 with a strided inner loop: ``X.min(axis=0)`` takes 4.9 ms at
262k points where the three columns' own reductions take 0.7 ms (measured, numpy 2.3), and a fluid frame
asks for its particles', cells' and nodes' bounds some ten times.  The values are the same (a minimum is
exact whatever the order).
"""

from __future__ import annotations

import numpy as np


def bounds(X) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)``: the smallest and largest value of each column of the (N, D) array ``X`` (N > 0)."""
    X = np.asarray(X)
    return (np.array([X[:, k].min() for k in range(X.shape[1])], dtype=X.dtype),
            np.array([X[:, k].max() for k in range(X.shape[1])], dtype=X.dtype))


def extent(X) -> np.ndarray:
    """``hi - lo`` of each column (``np.ptp(X, axis=0)``)."""
    lo, hi = bounds(X)
    return hi - lo
