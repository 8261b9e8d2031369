"""Single scattering on the GPU: the per-ray pass of eq. 3 as one compute kernel.

``single_scattering.glsl`` is the twin of
``translucency_addon.single_scattering.runtime.integrate_view_rays`` (times
``exit_factor``): one invocation per view ray walks the uniform sample grid
(3D DDA over the CSR cell lists) and sums, for every Gaussian it passes, the
closed-form chord integral (erf) times psi toward the viewer (per ray from
the SH, or the per-sample view term) times the per-sample light term, then
applies the exit factor ``F_t(cos_o, eta) / eta^2`` and ``mm_per_unit``.

Uploads (counted in ``uploads``):

* ``"bake"``: once per baked data set -- samples, SH, cell lists, grid
  (``SingleScatteringData.kernel_arrays()``, see :func:`pack_bake`);
* ``"rays"``: when the view rays change (camera moved, mesh edited);
* ``"frame"``: the per-sample coefficient (light term, times the view term
  when psi is per sample) -- the only upload of a frame in which only the
  lights changed.

The light term and the view term stay on the CPU (one SH evaluation per
sample and light: cheap next to the ray pass).  Nothing here touches ``gpu``
at import time.  API::

    integ, backend, message = make_integrator(data, prefer="AUTO")
    L = integ.integrate(light_term, rays, view_term=None, eta=1.3, mm_per_unit=mm)   # (n_rays, 3)
    integ.free()

With ``prefer="AUTO"``, ``make_integrator`` runs the numpy twin
(``CPUIntegrator``, inside an :class:`AutoIntegrator`) when
:func:`gpu_shaders.available` says no, when the renderer is a software
rasteriser (llvmpipe: the kernel is ~5x slower than numpy there, measured),
when the kernel does not compile or the data does not fit the texture
limits; the reason is logged once per session.  ``prefer="GPU"`` runs the
kernel wherever it can (llvmpipe included) and raises otherwise.

Accuracy: float32 throughout; erf is the Maclaurin series below |x| = 0.5
and Numerical Recipes' ``erfcc`` above (relative error <= 4e-7 measured in
float32); against the float64 twin the radiance agrees to <= 1e-6 of its
maximum on llvmpipe (``tests/test_gpu_single_scattering.py``, tolerance 1e-5).  :class:`AutoIntegrator` (``prefer="AUTO"``) also falls back *per
call* when a dispatch fails (e.g. no active GPU context inside a render
handler): that call runs on the CPU, and the GPU is kept for later calls if
the failure was a missing context, dropped otherwise.
"""

from __future__ import annotations

import weakref
from collections import Counter

import numpy as np

from . import _LOGGED, _log_once, runtime  # noqa: F401 - _LOGGED: the one set of messages logged once
from .runtime import KernelSpec

try:  # installed extension: translucency.gpu_shaders -> translucency.translucency_addon
    from ..translucency_addon import errors
    from ..translucency_addon.single_scattering import runtime as ss_runtime
except ImportError:  # top-level package (repo root on sys.path)
    from translucency_addon import errors
    from translucency_addon.single_scattering import runtime as ss_runtime

TEX_W = 4096  # width of every 1D-in-2D texture of the kernel (texels)
LOCAL_X = 64  # local group size (LOCAL_X x 1 x 1), one invocation per ray
KEPT_RAY_SETS = 3  # ray sets whose textures stay resident: a frame's view rays and their reflections inside
BIG = 1.0e30  # "no far clip" (t_exit = inf) in the ray texture
_F = "FLOAT_2D_ARRAY"
_U = "UINT_2D_ARRAY"
_W = frozenset({"WRITE"})

# Registered in the shared kernel table (no gpu call): compiled lazily by runtime.shader,
# dropped by runtime.free_shaders (gpu_shaders.free_all, add-on unregister).
runtime.KERNELS.setdefault("ss_integrate", KernelSpec(
    "single_scattering.glsl",
    (("samp_a", _F), ("samp_b", _F), ("sh", _F), ("coef", _F), ("cell_start", _U), ("cell_items", _U),
     ("grid", _F), ("ray_o", _F), ("ray_d", _F)),
    (("out_l", "RGBA32F", _W),),
    push=(("INT", "n_rays"), ("INT", "per_ray_psi"), ("INT", "sh_k"), ("FLOAT", "eta"), ("FLOAT", "out_scale")),
    defines=(("TEX_W", str(TEX_W)),),
    local=(LOCAL_X, 1, 1)))
runtime.KERNELS.setdefault("ss_erf_test", KernelSpec(
    "single_scattering.glsl", (("ray_o", _F),), (("out_l", "RGBA32F", _W),), push=(("INT", "n_rays"),),
    defines=(("TEX_W", str(TEX_W)), ("SS_ERF_TEST", "1")), local=(LOCAL_X, 1, 1)))

# AUTO runs the ray pass in numpy on software rasterisers: measured on llvmpipe (2 cores, bunny,
# 20k samples) the kernel took 2.3 s per camera frame against 0.47 s in numpy (0.04 s with cached
# ray-sample pairs).  prefer="GPU" still runs the kernel there (the parity tests do).
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer", "basic render driver")

_LIVE = weakref.WeakSet()


# ------------------------------------------------------------------ packing (numpy only)

def rows_for(n: int, per_texel: int = 1) -> int:
    """Texture rows (of TEX_W texels) for n values, per_texel values per texel."""
    return max(1, -(-int(n) // (TEX_W * per_texel)))


def pack_rows(values: np.ndarray) -> np.ndarray:
    """(n, 4) float32 rows -> (1, rows, TEX_W, 4), row-major, zero padded."""
    v = np.asarray(values, dtype=np.float32).reshape(-1, 4)
    out = np.zeros((rows_for(len(v)) * TEX_W, 4), dtype=np.float32)
    out[: len(v)] = v
    return out.reshape(1, -1, TEX_W, 4)


def pack_uints(values: np.ndarray) -> np.ndarray:
    """(n,) uint32 -> (1, rows, TEX_W, 4): value j in texel j // 4, component j % 4."""
    v = np.asarray(values, dtype=np.uint32).reshape(-1)
    out = np.zeros(rows_for(len(v), 4) * TEX_W * 4, dtype=np.uint32)
    out[: len(v)] = v
    return out.reshape(1, -1, TEX_W, 4)


def pack_bake(data) -> dict:
    """Everything uploaded once per bake, as texture arrays, plus ``shift`` and ``sh_k``.

    Positions are shifted so that the sample grid is centred on the origin
    (smaller magnitudes: less float32 cancellation in ``b - o``).
    """
    k = data.kernel_arrays()
    grid = k["grid"].astype(np.float64)
    shift = grid[:3] + 0.5 * grid[4:7] * grid[3]
    samples = k["samples"].astype(np.float64)
    a = np.zeros((len(samples), 4), dtype=np.float32)
    a[:, :3] = samples[:, :3] - shift
    a[:, 3] = samples[:, 3]
    b = np.zeros((len(samples), 4), dtype=np.float32)
    b[:, 0] = samples[:, 4]
    b[:, 1] = samples[:, 5]
    g = np.zeros((2, 4), dtype=np.float32)
    g[0, :3] = grid[:3] - shift
    g[0, 3] = grid[3]
    g[1, :3] = grid[4:7]
    sh = k["sh"]
    return {"samp_a": pack_rows(a), "samp_b": pack_rows(b), "sh": pack_rows(sh.reshape(-1, 4)),
            "cell_start": pack_uints(k["cell_start"]), "cell_items": pack_uints(k["cell_items"]),
            "grid": g.reshape(1, 1, 2, 4), "shift": shift, "sh_k": int(sh.shape[1]), "n_samples": int(len(samples))}


def pack_rays(origins, dirs, t_exit, cos_o, shift) -> tuple[np.ndarray, np.ndarray]:
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    ro = np.zeros((len(o), 4))
    ro[:, :3] = o - np.asarray(shift)
    ro[:, 3] = np.minimum(np.nan_to_num(np.asarray(t_exit, dtype=np.float64), nan=0.0, posinf=BIG), BIG)
    rd = np.zeros((len(o), 4))
    rd[:, :3] = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    rd[:, 3] = np.asarray(cos_o, dtype=np.float64).reshape(-1)
    return pack_rows(ro), pack_rows(rd)


def _max_texture_size() -> int:
    import gpu

    try:
        return int(gpu.capabilities.max_texture_size_get())
    except Exception:  # noqa: BLE001 - no GPU context or a driver failure: assume the common limit
        return 16384


# ------------------------------------------------------------------ GPU integrator

class GPUSingleScattering:
    """The per-ray pass on the GPU for one baked :class:`SingleScatteringData`."""

    backend = "GPU"
    last_backend = "GPU"

    def __init__(self, data, max_texture_size: int | None = None):
        self.data = data
        self.uploads = Counter()
        packed = pack_bake(data)
        limit = int(max_texture_size or _max_texture_size())
        tallest = max(packed[k].shape[1] for k in ("samp_a", "sh", "cell_start", "cell_items"))
        if tallest > limit:
            raise errors.GraphTooLarge(
                f"the single-scattering data needs a {TEX_W} x {tallest} texture; this GPU allows {limit} rows "
                f"({data.n_samples} samples, {len(data.grid.cell_items)} grid entries): lower the sample count")
        runtime.shader("ss_integrate")  # compile now: a failure falls back before any frame
        self.shift = packed["shift"]
        self.sh_k = packed["sh_k"]
        self.n_samples = packed["n_samples"]
        self.tex = {
            "samp_a": runtime.float_texture(packed["samp_a"]),
            "samp_b": runtime.float_texture(packed["samp_b"]),
            "sh": runtime.float_texture(packed["sh"]),
            "cell_start": runtime.uint_texture(packed["cell_start"]),
            "cell_items": runtime.uint_texture(packed["cell_items"]),
            "grid": runtime.float_texture(packed["grid"]),
        }
        self.uploads["bake"] += 1
        self._rays = None  # the ViewRays (or tuple) whose textures are resident
        self._kept: list = []  # (ViewRays, ray textures, ray count, output texture), newest first
        self._ray_tex: dict = {}
        self._n_rays = 0
        self._out = None
        _LIVE.add(self)

    # -- uploads ------------------------------------------------------------------------------
    def set_rays(self, origins, dirs, t_exit, cos_o) -> None:
        """Upload view rays (origins/dirs in object units, dirs into the object, cos_o = n . w_o)."""
        ro, rd = pack_rays(origins, dirs, t_exit, cos_o, self.shift)
        self._ray_tex = {"ray_o": runtime.float_texture(ro), "ray_d": runtime.float_texture(rd)}
        self._n_rays = int(len(np.asarray(t_exit).reshape(-1)))
        if self._out is None or self._out.height != ro.shape[1]:
            self._out = runtime.float_texture(None, (1, ro.shape[1], TEX_W))
        self.uploads["rays"] += 1

    def _ensure_rays(self, rays) -> None:
        """Make ``rays`` the resident set.  The last :data:`KEPT_RAY_SETS` sets keep their textures: a frame
        integrates its view rays and their reflections inside (``single_scattering/view_reflection.py``), so
        a frame that moves only the lights uploads none of them again."""
        if self._rays is rays:
            return
        for r, tex, n, out in self._kept:
            if r is rays:
                self._ray_tex, self._n_rays, self._out, self._rays = tex, n, out, rays
                return
        self.set_rays(rays.origins, rays.dirs, rays.t_exit, rays.cos_o)
        self._rays = rays
        self._kept = [(rays, self._ray_tex, self._n_rays, self._out)] + self._kept[:KEPT_RAY_SETS - 1]

    def run(self, coef, per_ray_psi: bool, eta: float, mm_per_unit: float) -> np.ndarray:
        """Dispatch over the resident rays with the per-sample coefficient ``coef`` (N, 3)."""
        if self.tex is None:
            raise errors.GPUUnavailable("the single-scattering GPU data was freed")
        if self._n_rays == 0:
            return np.zeros((0, 3))
        c = np.zeros((self.n_samples, 4), dtype=np.float32)
        c[:, :3] = np.asarray(coef, dtype=np.float64).reshape(self.n_samples, 3)
        coef_tex = runtime.float_texture(pack_rows(c))
        self.uploads["frame"] += 1
        samplers = dict(self.tex)
        samplers.update(self._ray_tex)
        samplers["coef"] = coef_tex
        eta = float(eta)
        rows = self._out.height
        runtime.dispatch("ss_integrate", (TEX_W // LOCAL_X, rows, 1), samplers=samplers, images={"out_l": self._out},
                         floats={"eta": eta, "out_scale": float(mm_per_unit) / (eta * eta)},
                         ints={"n_rays": self._n_rays, "per_ray_psi": int(bool(per_ray_psi)), "sh_k": self.sh_k})
        out = runtime.read_texture(self._out).reshape(-1, 4)[: self._n_rays, :3]
        return out.astype(np.float64)

    def integrate(self, light_term, rays, *, view_term=None, eta: float, mm_per_unit: float | None = None,
                  use_gpu: bool = True):
        """Outgoing radiance per ray of ``rays`` (a :class:`ViewRays`), (n_rays, 3).

        Same arguments and result as :meth:`CPUIntegrator.integrate` (``use_gpu`` is ignored).
        """
        mm = self.data.mm_per_unit if mm_per_unit is None else float(mm_per_unit)
        self._ensure_rays(rays)
        LT = np.asarray(light_term, dtype=np.float64)
        if view_term is not None:
            return self.run(LT * np.asarray(view_term, dtype=np.float64), False, eta, mm)
        return self.run(LT, True, eta, mm)

    def free(self) -> None:
        self.tex = None
        self._ray_tex = {}
        self._out = None
        self._rays = None
        self._kept = []
        _LIVE.discard(self)


def erf_on_gpu(x: np.ndarray) -> np.ndarray:
    """The kernel's ``erf_approx`` at ``x`` (test helper; needs a GPU context)."""
    x = np.asarray(x, dtype=np.float32).reshape(-1)
    v = np.zeros((len(x), 4), dtype=np.float32)
    v[:, 0] = x
    tex_in = runtime.float_texture(pack_rows(v))
    out = runtime.float_texture(None, (1, tex_in.height, TEX_W))
    runtime.dispatch("ss_erf_test", (TEX_W // LOCAL_X, tex_in.height, 1), samplers={"ray_o": tex_in},
                     images={"out_l": out}, ints={"n_rays": len(x)})
    return runtime.read_texture(out).reshape(-1, 4)[: len(x), 0].copy()


def erf_approx_numpy(x) -> np.ndarray:
    """The kernel's erf formula evaluated in float32 with numpy (documentation and tests)."""
    x = np.asarray(x, dtype=np.float32)
    ax = np.abs(x)
    z = x * x
    p = np.float32(1.0 / 9360.0)
    for c in (-1.0 / 1320.0, 1.0 / 216.0, -1.0 / 42.0, 1.0 / 10.0, -1.0 / 3.0, 1.0):
        p = p * z + np.float32(c)
    small = np.float32(1.1283791670955126) * x * p
    t = np.float32(1.0) / (np.float32(1.0) + np.float32(0.5) * ax)
    coeffs = (-1.26551223, 1.00002368, 0.37409196, 0.09678418, -0.18628806, 0.27886807, -1.13520398, 1.48851587,
              -0.82215223, 0.17087277)
    poly = np.float32(coeffs[-1])
    for c in coeffs[-2::-1]:
        poly = np.float32(c) + t * poly
    with np.errstate(under="ignore", over="ignore"):
        erfc = t * np.exp(-ax * ax + poly)
    big = np.where(x < 0, -(1 - erfc), 1 - erfc)
    return np.where(ax < 0.5, small, big).astype(np.float32)


# ------------------------------------------------------------------ selection and fallback

def _no_context(exc: BaseException) -> bool:
    """A failure that means 'no usable GPU context right now' (render thread, background mode)."""
    text = f"{type(exc).__name__}: {exc}".lower()
    return isinstance(exc, SystemError) or "context" in text or "background mode" in text


class AutoIntegrator:
    """GPU when it works, the numpy twin otherwise; falls back per call (see the module docstring)."""

    def __init__(self, data, gpu_integrator, message: str = ""):
        self.data = data
        self.gpu = gpu_integrator
        self.cpu = ss_runtime.CPUIntegrator(data)
        self.message = message
        self.last_backend = "GPU" if gpu_integrator is not None else "CPU"

    @property
    def backend(self) -> str:
        return "GPU" if self.gpu is not None else "CPU"

    def integrate(self, light_term, rays, *, view_term=None, eta: float, mm_per_unit: float | None = None,
                  use_gpu: bool = True):
        if use_gpu and self.gpu is not None:
            try:
                out = self.gpu.integrate(light_term, rays, view_term=view_term, eta=eta, mm_per_unit=mm_per_unit)
                self.last_backend = "GPU"
                return out
            except errors.TranslucencyError:
                raise
            except Exception as exc:  # noqa: BLE001 - no context (render handler), driver failure
                transient = _no_context(exc)
                reason = f"{type(exc).__name__}: {exc}"
                if transient:
                    self.message = f"single scattering on the CPU where no GPU context is active ({reason})"
                else:
                    self.message = f"the single-scattering GPU kernel failed ({reason}); using numpy"
                    self.gpu.free()
                    self.gpu = None
                _log_once(self.message)
        self.last_backend = "CPU"
        return self.cpu.integrate(light_term, rays, view_term=view_term, eta=eta, mm_per_unit=mm_per_unit)

    def free(self) -> None:
        if self.gpu is not None:
            self.gpu.free()
            self.gpu = None


def make_integrator(data, prefer: str = "AUTO", **gpu_options):
    """``(integrator, backend, message)`` for one baked data set.

    ``prefer``: ``"AUTO"`` (an :class:`AutoIntegrator`: the GPU when
    :func:`gpu_shaders.available` says yes, the renderer is not a software
    rasteriser (:data:`SOFTWARE_RENDERERS`) and the kernel compiles, else the
    numpy twin, the reason logged once), ``"GPU"`` (a bare
    :class:`GPUSingleScattering`; raise :class:`errors.GPUUnavailable` /
    :class:`errors.GraphTooLarge` instead of falling back) or ``"CPU"``.
    The choice is :func:`gpu_shaders.make_kernel`'s (the Voxel Number Map's too).
    """
    from . import make_kernel

    gpu_int, backend, message = make_kernel(
        lambda: GPUSingleScattering(data, **gpu_options), prefer, what="single-scattering", cpu_name="numpy",
        software_why="the single-scattering ray pass is faster in numpy")
    if str(prefer).upper() == "CPU":
        return ss_runtime.CPUIntegrator(data), "CPU", message
    if gpu_int is None:
        return AutoIntegrator(data, None, message), "CPU", message
    if str(prefer).upper() == "GPU":
        return gpu_int, "GPU", message
    return AutoIntegrator(data, gpu_int, ""), "GPU", message


def free_all() -> int:
    """Free the textures of every live GPU single-scattering integrator (add-on unregister)."""
    n = 0
    for g in list(_LIVE):
        g.free()
        n += 1
    return n


__all__ = ["GPUSingleScattering", "AutoIntegrator", "make_integrator", "free_all", "pack_bake", "pack_rays",
           "erf_on_gpu", "erf_approx_numpy", "TEX_W"]
