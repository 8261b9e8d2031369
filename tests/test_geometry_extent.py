"""geometry/extent.py: per-axis bounds by columns are numpy's axis-0 reductions exactly."""

import numpy as np

from translucency_addon.geometry.extent import bounds, extent


def test_bounds_are_numpys_axis_0_reductions():
    rng = np.random.default_rng(0)
    for X in (rng.normal(size=(1000, 3)), rng.integers(-50, 50, (7, 3)), rng.normal(size=(1, 2)).astype(np.float32)):
        lo, hi = bounds(X)
        assert lo.dtype == X.dtype and hi.dtype == X.dtype
        np.testing.assert_array_equal(lo, X.min(axis=0))
        np.testing.assert_array_equal(hi, X.max(axis=0))
        np.testing.assert_array_equal(extent(X), np.ptp(X, axis=0))
