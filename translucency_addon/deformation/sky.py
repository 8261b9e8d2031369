"""The sky visibility of a deformed bake (extends :mod:`.sky_visibility` to a pose, :mod:`.deformation`).

Which (surface node, direction) pairs are hidden and where their rays hit the mesh stay
those of the rest pose -- the bake's rays are not cast again per frame -- and the
directions turn with the surface.  What that costs in accuracy (a pose that opens or
closes a concavity) is measured in docs/accuracy.md, "Deformation".
"""

from __future__ import annotations

import numpy as np

from ..errors import CacheError


class DeformedSky:
    """The bake's sky visibility carried along by a pose (same interface as ``SkyVisibility``).

    Which (surface node, direction) pairs are hidden and where their rays hit the mesh stay
    those of the rest pose (the hit point moves with the mesh, so the interreflection bounce
    follows the pose).  The directions turn with the surface: pair (s, d) looks along
    ``R_s d``, with R_s the rotation of surface node s's mesh triangle.  The quadrature
    weights ``c w`` depend only on angles to the normal, which a rotation keeps, so they are
    the rest pose's.

    The hidden sky ``sum_d c w L(R_s d)`` of an environment of SH order <= 2 -- a polynomial
    of degree 2 in the direction, ``L(x) = a + b.x + x^T C x`` -- is exactly
    ``a S0 + b.(R_s S1) + tr(C R_s S2 R_s^T)`` with the rest pose's moments
    ``S_k = sum_d c w d^k`` per node (cached per refractive index in ``moments``): a frame
    costs O(surface nodes), not O(hidden pairs).  Higher orders are evaluated pair by pair.
    """

    def __init__(self, sky, rest_levels, rotations, moments: dict):
        self.rest = sky
        self.directions = sky.directions
        self.levels = sky.levels
        self._rest_levels = rest_levels
        self._rotations = rotations  # callable: level -> (n_surface, 3, 3)
        self._moments = moments  # (level, eta) -> (S0, S1, S2), shared by the poses of one rig

    def _weight(self, level, eta):
        return self.levels[level].weight(eta, self._rest_levels[level].normal, self.directions)

    def moments(self, level: int, eta: float):
        key = (level, float(eta))
        if key not in self._moments:
            lv = self.levels[level]
            w = self._weight(level, eta)
            d = self.directions[lv.direction]
            S0 = np.bincount(lv.node, w, lv.n_surface)
            S1 = np.stack([np.bincount(lv.node, w * d[:, i], lv.n_surface) for i in range(3)], axis=1)
            S2 = np.stack([np.bincount(lv.node, w * d[:, i] * d[:, j], lv.n_surface)
                           for i in range(3) for j in range(3)], axis=1).reshape(-1, 3, 3)
            self._moments[key] = (S0, S1, S2)
        return self._moments[key]

    def hidden_sky(self, level: int, eta: float, environment) -> np.ndarray:
        """``sum_d c w L(R_s d)`` per surface node, (n_surface, 3)."""
        lv = self.levels[level]
        R = self._rotations(level)
        if R is None:  # no triangle of this level's nodes turned: the rest pose's sum, bit for bit
            return lv.hidden_sky(self._weight(level, eta), environment.radiance_at(self.directions))
        quad = _quadratic_fit(environment)
        if quad is None:  # SH order > 2: pair by pair
            w = self._weight(level, eta)
            d = np.einsum("mij,mj->mi", R[lv.node], self.directions[lv.direction])
            hidden = np.zeros((lv.n_surface, 3))
            np.add.at(hidden, lv.node, w[:, None] * environment.radiance_at(d))
            return hidden
        S0, S1, S2 = self.moments(level, eta)
        M = R @ S2 @ R.transpose(0, 2, 1)
        m = np.column_stack([S0, np.einsum("sij,sj->si", R, S1), M[:, 0, 0], M[:, 1, 1], M[:, 2, 2],
                             M[:, 0, 1], M[:, 0, 2], M[:, 1, 2]])
        return m @ quad

    def correct(self, level: int, normals, eta: float, q_env, environment=None, vertex_radiance=None):
        """As :meth:`SkyVisibility.correct`, with each hidden direction turned by its node's rotation."""
        lv = self.levels[level]
        w = self._weight(level, eta)
        q = np.zeros((lv.n_surface, 3)) if q_env is None else np.array(q_env, dtype=np.float64)
        if environment is not None and not environment.is_black:
            if environment.sh is None:  # uniform: every direction sees the same radiance
                hidden = lv.hidden_sky(w, environment.radiance_at(self.directions))
            else:
                hidden = self.hidden_sky(level, eta, environment)
            q = np.maximum(q - hidden, 0.0)
        if vertex_radiance is not None:
            q = q + lv.bounce(w, vertex_radiance)
        return q

    def to_arrays(self, prefix: str = "sky/") -> dict:
        raise CacheError("a deformed bake is not written to a cache: it is the rest pose's bake at one pose; "
                         "save the rest pose's bake (its DeformationRig re-poses it)")

    def hidden_fraction(self, level: int, normals=None, eta: float = 1.0) -> np.ndarray:
        return self.rest.hidden_fraction(level, self._rest_levels[level].normal, eta)


def _quadratic_fit(environment):
    """``(10, 3)`` coefficients of ``L(x) = [1, x, y, z, xx, yy, zz, xy, xz, yz] . coef`` reproducing
    the environment exactly on the sphere, or None when it is not of degree <= 2 (SH order > 2)."""
    from ..scene.sh import fibonacci_directions

    if environment.sh is not None and np.asarray(environment.sh).shape[0] > 9:
        return None
    d = fibonacci_directions(64)
    x, y, z = d.T
    A = np.column_stack([np.ones(len(d)), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])
    return np.linalg.lstsq(A, environment.radiance_at(d), rcond=None)[0]
