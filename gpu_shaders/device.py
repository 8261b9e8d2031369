"""GPU-resident data of one QuadGraph level and the kernels that run on it.

:class:`GPULevel` owns a level's textures (``pack.py`` describes them) and
has one method per kernel; :class:`GPUVertexMap` owns the finest level's
vertex map and the radiance output.  The solver (``solver.py``) strings these
together; the parity tests call them one by one against the numpy twins in
``translucency_addon.diffusion.kernels``.

Uploads are counted in ``uploads`` (texture uploads per kind: ``graph``,
``coefficients``, ``q``, ``x``) so tests can check that a material edit
re-uploads the coefficients only.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from . import pack, runtime
from .runtime import dispatch, float_texture, groups_for, uint_texture

READBACK_WIDTH = 1024


class GPULevel:
    """Textures of one level: graph (once per bake), coefficients (per material), q (per frame), iterates."""

    def __init__(self, layout: pack.Layout, nbr: np.ndarray, precision: str = "fp32"):
        if precision not in pack.PRECISIONS:
            raise ValueError(f"precision must be one of {pack.PRECISIONS}, got {precision!r}")
        self.layout = layout
        self.precision = precision
        self.fmt = "RGBA16F" if precision == "fp16" else "RGBA32F"
        self.uploads = Counter()
        shape = layout.shape
        self.pages = pack.link_pages(np.asarray(nbr).reshape(layout.n_nodes, -1).shape[1])
        self.nbr = uint_texture(pack.neighbor_texels(layout, nbr))
        self.uploads["graph"] += 1
        self.x = [float_texture(None, shape), float_texture(None, shape)]  # ping-pong (Jacobi)
        self.r = float_texture(None, shape)
        self.d = [float_texture(None, shape), float_texture(None, shape)]  # ping-pong (Chebyshev)
        self.cur = 0  # which of self.x holds the current iterate
        self.q = float_texture(None, shape, self.fmt)
        self.q_stored = np.zeros((layout.n_surface, 3))
        self.volume_stored = None  # the lamps' volume source at the inner nodes as stored, or None
        self.q_scale = 1.0
        self.coef: pack.PackedCoefficients | None = None
        self.tex_coef: dict = {}
        self.transfer: dict | None = None
        self._chain = []
        w, h = layout.width, layout.height
        while True:
            w, h = -(-w // runtime.REDUCE_TILE), -(-h // runtime.REDUCE_TILE)
            self._chain.append(float_texture(None, (1, h, w)))
            if w == 1 and h == 1:
                break
        self._readback: dict = {}

    # ---------------------------------------------------------------- uploads
    def upload_coefficients(self, off, diag, b_scale) -> pack.PackedCoefficients:
        """The matrix of an ``assembly.LevelSystem`` (after a material edit)."""
        pc = pack.pack_coefficients(self.layout, off, diag, b_scale, self.precision)
        self.tex_coef = {
            "off_r": float_texture(pc.off[0], fmt=self.fmt),
            "off_g": float_texture(pc.off[1], fmt=self.fmt),
            "off_b": float_texture(pc.off[2], fmt=self.fmt),
            "ext": float_texture(pc.ext, fmt=self.fmt),
        }
        self.coef = pc
        self.uploads["coefficients"] += 1
        return pc

    def upload_q(self, q, scale: float = 1.0, volume=None) -> np.ndarray:
        """Incident light at the surface nodes (n_surface, 3) and the lamps' volume source at the inner nodes
        (n_inner, 3) or None, multiplied by ``scale``."""
        if volume is not None:  # the inner nodes' a is coef.inner_unit (pack.pack_coefficients)
            volume = np.asarray(volume, dtype=np.float64) / self.coef.inner_unit
        tex, stored, self.volume_stored = pack.pack_q(self.layout, q, self.precision, scale, volume)
        self.q = float_texture(tex, fmt=self.fmt)
        self.q_stored = stored
        self.q_scale = float(scale)
        self.uploads["q"] += 1
        return stored

    def stored_rhs(self) -> np.ndarray:
        """b = b_scale q (and the volume source at the inner nodes) of the stored (quantized, scaled) data,
        float64 (N, 3)."""
        b = np.zeros((self.layout.n_nodes, 3))
        b[self.layout.n_inner:] = self.coef.b_scale[:, None] * self.q_stored
        if self.volume_stored is not None:
            b[: self.layout.n_inner] = self.coef.b_inner * self.volume_stored
        return b

    def set_transfer(self, coarse: pack.Layout, idx, w) -> None:
        ia, ib, wa, wb = pack.pack_transfer(self.layout, coarse, idx, w, self.precision)
        self.transfer = {"idx_a": uint_texture(ia), "idx_b": uint_texture(ib),
                         "w_a": float_texture(wa, fmt=self.fmt), "w_b": float_texture(wb, fmt=self.fmt)}
        self.uploads["graph"] += 1

    def upload_nodes(self, values: np.ndarray):
        """A new RGBA32F node texture holding ``values`` (N, <=4)."""
        self.uploads["x"] += 1
        return float_texture(pack.scatter(self.layout, np.asarray(values, dtype=np.float32)))

    def set_x(self, values: np.ndarray) -> None:
        """Start the iteration from ``values`` (N, 3)."""
        self.x[0] = self.upload_nodes(values)
        self.cur = 0

    def clear_x(self) -> None:
        self.x[0].clear(format="FLOAT", value=(0.0, 0.0, 0.0, 0.0))
        self.cur = 0

    # ---------------------------------------------------------------- read-back
    def read_nodes(self, tex, n0: int = 0, count: int | None = None) -> np.ndarray:
        """Nodes n0 .. n0+count-1 of a node texture, in node order: (count, 3) float32.

        Gathers them on the GPU into a compact texture (unpack.glsl) and reads back only that.
        """
        L = self.layout
        if count is None:
            count = L.n_nodes - n0
        if count <= 0:
            return np.zeros((0, 3), dtype=np.float32)
        width = min(READBACK_WIDTH, -(-count // runtime.LOCAL) * runtime.LOCAL)
        height = -(-count // width)
        out = self._readback.get((width, height))
        if out is None:
            out = self._readback[(width, height)] = float_texture(None, (1, height, width))
        dispatch("unpack", groups_for(width, height), samplers={"src": tex}, images={"dst": out},
                 ints={"n0": n0, "count": count, "n_inner": L.n_inner, "per_row": L.per_row,
                       "rows_inner": L.rows_inner, "layer_h": L.height, "width": width})
        return runtime.read_texture(out).reshape(-1, 4)[:count, :3]

    def read(self, tex) -> np.ndarray:
        return self.read_nodes(tex, 0, self.layout.n_nodes)

    @property
    def x_current(self):
        return self.x[self.cur]

    def norm2(self, tex) -> np.ndarray:
        """Per-channel sum of squares over the whole texture (3,): multi-pass reduction, 1 texel read."""
        src = tex
        for i, dst in enumerate(self._chain):
            dispatch("reduce_sq" if i == 0 else "reduce_sum",
                     groups_for(dst.width, dst.height, 1, runtime.REDUCE_LOCAL),
                     samplers={"src": src}, images={"dst": dst})
            src = dst
        return runtime.read_texture(src).reshape(4)[:3].astype(np.float64)

    # ---------------------------------------------------------------- kernels
    def _groups(self):
        L = self.layout
        return groups_for(L.width, L.height, L.layers)

    def _coef(self) -> dict:
        d = {"nbr": self.nbr}
        d.update(self.tex_coef)
        return d

    def _pages(self) -> dict:
        return {"pages": self.pages, "page_layers": self.layout.layers}

    def jacobi(self, src, dst) -> None:
        """dst <- one Jacobi sweep from src."""
        s = self._coef()
        s.update(q=self.q, x_in=src)
        dispatch("jacobi", self._groups(), samplers=s, images={"x_out": dst}, ints=self._pages())

    def jacobi_step(self) -> None:
        """One sweep of the resident iterate (ping-pong)."""
        self.jacobi(self.x[self.cur], self.x[1 - self.cur])
        self.cur = 1 - self.cur

    def residual(self, x=None, out=None) -> None:
        """out (default self.r) <- b - A x (x default: the current iterate)."""
        s = self._coef()
        s.update(q=self.q, x_in=self.x[self.cur] if x is None else x)
        dispatch("residual", self._groups(), samplers=s, images={"r_out": self.r if out is None else out},
                 ints=self._pages())

    def cheb_init(self, theta) -> None:
        """d[0] <- r / (theta diag)."""
        s = dict(self.tex_coef)
        s["r_in"] = self.r
        dispatch("cheb_init", self._groups(), samplers=s, images={"d_out": self.d[0]},
                 floats={"inv_theta": tuple(float(v) for v in 1.0 / np.asarray(theta) * np.ones(3))},
                 ints=self._pages())

    def chebyshev(self, d_in, d_out, coef_d, coef_r) -> None:
        """One fused step on (x current, r) in place, d_in -> d_out."""
        s = self._coef()
        s["d_in"] = d_in
        dispatch("chebyshev", self._groups(), samplers=s,
                 images={"x_io": self.x[self.cur], "r_io": self.r, "d_out": d_out},
                 floats={"coef_d": tuple(float(v) for v in np.asarray(coef_d) * np.ones(3)),
                         "coef_r": tuple(float(v) for v in np.asarray(coef_r) * np.ones(3))},
                 ints=self._pages())

    def upsample_from(self, coarse: "GPULevel", src=None, dst=None) -> None:
        """dst (default: x[0], made current) <- eq. 10 from the coarse level's iterate."""
        s = dict(self.transfer)
        s["x_coarse"] = coarse.x[coarse.cur] if src is None else src
        if dst is None:
            dst = self.x[0]
            self.cur = 0
        dispatch("upsample", self._groups(), samplers=s, images={"x_fine": dst})

    def scale_x(self, factor) -> None:
        dispatch("scale", self._groups(), images={"x_io": self.x[self.cur]},
                 floats={"s": tuple(float(v) for v in np.asarray(factor) * np.ones(3))})

    def jplus(self, fdr: float, phi=None, out=None) -> None:
        """out (default self.r) <- J+ at surface texels (0 elsewhere)."""
        L = self.layout
        dispatch("jplus", self._groups(), samplers={"phi_in": self.x[self.cur] if phi is None else phi, "q": self.q},
                 images={"j_out": self.r if out is None else out},
                 floats={"fdr": float(fdr)}, ints={"surf_y0": L.surf_y0, "layer_h": L.height})

    def free(self) -> None:
        """Drop every texture (Blender frees a GPUTexture with its last reference)."""
        self.nbr = None
        self.x = [None, None]
        self.r = None
        self.d = [None, None]
        self.q = None
        self.tex_coef = {}
        self.transfer = None
        self._chain = []
        self._readback = {}


class GPUVertexMap:
    """The finest level's vertex map and the per-vertex radiance output."""

    def __init__(self, vl: pack.VertexLayout, layout: pack.Layout, idx, w):
        self.vl = vl
        ia, ib, wa, wb = pack.pack_vertex_map(vl, layout, idx, w)
        self.tex = {"idx_a": uint_texture(ia), "idx_b": uint_texture(ib),
                    "w_a": float_texture(wa), "w_b": float_texture(wb)}
        self.ones = float_texture(pack.vertex_scatter(vl, np.ones(vl.count, dtype=np.float32), channels=1),
                                  fmt="R32F")
        self.out = float_texture(None, vl.shape)

    def radiance(self, jplus_tex, eta: float, out_scale: float, cos_o=None) -> np.ndarray:
        """L_o per vertex (count, 3) float32; ``cos_o`` (count,) or None (along the normal)."""
        vl = self.vl
        cos_tex = self.ones if cos_o is None else float_texture(
            pack.vertex_scatter(vl, np.asarray(cos_o, dtype=np.float32), channels=1), fmt="R32F")
        s = dict(self.tex)
        s.update(jplus=jplus_tex, cos_o=cos_tex)
        dispatch("radiance", groups_for(vl.width, vl.height), samplers=s, images={"l_out": self.out},
                 floats={"eta": float(eta), "out_scale": float(out_scale)},
                 ints={"count": vl.count, "width": vl.width})
        return runtime.read_texture(self.out).reshape(-1, 4)[: vl.count, :3]

    def free(self) -> None:
        self.tex = {}
        self.ones = None
        self.out = None
