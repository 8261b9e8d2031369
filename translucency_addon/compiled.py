"""Loading a module's numba kernels once per process, or the reason they cannot run.

The engine's compiled paths (the Voronoi-fluid cells' faces, :mod:`.fluid.compiled_faces`; the conjugate
gradients' step, :mod:`.diffusion.compiled_cg`) each keep their kernels in a module-level dict and fall back
to their numpy twin where it holds ``{"error": why}``; this is the one place that fills it.
"""

from __future__ import annotations

import time


def load_kernels(store: dict, load, what: str) -> dict:
    """``store``, filled at the first call: ``load()``'s kernels (a dict; ``load`` imports the kernels'
    module, which needs numba, and runs each on a tiny case, so numba compiles them or loads them from its
    cache now) and ``first_call_s``, the seconds that took; or ``{"error": why}`` where numba is missing or
    ``load`` fails (``what``: the kernels' name in that sentence).  Later calls return ``store`` as it is."""
    if store:
        return store
    try:
        import numba
    except ImportError:
        store["error"] = "numba is not installed"
        return store
    t0 = time.perf_counter()
    try:
        kernels = load()
    except Exception as ex:  # noqa: BLE001 - any compile failure means the numpy path, with its reason
        store["error"] = f"numba {numba.__version__} could not compile {what} ({type(ex).__name__}: {ex})"
        return store
    store.update(kernels, first_call_s=time.perf_counter() - t0)
    return store
