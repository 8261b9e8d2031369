# SPDX-License-Identifier: GPL-3.0-or-later
"""Choose the diffusion solver: GPU compute shaders when possible, otherwise the CPU.

:func:`make_solver` asks ``gpu_shaders.make_solver`` (imported lazily, so a
missing or broken GPU layer never breaks registration) and falls back to the
engine's CPU :class:`DiffusionSolver` when ``gpu_shaders`` is missing, has no
``make_solver``, or raises.  It always returns ``(solver, backend, message)``:
``backend`` is ``"GPU"`` or ``"CPU"`` and ``message`` says why the GPU was not
used (empty when nothing needs saying).  :func:`free_solver` releases GPU
memory (``solver.free()``) when the solver has any.
"""

from __future__ import annotations

import threading


def cpu_solver(bake, material, field_values, options):
    from ..translucency_addon.diffusion import DiffusionSolver

    return DiffusionSolver(bake, material, field_values, options)


def make_solver(bake, material, field_values, options, prefer: str = "AUTO"):
    """``(solver, backend_name, message)`` for one baked object.

    ``prefer``: ``"AUTO"`` (GPU if available), ``"GPU"`` (same, but the
    fallback message is louder) or ``"CPU"``.  Off the main thread (a render
    job's thread) the GPU is never used: Blender's GPU context belongs to the
    main thread.
    """
    from ..translucency_addon.errors import MaterialError

    prefer = (prefer or "AUTO").upper()
    message = ""
    if prefer != "CPU" and threading.current_thread() is not threading.main_thread():
        message = "solving off Blender's main thread (render job): using the CPU solver"
    elif prefer != "CPU":
        try:
            from .. import gpu_shaders

            gpu_make = gpu_shaders.make_solver
        except Exception as ex:  # noqa: BLE001 - missing or broken GPU layer: fall back
            message = f"GPU solver not available ({type(ex).__name__}: {ex}); using the CPU solver"
        else:
            try:
                solver, name, gpu_message = gpu_make(bake, material, field_values, options, prefer=prefer)
            except MaterialError:
                raise  # the CPU solver would refuse the same material: report it as it is
            except Exception as ex:  # noqa: BLE001 - any GPU failure falls back to the CPU
                message = f"GPU solver failed ({type(ex).__name__}: {ex}); using the CPU solver"
            else:
                return solver, str(name or "GPU").upper(), str(gpu_message or "")
    return cpu_solver(bake, material, field_values, options), "CPU", message


def free_solver(solver) -> None:
    """Release a solver's GPU resources (no-op for the CPU solver); never raises."""
    free = getattr(solver, "free", None)
    if callable(free):
        try:
            free()
        except Exception as ex:  # noqa: BLE001 - freeing must not break cleanup paths
            print(f"Translucency: freeing the solver failed: {type(ex).__name__}: {ex}")
