# SPDX-License-Identifier: GPL-3.0-or-later
"""Where each pass runs, GPU or CPU: the add-on's one fallback policy.

Every GPU-to-CPU decision of the Blender side is taken here, and each says
why, with names and numbers:

* :func:`placement`: before anything is built -- the scene's Solver setting,
  a deformed frame (its graph changes every frame; the GPU solver packs it
  once), the thread (Blender's GPU context belongs to the main thread; a
  render job runs elsewhere), the solver kind (sparse LU has no GPU form), an earlier
  GPU failure in this render, the GPU layer importing, a GPU context with
  compute shaders (``gpu_shaders.available``) and, for the single-scattering
  ray pass and the Voxel Number Map in "Auto", a software rasteriser (where
  numpy and BLAS are faster).
* :func:`make_solver` / :func:`make_integrator` / :func:`make_transmission`: the
  diffusion solver, the single-scattering integrator and the Voxel Number
  Map's transport for a placement.  The GPU layer is asked strictly
  (``prefer="GPU"``: build it or raise, never fall back itself); a refusal (a
  level over the texture limits, a kernel that does not compile) becomes the
  CPU, with the GPU layer's reason.
* :func:`after_gpu_failure`: a GPU solve that raised while solving: the CPU
  from now on, or, during a render, the CPU for renders only.

The one fallback left below this module is the single-scattering
integrator's per call (``gpu_shaders.single_scattering.AutoIntegrator``):
a call made where no GPU context is current runs its numpy twin and says so.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

PREFERENCES = ("AUTO", "GPU", "CPU")
# The passes whose CPU twin beats the kernel on a software rasteriser (llvmpipe) in "Auto", and why.
SOFTWARE_SLOWER = {
    "single scattering": "the single-scattering ray pass is faster in numpy; using numpy",
    "Voxel Number Map": "the Voxel Number Map's n^2 loop is slower than BLAS on the same cores; using BLAS",
}


@dataclass(frozen=True)
class Placement:
    """Where a pass runs and why: ``backend`` is ``"GPU"`` or ``"CPU"``; ``reason`` says why not
    the GPU ('' when the GPU is used or the CPU was chosen in the settings)."""

    backend: str
    reason: str = ""

    @property
    def gpu(self) -> bool:
        return self.backend == "GPU"


def off_main_thread() -> bool:
    return threading.current_thread() is not threading.main_thread()


def placement(prefer: str = "AUTO", *, kind: str = "diffusion", solver: str = "fast", off_main: bool | None = None,
              failed_in_render: str = "", built: bool = False, gpu_failed: str = "") -> Placement:
    """Where a pass of ``kind`` (``"diffusion"``, ``"single scattering"`` or ``"Voxel Number Map"``) may run.

    ``prefer``: the scene's Solver setting (AUTO, GPU, CPU); ``solver``: the
    diffusion solver's name; ``off_main``: solving off Blender's main thread
    (default: the current thread's); ``failed_in_render``: why an earlier GPU
    solve of this object failed in a render ('' when none did); ``built``: the
    GPU solver exists already (a frame asks whether it may use it), so only
    the rules that change from frame to frame apply (thread, render failure);
    ``gpu_failed``: why an earlier GPU solve of this work failed (:func:`solve_with_cpu_retry`): the CPU, with
    that reason.  Deformed frames and the cavity exchange run on either: the GPU solver of a pose is rebound to the
    next pose (``DiffusionSolver.rebind``: new coefficients, the same graph textures), and it reads every
    solve's phi back for a cavity exchange (``gpu_shaders.solver.default_readback``).
    """
    if gpu_failed:
        return Placement("CPU", gpu_failed)
    prefer = (prefer or "AUTO").upper()
    if prefer == "CPU":
        return Placement("CPU")
    if off_main is None:
        off_main = off_main_thread()
    if off_main:
        return Placement("CPU", f"{kind} runs off Blender's main thread (thread "
                                f"'{threading.current_thread().name}', a render job), where the GPU context is "
                                "not current: using the CPU")
    if failed_in_render:
        return Placement("CPU", f"{failed_in_render}; renders of this object stay on the CPU solver (the viewport "
                                "keeps the GPU)")
    if built:
        return Placement("GPU")
    if kind == "diffusion" and solver == "direct":
        return Placement("CPU", "the direct solver (sparse LU) has no GPU version: using the CPU")
    try:
        from .. import gpu_shaders

        ok, why = gpu_shaders.available()
    except Exception as ex:  # noqa: BLE001 - a missing or broken GPU layer
        return Placement("CPU", f"the {kind} GPU layer is not available ({type(ex).__name__}: {ex}); using the CPU")
    if not ok:
        return Placement("CPU", f"the GPU cannot run {kind} here: {why}. The image is the "
                                "same, only slower; for the GPU, run Blender with a display, or headless on a "
                                "machine with a GPU driver that offers EGL. Set Scene > Translucency > Solver to "
                                "CPU to choose the CPU yourself, and this note goes away")
    if kind in SOFTWARE_SLOWER and prefer == "AUTO":
        from ..gpu_shaders.single_scattering import SOFTWARE_RENDERERS

        if any(name in why.lower() for name in SOFTWARE_RENDERERS):
            return Placement("CPU", f"the GPU ({why}) is a software rasteriser, on which {SOFTWARE_SLOWER[kind]}")
    return Placement("GPU", why)


def cpu_solver(bake, material, field_values, options):
    from ..translucency_addon.diffusion.solver import DiffusionSolver

    return DiffusionSolver(bake, material, field_values, options)


def make_solver(bake, material, field_values, options, prefer: str = "AUTO", *, off_main: bool | None = None):
    """``(solver, backend, message)`` for one baked object: ``backend`` is ``"GPU"`` or ``"CPU"`` and
    ``message`` says why the GPU was not used, or on which GPU it runs.  Material errors are raised
    whatever the backend (the CPU would refuse the same material)."""
    from ..translucency_addon.errors import MaterialError

    where = placement(prefer, solver=options.solver, off_main=off_main)
    if where.gpu:
        try:
            from .. import gpu_shaders

            solver, _name, message = gpu_shaders.make_solver(bake, material, field_values, options, prefer="GPU")
            return solver, "GPU", str(message or "")
        except MaterialError:
            raise
        except Exception as ex:  # noqa: BLE001 - too large for the textures, a kernel that does not compile
            where = Placement("CPU", f"the GPU solver cannot run ({type(ex).__name__}: {ex}); using the CPU solver")
    return cpu_solver(bake, material, field_values, options), "CPU", where.reason


def make_integrator(data, prefer: str = "AUTO", *, off_main: bool | None = None):
    """``(integrator, backend, message)`` for the single-scattering ray pass of one bake.

    On the GPU it is the kernel's dispatcher inside an ``AutoIntegrator``, which runs a call made
    where no GPU context is current (a render handler) in numpy; elsewhere the numpy twin.
    """
    from ..translucency_addon.single_scattering import CPUIntegrator

    def build():
        from ..gpu_shaders import single_scattering as gss

        integrator, _name, message = gss.make_integrator(data, "GPU")
        return gss.AutoIntegrator(data, integrator, ""), message

    built, where = _strictly_on_the_gpu(placement(prefer, kind="single scattering", off_main=off_main), build,
                                        "single-scattering", "numpy")
    if built is not None:
        return built[0], "GPU", built[1]
    return CPUIntegrator(data), "CPU", where.reason


def make_transmission(vnm, prefer: str = "AUTO", *, off_main: bool | None = None):
    """``(transmission or None, backend, message)`` for the Voxel Number Map's transport of one baked map.

    On the GPU the kernel's dispatcher (``gpu_shaders.voxel_number_map``); ``None`` means the
    evaluator's own BLAS product, with the reason.
    """
    def build():
        from ..gpu_shaders import voxel_number_map as gvnm

        transmission, _name, message = gvnm.make_transmission(vnm, "GPU")
        return transmission, message

    built, where = _strictly_on_the_gpu(placement(prefer, kind="Voxel Number Map", off_main=off_main), build,
                                        "Voxel Number Map", "BLAS")
    if built is not None:
        return built[0], "GPU", built[1]
    return None, "CPU", where.reason


def _strictly_on_the_gpu(where: Placement, build, what: str, cpu_name: str):
    """``(build() or None, placement)``: the GPU layer's kernel where ``where`` allows it; a refusal (too
    large for the textures, a kernel that does not compile) becomes the CPU with the layer's reason."""
    if not where.gpu:
        return None, where
    try:
        return build(), where
    except Exception as ex:  # noqa: BLE001 - too large for the textures, a kernel that does not compile
        return None, Placement("CPU", f"the {what} GPU kernel cannot run ({type(ex).__name__}: {ex}); "
                                      f"using {cpu_name}")


def after_gpu_failure(ex: BaseException, *, rendering: bool, on_gpu: bool = True) -> Placement | None:
    """A solve raised while solving: where to retry it, or None to let the error through.

    Only a GPU solve falls back (a CPU failure is reported as it is): to the CPU from now on, or,
    in a render (where a missing GPU context is the usual cause), for this render's frames only
    (``placement(failed_in_render=...)``).
    """
    if not on_gpu:
        return None
    return Placement("CPU", f"the GPU solve failed ({type(ex).__name__}: {ex}); using the CPU solver"
                            + (" for renders" if rendering else ""))


def solve_with_cpu_retry(solve, *, on_gpu, rendering: bool, gpu_failed):
    """``solve()``; where it raises on the GPU (not a :class:`TranslucencyError`: a missing GPU context, a
    driver failure), ``gpu_failed(reason)`` sends the work to the CPU (:func:`after_gpu_failure`'s reason) and
    ``solve()`` runs once more.  ``on_gpu()``: whether the failed solve ran on the GPU (a CPU failure is
    raised as it is).  The deformed frames' and the fluids' solves; an object's own solver keeps its retry
    in ``runtime._diffuse`` (its solution so far and render twin)."""
    from ..translucency_addon.errors import TranslucencyError

    try:
        return solve()
    except TranslucencyError:
        raise
    except Exception as ex:  # noqa: BLE001 - a GPU failure: once more on the CPU
        where = after_gpu_failure(ex, rendering=rendering, on_gpu=on_gpu())
        if where is None:
            raise
        gpu_failed(where.reason)
        return solve()


def free_solver(solver) -> None:
    """Release a solver's GPU resources (no-op for the CPU solver); never raises."""
    free = getattr(solver, "free", None)
    if callable(free):
        try:
            free()
        except Exception as ex:  # noqa: BLE001 - freeing must not break cleanup paths
            print(f"Translucency: freeing the solver failed: {type(ex).__name__}: {ex}")
