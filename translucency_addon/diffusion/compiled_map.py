r"""The output at a render mesh's vertices in compiled code (numba): the vertex map's product
``y_v = sum_k w_vk x[idx_vk]``, and the split's per-vertex combination where the lamps enter through the volume.

:func:`.radiance.map_to_points` carries the surface nodes' values (J+, and the split's terms) to the render
mesh's vertices, every frame; its product over a CSR matrix (:func:`.radiance.mapping_operator`) runs scipy's
multi-vector kernel, which loops over the columns for every entry.  Here one pass over the points reads each
point's K slots once for all the columns: at 655 k vertices (K = 6) 54 against 96 ms for the 12 columns of a
frame with the split, 14 against 19 ms for J+'s 3 (2 shared cores).  The same sums in the same order as the
CSR product (a test holds the two to rounding); below :data:`.radiance.COMPILED_MAP_MIN_POINTS` points, and
where numba is missing, the CSR product runs.  Why hand-written: scipy has no product that shares a row's
reads between the columns.

Where the lamps' light enters through the volume, the split's output per vertex (eq. 9 of :mod:`.split`: the
part of the output beyond the local return leaves in the diffusion's own shape, then ``shape L + single``)
is a dozen numpy passes over (n_points, 3) arrays, 39 ms a frame at 655 k vertices; :func:`transported_output`
is one (:func:`.map_kernels.transported_output`, the same arithmetic per element; a test holds it to the numpy
lines).
"""

from __future__ import annotations

import numpy as np

from ..compiled import load_kernels

_KERNEL = {}  # {"gather": fn, "transported_output": fn, "first_call_s": float} or {"error": "why not"}


def available() -> str:
    """'' when the compiled kernels can run, else why not (numba missing, or their compile failed)."""
    _kernel()
    return _KERNEL.get("error", "")


def gather(idx, w, X) -> np.ndarray:
    """(n_points, C) fp64: ``sum_k w[v, k] X[idx[v, k]]`` (idx, w (n_points, K); X (n_nodes, C))."""
    k = _kernel()
    idx, w = np.ascontiguousarray(idx), np.ascontiguousarray(w)
    X = np.ascontiguousarray(X, dtype=np.float64)
    out = np.empty((len(idx), X.shape[1]))
    k["gather"](idx, w, X, out)
    return out


def transported_output(L, shape, single, local, unit, c, fdr: float) -> np.ndarray:
    """(n_points, C): ``((tot - rest) shape + rest c) / tot * L + single`` per point and channel, with
    ``P = (1 - F_dr) L / unit``, ``rest = max(P - local, 0)``, ``tot = max(P, local)`` (:func:`.map_kernels.
    transported_output`); ``unit`` and ``c`` per point (n,) or one number for all."""
    k = _kernel()
    # the terms are column blocks of the map's one product: read where they lie, strided (a copy of each cost more
    # than the pass); numba compiles a version per layout, the warm-up the frame's (L contiguous, the terms not)
    arrays = [np.asarray(a, dtype=np.float64) for a in (L, shape, single, local)]
    unit, c = (np.ascontiguousarray(np.reshape(a, -1), dtype=np.float64) for a in (unit, c))
    out = np.empty(arrays[0].shape)
    k["transported_output"](*arrays, unit, c, float(fdr), out)
    return out


def _kernel() -> dict:
    def load():
        from . import map_kernels as m

        X = np.zeros((2, 1))
        for it, wt in ((np.int32, np.float32), (np.int64, np.float64), (np.int32, np.float64), (np.int64, np.float32)):
            m.gather(np.zeros((1, 2), dtype=it), np.zeros((1, 2), dtype=wt), X, np.empty((1, 1)))
        one, terms = np.ones((2, 1)), np.ones((2, 3))[:, :1]  # the terms: strided column blocks
        m.transported_output(one, terms, terms, terms, np.ones(1), np.ones(1), 0.5, np.empty((2, 1)))
        return {"gather": m.gather, "transported_output": m.transported_output}

    return load_kernels(_KERNEL, load, "the output's kernels")
