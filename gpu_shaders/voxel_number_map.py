"""The Voxel Number Map's transport on the GPU: ``voxel_number_map.glsl`` and its dispatch.

The kernel is the twin of ``translucency_addon.voxel_number_map.transport``'s
``pair_kernel`` followed by ``PreparedKernel.product`` (BLAS ``sspmv`` of the
packed kernel): one invocation per exit voxel sums ``S_io x_i`` over every
entry voxel, evaluating S from the fp16 LUT on the fly (so the GPU holds the
LUT, n (n + 1)/2 x 8 bytes, not the float32 kernel).  The irradiance maps,
rho and the vertex output stay on the CPU (O(n) per frame).

Uploads (counted in ``uploads``): ``"bake"`` once per map (LUT and voxel
geometry), ``"material"`` when the coefficients change (a 8 x 1 texture),
``"frame"`` the per-frame source x = A Phi.  Nothing touches ``gpu`` at
import time.  API::

    tr, backend, message = make_transmission(vnm, prefer="AUTO")   # None on the CPU
    ev = VoxelNumberMapEvaluator(vnm, material, transmission=tr)   # calls tr.set_coefficients
    ...; tr.free()

``prefer="AUTO"`` keeps the numpy/BLAS product (returns ``None``) where
:func:`gpu_shaders.available` says no, on a software rasteriser (llvmpipe: the
n^2 loop runs on the same CPU cores, slower than BLAS), where the map has
more than three component media (the LUT texel holds three lengths), or where
the LUT does not fit the texture limits; the reason is logged once.
``prefer="GPU"`` raises instead (:class:`errors.GPUUnavailable` /
:class:`errors.GraphTooLarge`); the parity test uses it on llvmpipe.
"""

from __future__ import annotations

import weakref
from collections import Counter

import numpy as np

from . import runtime
from .runtime import KernelSpec
# The texture rows and the texture limit are the single-scattering kernel's (same 4096-texel rows); the
# backend choice is gpu_shaders.make_kernel, shared with it.
from .single_scattering import TEX_W, _max_texture_size, pack_rows, rows_for

try:  # installed extension: translucency.gpu_shaders -> translucency.translucency_addon
    from ..translucency_addon import errors
except ImportError:  # top-level package (repo root on sys.path)
    from translucency_addon import errors

LOCAL_X = 64
MAX_COMPONENTS = 3
_F = "FLOAT_2D_ARRAY"
_W = frozenset({"WRITE"})

runtime.KERNELS.setdefault("vnm_transport", KernelSpec(
    "voxel_number_map.glsl",
    (("lut", _F), ("geom_a", _F), ("geom_b", _F), ("src", _F), ("coef", _F)),
    (("out_j", "RGBA32F", _W),),
    push=(("INT", "n_vox"),),
    defines=(("TEX_W", str(TEX_W)),),
    local=(LOCAL_X, 1, 1)))

_LIVE = weakref.WeakSet()


# ------------------------------------------------------------------ packing (numpy only)

def pack_map(vnm) -> dict:
    """The textures uploaded once per map: LUT (fp16-exact values) and voxel geometry (centred)."""
    C = vnm.n_components
    if C > MAX_COMPONENTS:
        raise errors.GraphTooLarge(f"the Voxel Number Map has {C} component media; the GPU kernel reads at most "
                                   f"{MAX_COMPONENTS} lengths per LUT texel")
    P = vnm.lengths.shape[1]
    lut = np.zeros((P, 4), dtype=np.float32)
    lut[:, :C] = vnm.lengths.T.astype(np.float32)
    lut[:, 3] = np.unpackbits(vnm.blocked, count=P)
    pos = np.asarray(vnm.surface.position, dtype=np.float64)
    shift = 0.5 * (pos.min(axis=0) + pos.max(axis=0))
    ga = np.zeros((vnm.n, 4), dtype=np.float32)
    ga[:, :3] = pos - shift
    gb = np.zeros((vnm.n, 4), dtype=np.float32)
    gb[:, :3] = vnm.surface.normal
    return {"lut": pack_rows(lut), "geom_a": pack_rows(ga), "geom_b": pack_rows(gb)}


def pack_coefficients(coef) -> np.ndarray:
    """(1, 1, 8, 4): texel c = h_mm sigma_t of component c, texel 4 + c = h_mm sigma_s."""
    out = np.zeros((8, 4), dtype=np.float32)
    C = len(coef.sigma_t)
    out[:C, :3] = coef.h_mm * np.asarray(coef.sigma_t)
    out[4:4 + C, :3] = coef.h_mm * np.asarray(coef.sigma_s)
    return out.reshape(1, 1, 8, 4)


class GPUTransmission:
    """Step 2 of the run time (``J = S x``) on the GPU for one baked map."""

    backend = "GPU"

    def __init__(self, vnm, max_texture_size: int | None = None):
        self.vnm = vnm
        self.n = vnm.n
        self.uploads = Counter()
        packed = pack_map(vnm)
        limit = int(max_texture_size or _max_texture_size())
        rows = packed["lut"].shape[1]
        if rows > limit:
            raise errors.GraphTooLarge(
                f"the Voxel Number Map's LUT needs a {TEX_W} x {rows} texture; this GPU allows {limit} rows "
                f"({self.n:,} surface voxels): lower the map's quality")
        runtime.shader("vnm_transport")  # compile now: a failure falls back before any frame
        self.tex = {"lut": runtime.float_texture(packed["lut"], fmt="RGBA16F"),
                    "geom_a": runtime.float_texture(packed["geom_a"]),
                    "geom_b": runtime.float_texture(packed["geom_b"])}
        self._out = runtime.float_texture(None, (1, rows_for(self.n), TEX_W))
        self.uploads["bake"] += 1
        self.lut_bytes = int(packed["lut"].size * 2)
        _LIVE.add(self)

    def set_coefficients(self, coef) -> None:
        if self.tex is None:
            raise errors.GPUUnavailable("the Voxel Number Map GPU data was freed")
        self.tex["coef"] = runtime.float_texture(pack_coefficients(coef))
        self.uploads["material"] += 1

    def product(self, x: np.ndarray) -> np.ndarray:
        """``J_o = sum_i S_io x_i`` (n, 3) for the source ``x`` (n, 3)."""
        if self.tex is None or "coef" not in self.tex:
            raise errors.GPUUnavailable("the Voxel Number Map GPU data was freed or has no coefficients")
        v = np.zeros((self.n, 4), dtype=np.float32)
        v[:, :3] = np.asarray(x, dtype=np.float64).reshape(self.n, 3)
        samplers = dict(self.tex)
        samplers["src"] = runtime.float_texture(pack_rows(v))
        self.uploads["frame"] += 1
        runtime.dispatch("vnm_transport", (TEX_W // LOCAL_X, rows_for(self.n), 1), samplers=samplers,
                         images={"out_j": self._out}, ints={"n_vox": self.n})
        return runtime.read_texture(self._out).reshape(-1, 4)[: self.n, :3].astype(np.float64)

    def free(self) -> None:
        self.tex = None
        self._out = None
        _LIVE.discard(self)


def make_transmission(vnm, prefer: str = "AUTO", **gpu_options):
    """``(transmission or None, backend, message)``: None means the numpy/BLAS product (see the module docstring).

    The choice is :func:`gpu_shaders.make_kernel`'s, the single-scattering kernel's rule."""
    from . import make_kernel

    return make_kernel(lambda: GPUTransmission(vnm, **gpu_options), prefer, what="Voxel Number Map", cpu_name="BLAS",
                       software_why="the Voxel Number Map's n^2 loop is slower than BLAS on the same cores")


def free_all() -> int:
    """Free the textures of every live Voxel Number Map GPU transmission (add-on unregister)."""
    n = 0
    for g in list(_LIVE):
        g.free()
        n += 1
    return n


__all__ = ["GPUTransmission", "make_transmission", "free_all", "pack_map", "pack_coefficients", "TEX_W"]
