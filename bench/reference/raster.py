# SPDX-License-Identifier: GPL-3.0-or-later
"""A numpy z-buffer rasteriser for "our side": per-vertex values -> image.

Same camera and pixel conventions as the Mitsuba reference
(:class:`bench.reference.scene.Camera`): pixel ``(i, j)`` is sampled at its
centre, and it belongs to the object's mask when the pixel-centre primary ray
hits a triangle, exactly the mask :func:`bench.reference.mitsuba_ref.render_mask`
returns.  Values are interpolated with the barycentric coordinates of the hit
point on the 3D triangle (perspective-correct for perspective cameras).

Vectorised over triangles: each triangle's bounding-box pixels are enumerated
in bulk (``np.repeat``), tested with edge functions and resolved with a sort
on (pixel, depth); there is no per-pixel or per-triangle Python loop, only a
loop over chunks of ``chunk`` candidate pixels to bound memory.

No bpy, no Mitsuba.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import Camera


@dataclass
class Raster:
    image: np.ndarray  # (H, W, C) interpolated values, `background` outside the mask
    mask: np.ndarray  # (H, W) bool
    triangle: np.ndarray  # (H, W) int64 index of the visible triangle, -1 outside
    depth: np.ndarray  # (H, W) view depth of the visible point, inf outside


def rasterize(
    V,
    F,
    values,
    camera: Camera,
    resolution,
    *,
    background: float = 0.0,
    supersample: int = 1,
    chunk: int = 4_000_000,
) -> Raster:
    """Rasterise a triangle mesh carrying per-vertex ``values`` (n,) or (n, C).

    ``resolution`` is ``(W, H)``.  Triangles are not culled by orientation (the
    nearest surface wins, as for a ray).  With a perspective camera every
    triangle with a vertex behind the eye is dropped; keep the object in front.

    ``supersample = k > 1`` averages a k x k grid of samples per pixel over the
    samples that hit the object, like the reference's box pixel filter; the
    mask, triangle and depth stay those of the pixel centre.
    """
    k = int(supersample)
    if k > 1:
        W, H = (int(resolution[0]), int(resolution[1]))
        centre = rasterize(V, F, values, camera, (W, H), background=background, chunk=chunk)
        fine = rasterize(V, F, values, camera, (W * k, H * k), background=0.0, chunk=chunk)
        img = fine.image if fine.image.ndim == 3 else fine.image[..., None]
        cov = fine.mask.reshape(H, k, W, k).sum(axis=(1, 3))
        acc = (img * fine.mask[..., None]).reshape(H, k, W, k, -1).sum(axis=(1, 3))
        out = np.where(cov[..., None] > 0, acc / np.maximum(cov, 1)[..., None], float(background))
        out = np.where(centre.mask[..., None], out, float(background))
        centre.image = out if centre.image.ndim == 3 else out[..., 0]
        return centre
    W, H = (int(resolution[0]), int(resolution[1]))
    V = np.asarray(V, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(F, dtype=np.int64).reshape(-1, 3)
    vals = np.asarray(values, dtype=np.float64)
    squeeze = vals.ndim == 1
    vals = vals.reshape(len(V), -1)
    C = vals.shape[1]

    col, row, z = camera.project(V, (W, H))
    x = col[F]  # (m, 3) continuous pixel coordinates, centre of column j at j + 0.5
    y = row[F]
    zt = z[F]
    keep = np.all(np.isfinite(x) & np.isfinite(y), axis=1)
    if camera.kind == "perspective":
        keep &= np.all(zt > 0.0, axis=1)
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    keep &= area != 0.0
    # candidate pixel index ranges: centres j + 0.5 inside [min x, max x]
    j0 = np.maximum(np.ceil(x.min(axis=1) - 0.5), 0)
    j1 = np.minimum(np.floor(x.max(axis=1) - 0.5), W - 1)
    i0 = np.maximum(np.ceil(y.min(axis=1) - 0.5), 0)
    i1 = np.minimum(np.floor(y.max(axis=1) - 0.5), H - 1)
    nx = np.where(keep, np.maximum(j1 - j0 + 1, 0), 0).astype(np.int64)
    ny = np.where(keep, np.maximum(i1 - i0 + 1, 0), 0).astype(np.int64)
    count = nx * ny
    tris = np.nonzero(count)[0]
    j0 = j0.astype(np.int64)
    i0 = i0.astype(np.int64)

    zbuf = np.full(H * W, np.inf)
    tbuf = np.full(H * W, -1, dtype=np.int64)
    bbuf = np.zeros((H * W, 3))
    # chunks of whole triangles with about `chunk` candidates each
    csum = np.cumsum(count[tris])
    starts = np.searchsorted(csum, np.arange(0, csum[-1] if len(csum) else 0, chunk), side="right")
    bounds = list(starts) + [len(tris)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b <= a:
            continue
        t_ids = tris[a:b]
        n = count[t_ids]
        t = np.repeat(t_ids, n)
        first = np.cumsum(n) - n
        k = np.arange(len(t)) - np.repeat(first, n)
        j = j0[t] + k % nx[t]
        i = i0[t] + k // nx[t]
        px = j + 0.5
        py = i + 0.5
        X, Y = x[t], y[t]
        inv = 1.0 / area[t]
        l0 = ((X[:, 1] - px) * (Y[:, 2] - py) - (X[:, 2] - px) * (Y[:, 1] - py)) * inv
        l1 = ((X[:, 2] - px) * (Y[:, 0] - py) - (X[:, 0] - px) * (Y[:, 2] - py)) * inv
        l2 = 1.0 - l0 - l1
        eps = -1e-10
        inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
        if not inside.any():
            continue
        t, i, j = t[inside], i[inside], j[inside]
        lam = np.stack([l0[inside], l1[inside], l2[inside]], axis=1)
        Z = zt[t]
        if camera.kind == "perspective":
            w = lam / Z
            s = w.sum(axis=1)
            bary = w / s[:, None]
            depth = 1.0 / s
        else:
            bary = lam
            depth = (lam * Z).sum(axis=1)
        pix = i * W + j
        order = np.lexsort((depth, pix))
        pix, depth, t, bary = pix[order], depth[order], t[order], bary[order]
        firsts = np.ones(len(pix), dtype=bool)
        firsts[1:] = pix[1:] != pix[:-1]
        pix, depth, t, bary = pix[firsts], depth[firsts], t[firsts], bary[firsts]
        better = depth < zbuf[pix]
        pix = pix[better]
        zbuf[pix] = depth[better]
        tbuf[pix] = t[better]
        bbuf[pix] = bary[better]

    mask = tbuf >= 0
    image = np.full((H * W, C), float(background))
    hit = np.nonzero(mask)[0]
    if len(hit):
        corner = F[tbuf[hit]]  # (h, 3)
        image[hit] = np.einsum("hk,hkc->hc", bbuf[hit], vals[corner])
    image = image.reshape(H, W, C)
    if squeeze:
        image = image[..., 0]
    return Raster(image=image, mask=mask.reshape(H, W), triangle=tbuf.reshape(H, W), depth=zbuf.reshape(H, W))
