"""Packing a QuadGraph level into textures (Wang et al. 2010, sec. 5.1, Fig. 6-7).

Pure numpy: nothing here touches ``gpu``, so the packing is tested and
benchmarked without a GPU context.

Layout
------
Every node is one texel of a set of 2D *array* textures, all with the same
(width, height, layers).  Nodes keep the bake's order (``quadgraph``: inner
nodes first, then surface nodes, each grown breadth-first into r x r blocks,
r = 32).  Block ``b`` of a group sits at block column ``b % per_row`` and
block row ``b // per_row``; surface blocks start on a new block row
(``rows_inner``), so the texture is split along v between inner and surface
nodes and the node kind follows from the row (``jplus.glsl``).

Block rows beyond the device's maximum texture size continue in further
layers (``rows_per_layer`` block rows per layer); the width is capped at the
maximum size too.  When even that does not fit (more layers than the device
or the address format allows) :class:`GraphTooLarge` is raised with the
numbers.

A neighbour reference is the packed texel address ``x | y << 14 | layer << 28``
(``common.glsl``), ``NONE = 0xFFFFFFFF``; hence width and height are at most
16384 and there are at most 15 layers.

Data per level (``(layers, height, width, 4)`` float32 arrays, uint32 for addresses):

* ``nbr``: the 4 neighbour addresses (RGBA32UI), once per bake;
* ``off_r, off_g, off_b``: c_ij for the 4 links, one texture per colour channel;
* a graph with more than 4 link slots per node (a particle fluid's cells: 15-25) keeps them in link
  pages, 4 per page, page g in layers ``g * layers ...`` of ``nbr`` and ``off_*`` (:func:`link_pages`);
* ``ext``: rgb = e_i = a_ii - sum_j c_ij (absorption/boundary part of the
  diagonal; the kernels form a_ii = e_i + sum_j c_ij in fp32), a = b_scale_i at surface nodes and the
  largest b_scale at inner nodes (``inner_unit``: a unit of the others' size, so fp16's scale stays
  theirs), times the coefficients' scale; with ``off_*`` re-uploaded after a material edit;
* ``q``: the incident light at surface nodes and the lamps' volume source over ``inner_unit`` at inner
  nodes (``diffusion.beam_source``; 0 without one), per frame; b_i = a_i q_i is formed in the kernels;
* Shepard transfer (eq. 10, levels >= 1): 8 coarse addresses in two RGBA32UI
  textures and 8 weights in two float textures;
* the vertex map (finest level) in a separate row-major vertex layout.

Precision
---------
``"fp32"`` stores everything in RGBA32F.  ``"fp16"`` stores the coefficients,
q and the Shepard weights in RGBA16F, as the paper does; the iterates (phi,
r, d) stay fp32 (a fp16 residual could not reach a 1e-4 relative tolerance)
and so do the vertex-map weights (they scale the output directly).  fp16
values are rounded on the host (:func:`quantize`) so the upload is exact and
the numpy twins can be fed the very same numbers.  To stay in fp16's normal
range the coefficients of a level are multiplied by one power of two (the
solution and the relative residual do not change) and q by another (the
solution scales with it; the solver divides it out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._engine import errors, quadgraph

NONE = np.uint32(0xFFFFFFFF)
ADDRESS_MAX = 16384  # x and y fields of an address are 14 bits
LAYERS_MAX = 15  # 4 bits; layer 15 with x = y = 16383 would be NONE
PRECISIONS = ("fp32", "fp16")
FP16_MAX = 65504.0
FP16_MIN_NORMAL = 2.0**-14
FP16_TARGET = 2.0**11  # coefficients/q are scaled so their maximum is near this


@dataclass(frozen=True)
class Layout:
    """Texel placement of one level's nodes (see the module docstring)."""

    n_inner: int
    n_surface: int
    block: int
    per_row: int
    rows_inner: int
    rows_surface: int
    rows_per_layer: int
    layers: int

    @property
    def n_nodes(self) -> int:
        return self.n_inner + self.n_surface

    @property
    def width(self) -> int:
        return self.per_row * self.block

    @property
    def height(self) -> int:
        """Height of one layer in texels."""
        return self.rows_per_layer * self.block

    @property
    def shape(self) -> tuple:
        """(layers, height, width) of every node texture."""
        return (self.layers, self.height, self.width)

    @property
    def surf_y0(self) -> int:
        """Global texel row (layer * height + y) where the surface region starts."""
        return self.rows_inner * self.block

    @property
    def texels(self) -> int:
        return self.layers * self.height * self.width

    def texel(self, n) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, layer) of nodes ``n`` (same formula as unpack.glsl)."""
        n = np.asarray(n, dtype=np.int64)
        surf = n >= self.n_inner
        local = np.where(surf, n - self.n_inner, n)
        row0 = np.where(surf, self.rows_inner, 0)
        B = self.block * self.block
        b, o = np.divmod(local, B)
        bx = b % self.per_row
        by = b // self.per_row + row0
        x = bx * self.block + o % self.block
        row = by * self.block + o // self.block
        layer, y = np.divmod(row, self.height)
        return x, y, layer

    def flat_index(self, n=None) -> np.ndarray:
        """Index of node n's texel in a flattened (layers, height, width) array."""
        if n is None:
            n = np.arange(self.n_nodes)
        x, y, layer = self.texel(n)
        return (layer * self.height + y) * self.width + x

    def address(self, n=None) -> np.ndarray:
        """Packed texel addresses (uint32) of nodes ``n`` (all nodes by default)."""
        if n is None:
            n = np.arange(self.n_nodes)
        x, y, layer = self.texel(n)
        return (x | (y << 14) | (layer << 28)).astype(np.uint32)


def plan_layout(n_inner: int, n_surface: int, block: int = quadgraph.BLOCK_SIZE,
                max_size: int = 16384, max_layers: int = LAYERS_MAX, what: str = "level") -> Layout:
    """Choose the texture layout of a level within the device limits, or raise GraphTooLarge.

    ``max_size``: ``gpu.capabilities.max_texture_size_get()`` (or a smaller
    test value); ``max_layers``: ``max_texture_layers_get()``.
    """
    cap = min(int(max_size), ADDRESS_MAX)
    max_layers = min(int(max_layers), LAYERS_MAX)
    if cap < block:
        raise errors.GraphTooLarge(
            f"the GPU's maximum texture size ({max_size}) is smaller than one {block}x{block} block of the "
            f"QuadGraph packing; use the CPU solver")
    _w, h, per_row, rows_inner = quadgraph.tex_layout(n_inner, n_surface, block, max_width=cap)
    total_rows = max(h // block, 1)
    rows_surface = total_rows - rows_inner
    rows_per_layer = min(total_rows, cap // block)
    layers = -(-total_rows // rows_per_layer)
    if layers > max_layers:
        need = layers * rows_per_layer * block
        raise errors.GraphTooLarge(
            f"{what} with {n_inner + n_surface:,} nodes needs {per_row * block} x {need} texels "
            f"({layers} layers of {per_row * block} x {rows_per_layer * block}), but this GPU allows textures of at "
            f"most {max_size} x {max_size} with {max_layers} layers; bake at a lower quality or use the CPU solver")
    return Layout(n_inner=int(n_inner), n_surface=int(n_surface), block=int(block), per_row=int(per_row),
                  rows_inner=int(rows_inner), rows_surface=int(rows_surface),
                  rows_per_layer=int(rows_per_layer), layers=int(layers))


@dataclass(frozen=True)
class VertexLayout:
    """Row-major placement of the user's vertices (output of radiance.glsl)."""

    count: int
    width: int
    height: int

    @property
    def shape(self) -> tuple:
        return (1, self.height, self.width)


def plan_vertex_layout(count: int, max_size: int = 16384, width: int = 1024) -> VertexLayout:
    cap = min(int(max_size), ADDRESS_MAX)
    w = max(16, min(width, cap) // 16 * 16)
    h = -(-max(count, 1) // w)
    h = -(-h // 16) * 16
    if h > cap:
        raise errors.GraphTooLarge(
            f"{count:,} mesh vertices need a {w} x {h} output texture; this GPU allows {max_size} x {max_size}")
    return VertexLayout(count=int(count), width=int(w), height=int(h))


# ------------------------------------------------------------------ precision
def quantize(a: np.ndarray, precision: str) -> np.ndarray:
    """``a`` as float32, rounded to fp16 (round to nearest even) when ``precision == "fp16"``."""
    a = np.asarray(a, dtype=np.float64)
    if precision == "fp32":
        return a.astype(np.float32)
    if precision != "fp16":
        raise errors.TranslucencyError(f"unknown GPU precision {precision!r}; choose fp32 or fp16")
    if np.any(np.abs(a) > FP16_MAX):
        raise errors.TranslucencyError("value out of fp16 range (scale it first)")
    return a.astype(np.float16).astype(np.float32)


def pow2_scale(max_abs: float, target: float = FP16_TARGET) -> float:
    """Power of two s with ``max_abs * s`` in [target, 2 target) (1 for zero)."""
    if not np.isfinite(max_abs) or max_abs <= 0:
        return 1.0
    return float(2.0 ** np.floor(np.log2(target / max_abs)))


# ------------------------------------------------------------------ packing
def scatter(layout: Layout, values: np.ndarray, channels: int = 4, dtype=np.float32, fill=0) -> np.ndarray:
    """Node values (N, C<=channels) -> texel array (layers, height, width, channels)."""
    values = np.asarray(values)
    if values.ndim == 1:
        values = values[:, None]
    out = np.full((layout.texels, channels), fill, dtype=dtype)
    out[layout.flat_index(), : values.shape[1]] = values
    return out.reshape(layout.shape + (channels,))


def gather(layout: Layout, texels: np.ndarray) -> np.ndarray:
    """Inverse of :func:`scatter`: (layers, height, width, C) -> (N, C)."""
    t = np.asarray(texels).reshape(layout.texels, -1)
    return t[layout.flat_index()]


def link_pages(k: int) -> int:
    """Link pages of a graph with ``k`` link slots per node: 4 links per texel, ceil(k / 4) texels.

    A QuadGraph level has 4 slots (one page); a particle fluid's Voronoi-fluid cells 15-25.  Page g of
    a node at texel (x, y, layer) sits at (x, y, layer + g * layout.layers) of the ``nbr`` and ``off_*``
    textures (``common.glsl``'s ``LINKS``); node values (q, the iterates) have one page.
    """
    return max(1, -(-int(k) // 4))


def _paged(layout: Layout, per_node: np.ndarray, dtype=np.float32, fill=0) -> np.ndarray:
    """(N, 4 P) values per link slot -> (P * layers, height, width, 4) texels, page after page."""
    pages = per_node.shape[1] // 4
    return np.concatenate([scatter(layout, per_node[:, 4 * g:4 * g + 4], dtype=dtype, fill=fill)
                           for g in range(pages)], axis=0)


def _pad_links(a: np.ndarray, fill) -> np.ndarray:
    """(N, K, ...) -> (N, 4 P, ...), the new slots filled with ``fill``."""
    k = a.shape[1]
    extra = 4 * link_pages(k) - k
    if not extra:
        return a
    pad = np.full((a.shape[0], extra) + a.shape[2:], fill, dtype=a.dtype)
    return np.concatenate([a, pad], axis=1)


def neighbor_texels(layout: Layout, nbr: np.ndarray) -> np.ndarray:
    """(N, K) node indices (-1: none) -> (P * layers, height, width, 4) uint32 addresses (NONE padding),
    P = :func:`link_pages` (K)."""
    nbr = _pad_links(np.asarray(nbr, dtype=np.int64).reshape(layout.n_nodes, -1), -1)
    addr = layout.address()
    a = np.where(nbr >= 0, addr[np.maximum(nbr, 0)], NONE).astype(np.uint32)
    return _paged(layout, a, dtype=np.uint32, fill=NONE)


@dataclass
class PackedCoefficients:
    off: tuple  # (off_r, off_g, off_b) texel arrays, P pages (link_pages) along the layers
    ext: np.ndarray  # rgb = e, a = b_scale (scaled by `scale`)
    scale: float  # power of two the coefficients were multiplied by
    diag: np.ndarray  # (N, 3) float64 diagonal of the stored (quantized, scaled) matrix
    off_nodes: np.ndarray  # (N, 4 P, 3) float64 stored off-diagonals (scaled; padded slots 0)
    b_scale: np.ndarray  # (n_surface,) float64 stored b_scale (scaled)
    b_inner: float  # the stored a of the inner nodes: inner_unit, scaled (b = a q there: the volume source)
    inner_unit: float  # the largest b_scale (1 without surface nodes): the inner nodes' q is volume / inner_unit
    gershgorin: np.ndarray  # (3,) Gershgorin bound of D^-1 A of the stored matrix
    subnormal: int  # stored nonzero values in fp16's subnormal range (precision loss)
    precision: str


def pack_coefficients(layout: Layout, off: np.ndarray, diag: np.ndarray, b_scale: np.ndarray,
                      precision: str = "fp32") -> PackedCoefficients:
    """The matrix (kernel form of ``assembly.LevelSystem``) as textures.

    ``b_scale`` must be the same for the three channels (it is for both of
    ``assembly.assemble``'s schemes); it is stored once per node in ext.a, and ``inner_unit`` (the largest
    b_scale) at the inner nodes, whose q texels hold a volume source's right-hand side over it.
    """
    N = layout.n_nodes
    off = _pad_links(np.asarray(off, dtype=np.float64).reshape(N, -1, 3), 0.0)
    diag = np.asarray(diag, dtype=np.float64).reshape(N, 3)
    bs = np.asarray(b_scale, dtype=np.float64)
    if bs.ndim == 2:
        if bs.shape[0] and not np.allclose(bs, bs[:, :1], rtol=1e-12, atol=0.0):
            raise errors.TranslucencyError("the GPU packing needs a b_scale that is equal for the three channels")
        bs = bs[:, 0] if bs.shape[0] else np.zeros(0)
    if bs.shape != (layout.n_surface,):
        raise errors.TranslucencyError(f"b_scale has {bs.shape} values for {layout.n_surface} surface nodes")
    e = diag - off.sum(axis=1)
    inner_unit = float(np.abs(bs).max(initial=0.0)) or 1.0
    bfull = np.full(N, inner_unit)
    bfull[layout.n_inner:] = bs
    scale = 1.0
    if precision == "fp16":
        scale = pow2_scale(max(np.abs(off).max(initial=0.0), np.abs(e).max(initial=0.0), np.abs(bfull).max(initial=0.0)))
    off_q = quantize(off * scale, precision).astype(np.float64)
    e_q = quantize(e * scale, precision).astype(np.float64)
    b_q = quantize(bfull * scale, precision).astype(np.float64)
    subnormal = 0
    if precision == "fp16":
        vals = np.concatenate([off_q.ravel(), e_q.ravel(), b_q])
        subnormal = int(np.count_nonzero((vals != 0) & (np.abs(vals) < FP16_MIN_NORMAL)))
    # The diagonal the kernels form in fp32 from the stored numbers; a texel
    # with a non-positive diagonal is taken for padding, so none may occur.
    diag_q = e_q + off_q.sum(axis=1)
    if N and not np.all(diag_q > 0):
        raise errors.TranslucencyError(
            f"{int(np.count_nonzero(~(diag_q > 0)))} nodes have a non-positive diagonal in {precision} storage")
    with np.errstate(divide="ignore", invalid="ignore"):
        gersh = (1.0 + off_q.sum(axis=1) / np.where(diag_q > 0, diag_q, np.inf)).max(axis=0)
    off_tex = tuple(_paged(layout, off_q[:, :, c]) for c in range(3))
    ext_tex = scatter(layout, np.column_stack([e_q, b_q]))
    return PackedCoefficients(off=off_tex, ext=ext_tex, scale=scale, diag=diag_q, off_nodes=off_q,
                              b_scale=b_q[layout.n_inner:],
                              b_inner=float(quantize(np.array([inner_unit * scale]), precision)[0]),
                              inner_unit=inner_unit,
                              gershgorin=gersh, subnormal=subnormal,
                              precision=precision)


def pack_q(layout: Layout, q: np.ndarray, precision: str = "fp32", scale: float = 1.0, volume=None):
    """Incident light (n_surface, 3) and a volume source (n_inner, 3) or None -> (texels, stored q
    (n_surface, 3) float64, stored volume source (n_inner, 3) float64 or None)."""
    q = np.asarray(q, dtype=np.float64).reshape(layout.n_surface, 3)
    qq = quantize(q * scale, precision)
    full = np.zeros((layout.n_nodes, 3), dtype=np.float32)
    full[layout.n_inner:] = qq
    vq = None
    if volume is not None:
        vq = quantize(np.asarray(volume, dtype=np.float64).reshape(layout.n_inner, 3) * scale, precision)
        full[: layout.n_inner] = vq
    return scatter(layout, full), qq.astype(np.float64), None if vq is None else vq.astype(np.float64)


def pack_transfer(layout_fine: Layout, layout_coarse: Layout, idx: np.ndarray, w: np.ndarray,
                  precision: str = "fp32"):
    """Shepard transfer (bake.shepard[k]) -> (idx_a, idx_b uint32 texels, w_a, w_b float texels).

    ``idx`` (N_fine, b <= 8) global coarse node indices, -1 padded; ``w`` weights.
    """
    idx = np.asarray(idx, dtype=np.int64)
    w = np.asarray(w, dtype=np.float64)
    n, b = idx.shape
    if b > 8:
        raise errors.TranslucencyError(f"at most 8 Shepard neighbours fit the GPU packing, got {b}")
    idx8 = np.full((n, 8), -1, dtype=np.int64)
    idx8[:, :b] = idx
    w8 = np.zeros((n, 8))
    w8[:, :b] = np.where(idx >= 0, w, 0.0)
    addr = layout_coarse.address()
    a = np.where(idx8 >= 0, addr[np.maximum(idx8, 0)], NONE).astype(np.uint32)
    wq = quantize(w8, precision)
    return (scatter(layout_fine, a[:, :4], dtype=np.uint32, fill=NONE),
            scatter(layout_fine, a[:, 4:], dtype=np.uint32, fill=NONE),
            scatter(layout_fine, wq[:, :4]), scatter(layout_fine, wq[:, 4:]))


def vertex_scatter(vl: VertexLayout, values: np.ndarray, channels: int = 4, dtype=np.float32, fill=0):
    values = np.asarray(values)
    if values.ndim == 1:
        values = values[:, None]
    out = np.full((vl.height * vl.width, channels), fill, dtype=dtype)
    out[: vl.count, : values.shape[1]] = values
    return out.reshape(vl.shape + (channels,))


def pack_vertex_map(vl: VertexLayout, layout: Layout, idx: np.ndarray, w: np.ndarray):
    """bake.vertex_map (indices into the finest *surface* nodes) -> vertex-layout textures.

    Weights stay fp32 whatever the precision: they scale the output directly.
    """
    idx = np.asarray(idx, dtype=np.int64)
    w = np.asarray(w, dtype=np.float64)
    n, k = idx.shape
    if k > 8:
        raise errors.TranslucencyError(f"at most 8 nodes per vertex fit the GPU packing, got {k}")
    idx8 = np.full((n, 8), -1, dtype=np.int64)
    idx8[:, :k] = idx
    w8 = np.zeros((n, 8))
    w8[:, :k] = np.where(idx >= 0, w, 0.0)
    addr = layout.address(layout.n_inner + np.maximum(idx8, 0))
    a = np.where(idx8 >= 0, addr, NONE).astype(np.uint32)
    return (vertex_scatter(vl, a[:, :4], dtype=np.uint32, fill=NONE),
            vertex_scatter(vl, a[:, 4:], dtype=np.uint32, fill=NONE),
            vertex_scatter(vl, w8[:, :4].astype(np.float32)), vertex_scatter(vl, w8[:, 4:].astype(np.float32)))


def texture_bytes(layout: Layout, precision: str = "fp32", transfer: bool = False, pages: int = 1) -> int:
    """GPU memory of one level's textures (graph, coefficients, q, iterates, transfer); ``pages``: its
    :func:`link_pages`."""
    t = layout.texels
    f = 8 if precision == "fp16" else 16
    graph = 16 * t * pages  # nbr
    coef = (3 * pages + 1) * f * t  # off_r/g/b, ext
    q = f * t
    iterates = 5 * 16 * t  # x ping-pong, r, d ping-pong
    tr = (2 * 16 + 2 * f) * t if transfer else 0
    return int(graph + coef + q + iterates + tr)
