"""Output query: J+ at the surface nodes and the radiance that leaves (Wang et al. 2010 eq. 4, 7 corrected).

From the boundary condition (derived in :mod:`.diffusion`)::

    J+ = (phi - 2 q) / (2 (1 + F_dr))
    L_o(w_o) = F_t(w_o) J+ / (pi eta^2)

with the clamp of negative J+ kept from creating power (:func:`clamp_scale`).
The numpy twin of the GPU's J+ kernel is ``kernels.outgoing_partial_current``.
"""

from __future__ import annotations

import numpy as np

from ..scene.fresnel import fresnel_transmittance
from . import compiled_map
from .kernels import partial_current


def clamp_scale(phi_s: np.ndarray, q: np.ndarray, area: np.ndarray, fdr: float) -> np.ndarray:
    """Per-channel factor (<= 1) that keeps the clamp of J+ from creating power.

    The exact discrete balance gives ``sum_s a_s (1 - F_dr) J+_s = in - absorbed``
    with the unclamped J+.  Clamping its negative values to 0 raises that sum,
    and where the diffusion model fails -- an object much thinner than a
    transport mean free path lit on one side, where the surface node's phi is
    below 2q -- the output then emitted more than came in (fuzz test: 8 % at
    a 4 um sphere with 1 mm mean free paths).  When the unclamped total is
    positive and smaller than the clamped one, the clamped J+ is scaled down
    to it, so the output emits exactly ``in - absorbed``; otherwise (nothing
    was clamped, or the model gives a net inflow: an absorber, where the
    clamped output is already below the light that came in) the factor is 1.
    """
    j = partial_current(phi_s, q, fdr)
    a = np.asarray(area, dtype=np.float64)
    unclamped = a @ j
    clamped = a @ np.maximum(j, 0.0)
    ok = (unclamped > 0) & (clamped > unclamped)
    return np.where(ok, unclamped / np.where(ok, clamped, 1.0), 1.0)


def outgoing_radiance(jplus: np.ndarray, cos_o, eta: float) -> np.ndarray:
    """L_o = F_t(w_o) J+ / (pi eta^2) (corrected eq. 4 / 7).

    Rule for phi - 2q < 0: J+ is clamped to 0 before this (kernels.outgoing_partial_current).
    A negative J+ would mean light flowing *into* the object through the
    exitant half-space, which the diffusion approximation cannot resolve; it
    occurs where a link is shorter than 2 kappa (the FV row gives
    ``phi_s - 2q >= 0`` whenever ``phi_k >= q (2 - d_sk/kappa)``), i.e. on
    graphs finer than a transport mean free path, and in strong absorbers.
    The clamp removes no light from lit regions; the power it would add is
    taken back by :func:`clamp_scale` (every backend's output: ``DiffusionSolver.output_clamp``).
    ``cos_o`` (n,) per point, or one number for all of them (the view along the normal: 1).
    """
    ft = fresnel_transmittance(np.clip(cos_o, 0.0, 1.0), eta)
    ft = np.where(np.asarray(cos_o) > 0, ft, 0.0)
    f = ft / (np.pi * eta * eta)
    return jplus * (f[:, None] if np.ndim(f) else f)  # one cosine for every point (seen along the normal)


def mapping_operator(idx, w, n_nodes: int):
    """The vertex map ``y_v = sum_k w_vk x[idx_vk]`` as one CSR matrix (n_points x n_nodes), cached per map.

    ``idx``/``w`` (n_points, K): the vertex map's form (``Bake.vertex_map``, a fluid's surface map); padded
    slots carry weight 0.  Built straight from the arrays (row v holds its K entries in slot order, so the
    product sums them in the order the per-slot gather did), and kept for the arrays' lifetime: a frame
    maps several node arrays through the same map, every frame.  One compiled product over all of them
    (:func:`map_to_points`) replaces a gather of (n_points, K, C) per array: at 655 k vertices the output's
    interpolations took 0.47 s as gathers and einsums.
    """
    import scipy.sparse as sp

    key = (id(idx), id(w), int(n_nodes))
    hit = _MAPS.get(key)
    if hit is not None and hit[0] is idx and hit[1] is w:
        return hit[2]
    i = np.asarray(idx)
    n, k = i.shape
    data = np.ascontiguousarray(np.asarray(w, dtype=np.float64).reshape(-1))
    ind = np.ascontiguousarray(i.reshape(-1), dtype=np.int64 if n_nodes >= 2**31 else np.int32)
    ptr = np.arange(0, n * k + 1, k, dtype=np.int64 if n * k >= 2**31 else np.int32)
    op = sp.csr_matrix((data, ind, ptr), shape=(n, int(n_nodes)), copy=False)
    if len(_MAPS) >= 8:
        _MAPS.pop(next(iter(_MAPS)))
    _MAPS[key] = (idx, w, op)  # the arrays are kept so their ids cannot be reused while cached
    return op


COMPILED_MAP_MIN_POINTS = 65536  # from this many points the compiled gather (:mod:`.compiled_map`) runs


def map_to_points(idx, w, *node_arrays) -> list:
    """Each of ``node_arrays`` ((n_nodes,) or (n_nodes, C)) carried to the points of the map ``idx``/``w``,
    by one product over all their columns: the compiled gather on large meshes where numba runs
    (:mod:`.compiled_map`), else the sparse product (:func:`mapping_operator`); the same sums."""
    n_nodes = len(node_arrays[0])
    cols = [np.asarray(a, dtype=np.float64).reshape(n_nodes, -1) for a in node_arrays]
    X = cols[0] if len(cols) == 1 else np.hstack(cols)
    if len(idx) >= COMPILED_MAP_MIN_POINTS and not compiled_map.available():
        out = compiled_map.gather(idx, w, X)
    else:
        out = mapping_operator(idx, w, n_nodes) @ X
    res, j = [], 0
    for a, c in zip(node_arrays, cols):
        m = out[:, j:j + c.shape[1]]
        res.append(m[:, 0] if np.ndim(a) == 1 else m)
        j += c.shape[1]
    return res


_MAPS: dict = {}  # (id(idx), id(w), n_nodes) -> (idx, w, CSR)
