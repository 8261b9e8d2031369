"""Environment maps (equirectangular radiance) -> spherical harmonics and a sun light.

The world as Cycles sees it is a radiance function L(w) of direction.  The
engine receives it as real SH coefficients (:mod:`.sh`, order 2: the order
the diffusion's Funk-Hecke kernel and the deformed sky visibility use) plus,
for an HDRI with a sun, one directional light (``lights.Light("sun")``) that
carries the sun's energy with shadows instead of smearing it into nine
coefficients (an order-2 projection of a 0.5 degree sun rings over the whole
sphere and lights the side facing away from it).

Conventions (Cycles' ``direction_to_equirectangular``, Blender's image rows
bottom to top): pixel (row i, column j) of an H x W map is the direction with
elevation ``pi ((i + 0.5) / H - 0.5)`` and azimuth ``atan2(y, x) = pi (1 - 2 (j + 0.5) / W)``.

Quadrature: every pixel is one sample at its centre with its exact solid
angle ``(2 pi / W) (sin(el_top) - sin(el_bottom))``, so a constant map
integrates to 4 pi exactly; the basis is taken at the centre (midpoint rule),
an error of O(1/H^2) in the other coefficients (2e-3 of the DC term at
H = 64, 3e-5 at H = 512: ``tests/test_environment_map.py``).

Downsampling (:func:`downsample`) averages blocks weighted by solid angle, so
every block keeps its power; it works in row bands so a 16k x 8k map needs
only its own buffer plus one band (see ``bench/world.py`` for time and memory).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sh import sh_basis

#: the SH order the engine's environment uses (diffusion kernel, deformed sky visibility)
ENGINE_ORDER = 2


def equirect_directions(h: int, w: int) -> np.ndarray:
    """Unit directions (h, w, 3) of an h x w equirectangular map's pixel centres (Cycles' convention)."""
    el = np.pi * ((np.arange(h) + 0.5) / h - 0.5)
    az = np.pi * (1.0 - 2.0 * (np.arange(w) + 0.5) / w)
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    return np.stack(np.broadcast_arrays(ce * np.cos(az)[None, :], ce * np.sin(az)[None, :], se), axis=-1)


def equirect_solid_angles(h: int, w: int) -> np.ndarray:
    """Exact solid angle of each row's pixels, (h,): ``(2 pi / w) (sin(el_top) - sin(el_bottom))``."""
    edges = np.sin(np.pi * (np.arange(h + 1) / h - 0.5))
    return (2.0 * np.pi / w) * np.diff(edges)


def direction_to_uv(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cycles' equirectangular (u, v) in [0, 1) of unit directions (n, 3)."""
    d = np.asarray(dirs, dtype=np.float64)
    u = 0.5 - np.arctan2(d[:, 1], d[:, 0]) / (2.0 * np.pi)
    v = np.arcsin(np.clip(d[:, 2], -1.0, 1.0)) / np.pi + 0.5
    return u % 1.0, v


def sample_equirect(pixels: np.ndarray, dirs: np.ndarray, interpolation: str = "Linear") -> np.ndarray:
    """Radiance (n, 3) of an (h, w, 3) equirectangular map in directions (n, 3).

    ``Linear``: bilinear between pixel centres, periodic in azimuth, clamped at the
    poles (Cycles' image texture); ``Closest``: the pixel the direction falls in.
    Cubic and Smart are sampled as Linear (the difference is below a pixel).
    """
    h, w = pixels.shape[:2]
    u, v = direction_to_uv(dirs)
    if interpolation == "Closest":
        j = np.minimum((u * w).astype(np.int64), w - 1)
        i = np.clip((v * h).astype(np.int64), 0, h - 1)
        return pixels[i, j, :3].astype(np.float64)
    x = u * w - 0.5
    y = np.clip(v * h - 0.5, 0.0, h - 1.0)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 %= w
    x1 = (x0 + 1) % w
    y1 = np.minimum(y0 + 1, h - 1)
    p = pixels
    top = p[y0, x0, :3] * (1 - fx) + p[y0, x1, :3] * fx
    bot = p[y1, x0, :3] * (1 - fx) + p[y1, x1, :3] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float64)


def downsample(pixels: np.ndarray, max_width: int = 2048, band_rows: int | None = None,
               band_bytes: int = 64 << 20) -> np.ndarray:
    """An (h, w, c>=3) map reduced by an integer factor f so its width is at most ``max_width``.

    Each f x f block becomes its solid-angle-weighted mean, so each block's power
    (radiance x solid angle) is kept exactly.  Works in bands of ``band_rows``
    output rows (default: as many as fit ``band_bytes`` of float64 input), so
    the extra memory stays bounded whatever the input size (about 150 MiB for a
    16k map, ``bench/world.py``).  Returns float32 (h/f, w/f, 3); the input is returned
    (first three channels) when it is already small enough.
    """
    h, w = pixels.shape[:2]
    f = 1
    while w // f > max_width:
        f *= 2
    if f == 1:
        return np.ascontiguousarray(pixels[..., :3], dtype=np.float32)
    H, W = h // f, w // f
    if band_rows is None:
        band_rows = max(1, band_bytes // (f * w * 3 * 8))
    omega = equirect_solid_angles(h, w)  # per input row (the same for every column)
    out = np.empty((H, W, 3), dtype=np.float32)
    for r0 in range(0, H, band_rows):
        r1 = min(H, r0 + band_rows)
        block = pixels[r0 * f:r1 * f, :W * f, :3].astype(np.float64)
        wt = omega[r0 * f:r1 * f]
        block *= wt[:, None, None]
        s = block.reshape(r1 - r0, f, W, f, 3).sum(axis=(1, 3))
        ws = wt.reshape(r1 - r0, f).sum(axis=1) * f
        out[r0:r1] = s / ws[:, None, None]
    return out


def project_samples(radiance: np.ndarray, dirs: np.ndarray, weights: np.ndarray, order: int = ENGINE_ORDER,
                    chunk: int = 1 << 18) -> np.ndarray:
    """SH coefficients ((order+1)^2, 3) of radiance samples (n, 3) at directions (n, 3) with solid angles (n,).

    ``sum_i L_i Y(w_i) dw_i``, in chunks so the basis matrix stays small.
    """
    L = np.asarray(radiance, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    wt = np.asarray(weights, dtype=np.float64).reshape(-1)
    k = (order + 1) ** 2
    out = np.zeros((k, 3))
    for a in range(0, len(L), chunk):
        b = a + chunk
        out += sh_basis(d[a:b], order).T @ (L[a:b] * wt[a:b, None])
    return out


def project_equirect(pixels: np.ndarray, order: int = ENGINE_ORDER) -> np.ndarray:
    """SH coefficients ((order+1)^2, 3) of an (h, w, >=3) equirectangular map (exact per-pixel solid angles)."""
    h, w = pixels.shape[:2]
    dirs = equirect_directions(h, w).reshape(-1, 3)
    wt = np.repeat(equirect_solid_angles(h, w), w)
    return project_samples(np.asarray(pixels[..., :3]).reshape(-1, 3), dirs, wt, order)


def rotate_sh(coeffs: np.ndarray, R: np.ndarray) -> np.ndarray:
    """SH of ``L'(w) = L(R w)``: radiance coefficients expressed in a frame rotated by ``R`` (3x3).

    Exact for band-limited coefficients: evaluated at ``R w_j`` on a Fibonacci set
    that determines the band, then solved back by least squares.
    """
    from .sh import evaluate, fibonacci_directions

    c = np.asarray(coeffs, dtype=np.float64)
    order = int(round(np.sqrt(c.shape[0]))) - 1
    d = fibonacci_directions(4 * c.shape[0] + 16)
    Y = sh_basis(d, order)
    vals = evaluate(c, d @ np.asarray(R, dtype=np.float64).T)
    return np.linalg.lstsq(Y, vals, rcond=None)[0]


# ------------------------------------------------------------------ the sun


@dataclass(frozen=True)
class ExtractedSun:
    """A sun taken out of an environment map (world space).

    ``direction``: unit vector *towards* the sun; ``irradiance``: RGB W/m^2 on a
    plane facing it (the power the region held above the sky around it);
    ``angle``: angular diameter in radians of a disk with the region's solid
    angle; ``solid_angle`` sr; ``pixels``: how many samples the region holds;
    ``peak``, ``threshold``, ``background``: the luminances that decided it.
    """

    direction: tuple
    irradiance: tuple
    angle: float
    solid_angle: float
    pixels: int
    peak: float
    threshold: float
    background: float
    fraction: float  # of the map's total power (radiance x solid angle) the sun held

    @property
    def angle_degrees(self) -> float:
        return float(np.degrees(self.angle))


#: a sun is a region of at most this solid angle (a disk 10 degrees across): larger bright regions
#: (a window, an overcast sky) are smooth enough for order-2 SH and stay there
SUN_MAX_SOLID_ANGLE = 2.0 * np.pi * (1.0 - np.cos(np.radians(5.0)))
#: ... whose peak is at least this many times the map's median luminance
SUN_MIN_CONTRAST = 50.0
#: ... and which holds at least this fraction of the map's power (else it changes nothing visible)
SUN_MIN_FRACTION = 0.05

_LUMA = np.array([0.2126, 0.7152, 0.0722])


def extract_sun(pixels: np.ndarray, *, max_solid_angle: float = SUN_MAX_SOLID_ANGLE,
                min_contrast: float = SUN_MIN_CONTRAST, min_fraction: float = SUN_MIN_FRACTION):
    """Find an HDRI's sun and remove it: ``(ExtractedSun or None, map without it, reason)``.

    The threshold is derived from the map itself: the geometric mean of the
    peak luminance and the median (the sky's typical value),
    ``T = sqrt(peak * median)``; the sun is the connected region (periodic in
    azimuth) around the brightest pixel above T.  It is kept as a sun only if
    it is small (``<= max_solid_angle`` sr), much brighter than the sky
    (``peak >= min_contrast * median``) and carries a visible share of the
    power (``>= min_fraction``); ``reason`` says in numbers why not otherwise.
    Removing it replaces the region's pixels by the mean of the ring of pixels
    around it, and the sun's irradiance is the power removed,
    ``sum_i (L_i - L_ring) dw_i`` per channel, so the map's total power is
    conserved exactly between the SH and the light.
    """
    from scipy import ndimage

    p = np.asarray(pixels[..., :3], dtype=np.float64)
    h, w = p.shape[:2]
    omega = np.repeat(equirect_solid_angles(h, w)[:, None], w, axis=1)
    lum = p @ _LUMA
    total = float(np.sum(lum * omega))
    k = int(np.argmax(lum))
    peak = float(lum.flat[k])
    median = float(np.median(lum))
    if not np.isfinite(peak) or peak <= 0.0:
        return None, pixels, "the world is black"
    if peak < min_contrast * max(median, 1e-30):
        return None, pixels, (f"no sun: the brightest pixel is {peak / max(median, 1e-30):.3g}x the median "
                              f"luminance, below {min_contrast:g}x")
    T = float(np.sqrt(peak * max(median, 1e-30 * peak)))
    above = lum > T
    labels, _ = ndimage.label(np.concatenate([above, above], axis=1))  # azimuth wraps
    ki, kj = divmod(k, w)
    lab = labels[ki, kj]
    region2 = labels == lab
    region = region2[:, :w] | region2[:, w:]
    sa = float(np.sum(omega[region]))
    if sa > max_solid_angle:
        across = 2 * np.degrees(np.arccos(1 - max_solid_angle / (2 * np.pi)))
        return None, pixels, (f"no sun: the bright region around the peak covers {sa:.3g} sr, more than "
                              f"{max_solid_angle:.3g} sr (a disk {across:.0f} degrees across); it stays in the SH")
    ring = ndimage.binary_dilation(np.concatenate([region] * 3, axis=1), iterations=2)[:, w:2 * w] & ~region
    fill = (np.sum(p[ring] * omega[ring][:, None], axis=0) / max(np.sum(omega[ring]), 1e-300)
            if ring.any() else np.zeros(3))
    excess = (p[region] - fill) * omega[region][:, None]
    E = np.maximum(np.sum(excess, axis=0), 0.0)
    fraction = float(np.sum(np.maximum(excess @ _LUMA, 0.0)) / max(total, 1e-300))
    if fraction < min_fraction:
        return None, pixels, (f"no sun: the brightest region holds {100 * fraction:.1f} % of the world's power, "
                              f"below {100 * min_fraction:g} %; it stays in the SH")
    dirs = equirect_directions(h, w)[region]
    wl = np.maximum(excess @ _LUMA, 0.0)
    d = np.sum(dirs * wl[:, None], axis=0)
    d = d / max(np.linalg.norm(d), 1e-300)
    out = np.array(pixels[..., :3], dtype=np.float32, copy=True)
    out[region] = fill
    angle = 2.0 * float(np.arccos(max(-1.0, 1.0 - sa / (2.0 * np.pi))))
    sun = ExtractedSun(direction=tuple(float(x) for x in d), irradiance=tuple(float(x) for x in E), angle=angle,
                       solid_angle=sa, pixels=int(region.sum()), peak=peak, threshold=T, background=median,
                       fraction=fraction)
    return sun, out, ""
