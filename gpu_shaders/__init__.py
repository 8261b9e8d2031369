"""GPU backend of the diffusion solve: GLSL compute kernels run through Blender's ``gpu`` module.

Nothing here imports ``gpu`` at import time (``blender -b`` and add-on
registration must not touch it).  The API (the add-on's ``ops.backend``
decides GPU or CPU and asks with ``prefer="GPU"``; scripts and benches may
let ``prefer="AUTO"`` fall back here)::

    from .gpu_shaders import available, make_solver, free_all

    ok, reason = available()                       # cheap; never raises
    solver, backend, message = make_solver(bake, material, field_values, options, prefer="AUTO")
    # backend: "GPU" or "CPU"; message: why, to show in the UI (also logged once per session)
    result = solver.solve(lights, environment)     # same call for both backends
    L = solver.vertex_radiance(result)             # (n_vertices, 3)
    solver.set_material(material, field_values)    # after a material edit (re-uploads coefficients only)
    solver.free()                                  # object/bake removed (GPU solver; safe twice)
    free_all()                                     # add-on unregister: all GPU textures + compiled kernels

Files: ``*.glsl`` (the kernels, one per numpy twin in
``translucency_addon.diffusion.kernels``), ``runtime.py`` (compile, cache, dispatch,
textures), ``pack.py`` (texture layout and packing, numpy only),
``device.py`` (a level's textures and kernel calls), ``solver.py``
(``GPUDiffusionSolver``).
"""

from __future__ import annotations

import logging
import warnings

log = logging.getLogger(__name__)

PREFERENCES = ("AUTO", "GPU", "CPU")
_LOGGED: set = set()


def _log_once(message: str) -> None:
    """Log a fallback reason once per session (and print it: the console of ``blender -b``)."""
    if message not in _LOGGED:
        _LOGGED.add(message)
        log.warning(message)
        print(f"Translucency: {message}", flush=True)


def init_headless() -> str:
    """Start Blender's GPU backend in background mode (``blender -b``, bpy from PyPI).

    Every ``gpu`` call raises ``SystemError`` there until Blender has set up
    its GPU backend; a 1x1 Workbench render of a temporary scene does that in
    about a second (the trick Blender's own test scripts use; measured with bpy
    4.2 to 5.2 from PyPI on Linux without a display).
    The user's scenes are not touched.  Returns the renderer string; raises
    what the render raised when it cannot start.  Never call it at import or
    register time.
    """
    import bpy
    import gpu

    try:
        return gpu.platform.renderer_get()
    except SystemError:
        pass
    scene = bpy.data.scenes.new("translucency-gpu-init")
    cam_data = bpy.data.cameras.new("translucency-gpu-init")
    cam = bpy.data.objects.new("translucency-gpu-init", cam_data)
    try:
        scene.collection.objects.link(cam)
        scene.camera = cam
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 1
        scene.render.resolution_percentage = 100
        bpy.ops.render.render(scene=scene.name)
    finally:
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
        bpy.data.scenes.remove(scene)
    return gpu.platform.renderer_get()


def available() -> tuple[bool, str]:
    """Whether compute shaders can run now: ``(True, renderer)`` or ``(False, reason)``. Never raises."""
    try:
        import gpu
    except ImportError:
        return False, "Blender's gpu module is not available (not running inside Blender)"
    try:
        renderer = gpu.platform.renderer_get()
    except SystemError:  # background mode before the GPU backend is initialised
        # Blender's own text ("... requires the gpu module to be initialized. See gpu.init.") names
        # an internal call a user cannot make; say what it means instead.
        return False, ("Blender's GPU backend is not running in this process: in background mode "
                       "(blender -b, bpy as a Python module) Blender starts it only for a Workbench or "
                       "EEVEE render")
    except Exception as exc:  # noqa: BLE001 - any failure means: no GPU here
        return False, f"no GPU context ({type(exc).__name__}: {exc})"
    try:
        with warnings.catch_warnings():  # deprecated (always true) in Blender 5.0, meaningful before
            warnings.simplefilter("ignore", DeprecationWarning)
            supported = gpu.capabilities.compute_shader_support_get()
    except Exception as exc:  # noqa: BLE001 - a driver or backend failure means: no usable GPU here
        return False, f"cannot query GPU capabilities ({type(exc).__name__}: {exc})"
    if not supported:
        return False, f"the GPU backend ({renderer}) has no compute shader support"
    return True, renderer or "unknown renderer"


def storage_buffers() -> tuple[bool, str]:
    """Whether this Blender's Python ``gpu`` module lets a compute shader bind a storage buffer.

    The kernels pack the QuadGraph into 2D textures (image load/store and
    samplers) because Blender 4.2-5.2 expose no storage buffer to Python:
    ``gpu.types`` has no ``GPUStorageBuf`` and ``GPUShaderCreateInfo`` no
    ``storage_buf`` (checked in 4.2.23, 4.5.15, 5.0.1, 5.1.2 and 5.2.3; Blender's
    main branch has a ``GPUStorageBuf`` type).  When a release has both, the
    texture limits and the multi-pass reduction could go; until then this
    says why the texture path runs.  Never raises; needs no GPU context.
    """
    try:
        import gpu
    except ImportError:
        return False, "Blender's gpu module is not available (not running inside Blender)"
    missing = [name for name, ok in (
        ("gpu.types.GPUStorageBuf", hasattr(gpu.types, "GPUStorageBuf")),
        ("GPUShaderCreateInfo.storage_buf", hasattr(gpu.types.GPUShaderCreateInfo, "storage_buf")),
    ) if not ok]
    if missing:
        return False, f"this Blender's Python gpu module has no {' and no '.join(missing)}: textures carry the graph"
    return True, "storage buffers are exposed to Python compute shaders"


def make_solver(bake, material, field_values=None, options=None, prefer: str = "AUTO", **gpu_options):
    """A diffusion solver for ``bake``: ``(solver, backend_name, message)``.

    ``prefer``: ``"AUTO"`` (GPU when possible, else the CPU with a message),
    ``"GPU"`` (raise :class:`errors.GPUUnavailable` / :class:`errors.GraphTooLarge`
    instead of falling back) or ``"CPU"``.  ``gpu_options`` go to
    :class:`GPUDiffusionSolver` (``precision``, ``readback``, ...).  Material
    errors are raised whatever the backend.  The fallback reason is logged
    once per session and returned every time.
    """
    from ._engine import diffusion, errors

    prefer = str(prefer).upper()
    if prefer not in PREFERENCES:
        raise errors.TranslucencyError(f"unknown backend preference {prefer!r}; choose one of {', '.join(PREFERENCES)}")
    options = options or diffusion.SolveOptions()

    def cpu(message: str):
        if prefer == "AUTO":
            _log_once(message)
        return diffusion.DiffusionSolver(bake, material, field_values, options), "CPU", message

    if prefer == "CPU":
        return cpu("CPU solver selected")
    if options.solver == "direct":
        if prefer == "GPU":
            raise errors.GPUUnavailable("the direct solver has no GPU version; choose 'fast' or 'paper'")
        return cpu("the direct solver runs on the CPU only")
    ok, reason = available()
    if not ok:
        if prefer == "GPU":
            raise errors.GPUUnavailable(f"GPU solver unavailable: {reason}")
        return cpu(f"GPU solver unavailable ({reason}); using the CPU solver")
    from .solver import GPUDiffusionSolver

    try:
        solver = GPUDiffusionSolver(bake, material, field_values, options, **gpu_options)
    except errors.GraphTooLarge as exc:
        if prefer == "GPU":
            raise
        return cpu(f"{exc}; using the CPU solver")
    except errors.TranslucencyError:
        raise  # material or option errors: the same on every backend
    except Exception as exc:  # noqa: BLE001 - shader compile or driver failure
        if prefer == "GPU":
            raise errors.GPUUnavailable(f"GPU solver failed to start: {type(exc).__name__}: {exc}") from exc
        return cpu(f"GPU solver failed to start ({type(exc).__name__}: {exc}); using the CPU solver")
    return solver, "GPU", f"GPU solver on {reason} ({solver.precision})"


def make_kernel(build, prefer: str = "AUTO", *, what: str, cpu_name: str, software_why: str):
    """The backend choice of an optional pass's kernel: ``(kernel or None, backend, message)``.

    One rule for the single-scattering ray pass (``single_scattering.make_integrator``) and the
    Voxel Number Map's transport (``voxel_number_map.make_transmission``): ``build()`` makes the
    GPU kernel object; ``what`` names it in messages, ``cpu_name`` is its CPU twin ("numpy",
    "BLAS") and ``software_why`` says why the twin wins on a software rasteriser.

    ``prefer``: ``"CPU"`` -> ``(None, "CPU", ...)``; ``"AUTO"`` -> the kernel when
    :func:`available` says yes, the renderer is not a software rasteriser
    (:data:`single_scattering.SOFTWARE_RENDERERS`) and ``build()`` succeeds, else ``None`` with
    the reason (logged once); ``"GPU"`` -> the kernel wherever it builds (llvmpipe included),
    else :class:`errors.GPUUnavailable` / :class:`errors.GraphTooLarge`.
    """
    from ._engine import errors
    from .single_scattering import SOFTWARE_RENDERERS

    prefer = str(prefer).upper()
    if prefer not in PREFERENCES:
        raise errors.TranslucencyError(f"unknown backend preference {prefer!r}; choose one of {', '.join(PREFERENCES)}")
    if prefer == "CPU":
        return None, "CPU", f"CPU ({cpu_name}) selected"
    ok, reason = available()
    if not ok:
        if prefer == "GPU":
            raise errors.GPUUnavailable(f"{what} GPU kernel unavailable: {reason}")
        message = f"{what} GPU kernel unavailable ({reason}); using {cpu_name}"
    elif prefer == "AUTO" and any(name in reason.lower() for name in SOFTWARE_RENDERERS):
        message = f"the GPU ({reason}) is a software rasteriser, on which {software_why}; using {cpu_name}"
    else:
        try:
            return build(), "GPU", f"{what} kernel on {reason}"
        except errors.GraphTooLarge as exc:
            if prefer == "GPU":
                raise
            message = f"{exc}; using {cpu_name}"
        except Exception as exc:  # noqa: BLE001 - compile or driver failure
            if prefer == "GPU":
                raise errors.GPUUnavailable(f"{what} GPU kernel failed to start: {type(exc).__name__}: {exc}") from exc
            message = f"{what} GPU kernel failed to start ({type(exc).__name__}: {exc}); using {cpu_name}"
    _log_once(message)
    return None, "CPU", message


def free_all() -> int:
    """Free every GPU resource of this package (call on add-on unregister): the textures of
    every diffusion solver, single-scattering integrator and Voxel Number Map transmission, and
    the compiled kernels.
    Returns how many solvers/integrators were freed; safe to call again."""
    import sys

    n = 0
    for sub in ("solver", "single_scattering", "voxel_number_map"):  # only imported modules can own textures
        mod = sys.modules.get(f"{__name__}.{sub}")
        if mod is not None and hasattr(mod, "free_all"):
            n += mod.free_all()
    runtime = sys.modules.get(f"{__name__}.runtime")
    if runtime is not None:
        runtime.free_shaders()
    return n


__all__ = ["available", "make_solver", "make_kernel", "free_all", "PREFERENCES"]
