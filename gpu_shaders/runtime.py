"""Thin layer over Blender's ``gpu`` module: kernels, textures, dispatch, read-back.

Rules (docs/architecture.md):

* ``gpu`` is imported inside functions only, never at import or register time:
  in background mode every ``gpu`` call raises ``SystemError`` until the GPU
  backend has started (a 1x1 Workbench render starts it, ``init_headless``),
  and add-ons that touch it at register time break ``blender -b``.
* Kernels are ``*.glsl`` files next to this module.  Each is compiled on first
  use (``common.glsl`` prepended) and cached for the session;
  :func:`free_shaders` drops the cache.
* Every dispatch goes through :func:`dispatch`, which binds the shader, sets
  its resources, dispatches and always calls ``gpu.shader.unbind()`` (also on
  errors), so no shader is left bound between calls.  ``gpu.compute.dispatch``
  itself issues the texture-fetch and image-access memory barriers.
* No storage buffers exist in Python: everything lives in 2D *array* textures
  (one layer unless a level is split, see ``pack.Layout``).  Read-only inputs
  are bound as samplers (``texelFetch``), outputs as images.
* Blender's ``Buffer`` uploads float data only; RGBA32UI textures are filled
  through ``to_uint.glsl`` (:func:`uint_texture`).  ``GPUTexture.read()`` of
  RGBA32UI returns garbage in bpy 5.0.1 on llvmpipe (R32UI and float formats
  are fine), so only float textures are ever read back, and only layer 0 of
  an array texture is returned by ``read()``: read-backs go through
  single-layer textures (``unpack.glsl``, ``reduce.glsl``, the vertex output).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
BLOCK = 32  # r of the block layout (must match quadgraph.BLOCK_SIZE and pack.Layout)
LOCAL = 16  # local group size of the per-texel kernels (LOCAL x LOCAL x 1)
REDUCE_TILE = 16  # texels per axis summed by one invocation of reduce.glsl
REDUCE_LOCAL = 8

U = "UINT_2D_ARRAY"
F = "FLOAT_2D_ARRAY"


@dataclass(frozen=True)
class KernelSpec:
    source: str  # file name in gpu_shaders/
    samplers: tuple  # ((name, sampler type), ...) read-only inputs
    images: tuple  # ((name, format, qualifiers), ...) outputs (2D array images)
    push: tuple = ()  # ((type, name), ...)
    defines: tuple = ()  # ((name, value), ...)
    local: tuple = (LOCAL, LOCAL, 1)


_COEF = (("nbr", U), ("off_r", F), ("off_g", F), ("off_b", F), ("ext", F))
W = frozenset({"WRITE"})
RW = frozenset({"READ", "WRITE"})

_PAGES = (("INT", "pages"), ("INT", "page_layers"))  # link pages (pack.link_pages; common.glsl's LINKS)

KERNELS = {
    "jacobi": KernelSpec("jacobi.glsl", _COEF + (("q", F), ("x_in", F)), (("x_out", "RGBA32F", W),), push=_PAGES),
    "residual": KernelSpec("residual.glsl", _COEF + (("q", F), ("x_in", F)), (("r_out", "RGBA32F", W),),
                           push=_PAGES),
    "chebyshev": KernelSpec(
        "chebyshev.glsl", _COEF + (("d_in", F),),
        (("x_io", "RGBA32F", RW), ("r_io", "RGBA32F", RW), ("d_out", "RGBA32F", W)),
        push=(("VEC3", "coef_d"), ("VEC3", "coef_r")) + _PAGES),
    "cheb_init": KernelSpec(
        "cheb_init.glsl", _COEF[1:] + (("r_in", F),), (("d_out", "RGBA32F", W),),
        push=(("VEC3", "inv_theta"),) + _PAGES),
    "reduce_sq": KernelSpec(
        "reduce.glsl", (("src", F),), (("dst", "RGBA32F", W),),
        defines=(("SQUARE", "1"), ("TILE", str(REDUCE_TILE))), local=(REDUCE_LOCAL, REDUCE_LOCAL, 1)),
    "reduce_sum": KernelSpec(
        "reduce.glsl", (("src", F),), (("dst", "RGBA32F", W),),
        defines=(("SQUARE", "0"), ("TILE", str(REDUCE_TILE))), local=(REDUCE_LOCAL, REDUCE_LOCAL, 1)),
    "upsample": KernelSpec(
        "upsample.glsl", (("idx_a", U), ("idx_b", U), ("w_a", F), ("w_b", F), ("x_coarse", F)),
        (("x_fine", "RGBA32F", W),)),
    "jplus": KernelSpec(
        "jplus.glsl", (("phi_in", F), ("q", F)), (("j_out", "RGBA32F", W),),
        push=(("FLOAT", "fdr"), ("INT", "surf_y0"), ("INT", "layer_h"))),
    "radiance": KernelSpec(
        "radiance.glsl", (("idx_a", U), ("idx_b", U), ("w_a", F), ("w_b", F), ("jplus", F), ("cos_o", F)),
        (("l_out", "RGBA32F", W),),
        push=(("FLOAT", "eta"), ("FLOAT", "out_scale"), ("INT", "count"), ("INT", "width"))),
    "unpack": KernelSpec(
        "unpack.glsl", (("src", F),), (("dst", "RGBA32F", W),),
        push=(("INT", "n0"), ("INT", "count"), ("INT", "n_inner"), ("INT", "per_row"),
              ("INT", "rows_inner"), ("INT", "layer_h"), ("INT", "width")),
        defines=(("BLOCK", str(BLOCK)),)),
    "to_uint": KernelSpec("to_uint.glsl", (("lo_in", F), ("hi_in", F)), (("dst", "RGBA32UI", W),)),
    "scale": KernelSpec("scale.glsl", (), (("x_io", "RGBA32F", RW),), push=(("VEC3", "s"),)),
}

_SHADERS: dict = {}
STATS = {"compiled": 0, "dispatches": 0, "bytes_up": 0, "bytes_down": 0}  # bytes: texture data uploaded / read back


def glsl_source(name: str) -> str:
    """The full compute source of kernel ``name`` (common.glsl + the kernel file)."""
    spec = KERNELS[name]
    with open(os.path.join(HERE, "common.glsl"), encoding="utf-8") as f:
        common = f.read()
    with open(os.path.join(HERE, spec.source), encoding="utf-8") as f:
        body = f.read()
    return common + "\n" + body


def shader(name: str):
    """The compiled kernel ``name`` (compiled on first use, then cached)."""
    sh = _SHADERS.get(name)
    if sh is not None:
        return sh
    import gpu

    spec = KERNELS[name]
    info = gpu.types.GPUShaderCreateInfo()
    for slot, (sname, stype) in enumerate(spec.samplers):
        info.sampler(slot, stype, sname)
    for slot, (iname, fmt, qual) in enumerate(spec.images):
        itype = "UINT_2D_ARRAY" if fmt.endswith("UI") else "FLOAT_2D_ARRAY"
        info.image(slot, fmt, itype, iname, qualifiers=set(qual))
    for ptype, pname in spec.push:
        info.push_constant(ptype, pname)
    for dname, value in spec.defines:
        info.define(dname, value)
    info.local_group_size(*spec.local)
    info.compute_source(glsl_source(name))
    try:
        sh = gpu.shader.create_from_info(info)
    except Exception as exc:  # Blender raises a bare Exception with "Shader Compile Error"
        raise RuntimeError(f"compiling GPU kernel {spec.source} failed: {exc}") from exc
    _SHADERS[name] = sh
    STATS["compiled"] += 1
    return sh


def free_shaders() -> None:
    """Drop the compiled kernels (add-on unregister); they are recompiled on next use."""
    _SHADERS.clear()


def dispatch(name: str, groups, samplers=None, images=None, floats=None, ints=None) -> None:
    """Run kernel ``name`` over ``groups`` work groups; the shader is always unbound after."""
    import gpu

    sh = shader(name)
    sh.bind()
    try:
        for key, tex in (samplers or {}).items():
            sh.uniform_sampler(key, tex)
        for key, tex in (images or {}).items():
            sh.image(key, tex)
        for key, val in (floats or {}).items():
            sh.uniform_float(key, val)
        for key, val in (ints or {}).items():
            sh.uniform_int(key, int(val))
        gpu.compute.dispatch(sh, *(int(g) for g in groups))
        STATS["dispatches"] += 1
    finally:
        gpu.shader.unbind()


def groups_for(width: int, height: int, layers: int = 1, local: int = LOCAL):
    return (-(-width // local), -(-height // local), layers)


# ------------------------------------------------------------------ textures
def float_texture(data: np.ndarray | None, shape=None, fmt: str = "RGBA32F"):
    """A 2D array texture from ``data`` (layers, height, width, channels) float32, or zeros.

    ``fmt`` RGBA32F, RGBA16F or R32F.  Values for RGBA16F should already be
    representable in fp16 (``pack.quantize``) so the upload does not round.
    """
    import gpu

    if data is not None:
        data = np.ascontiguousarray(data, dtype=np.float32)
        layers, height, width = data.shape[:3]
        buf = gpu.types.Buffer("FLOAT", data.size, data.reshape(-1))
        STATS["bytes_up"] += int(data.nbytes)
        return gpu.types.GPUTexture((width, height), layers=layers, format=fmt, data=buf)
    layers, height, width = shape
    tex = gpu.types.GPUTexture((width, height), layers=layers, format=fmt)
    tex.clear(format="FLOAT", value=(0.0, 0.0, 0.0, 0.0) if fmt.startswith("RGBA") else (0.0,))
    return tex


def uint_texture(data: np.ndarray):
    """An RGBA32UI 2D array texture from uint32 ``data`` (layers, height, width, 4).

    Uploaded as two exact float halves and joined on the GPU (``to_uint.glsl``).
    """
    data = np.ascontiguousarray(data, dtype=np.uint32)
    layers, height, width = data.shape[:3]
    lo = float_texture((data & 0xFFFF).astype(np.float32))
    hi = float_texture((data >> 16).astype(np.float32))
    import gpu

    out = gpu.types.GPUTexture((width, height), layers=layers, format="RGBA32UI")
    dispatch("to_uint", groups_for(width, height, layers), samplers={"lo_in": lo, "hi_in": hi},
             images={"dst": out})
    return out


def read_texture(tex, channels: int = 4) -> np.ndarray:
    """Layer 0 of a float texture as a (height, width, channels) float32 array.

    Blender's ``Buffer`` exports its memory with Fortran strides on C-ordered
    data, so ``ravel(order="K")`` (memory order) is used: it is also right if
    a later Blender exports C strides.
    """
    buf = tex.read()
    flat = np.asarray(buf).ravel(order="K")
    STATS["bytes_down"] += int(flat.nbytes)
    return flat.reshape(tex.height, tex.width, channels).astype(np.float32, copy=True)
