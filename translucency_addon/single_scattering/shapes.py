"""Small closed test meshes for the single-scattering tests and bench.

Kept for its API (``box(size, center, n)`` with n divisions per face edge);
the meshes themselves live in :mod:`translucency_addon.geometry.primitives`.
"""

from __future__ import annotations

from ..geometry.primitives import torus, uv_sphere
from ..geometry.primitives import box as _box


def box(size=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0), n: int = 8):
    """Axis-aligned box, each face split into n x n quads, shared vertices merged."""
    return _box(size, center, n=n)


__all__ = ["box", "torus", "uv_sphere"]
