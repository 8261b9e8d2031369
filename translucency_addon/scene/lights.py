"""Light sources and the diffused incoming light q of Wang et al. eq. 3.

    q(x) = integral_{2 pi} L_i(x, w) (n . w) F_t(w) dw                  (eq. 3)

Lights are given in radiometric units, in the *object's* space (the space of
the QuadGraph), together with ``mm_per_unit`` which converts that space to
millimetres.  Converting Blender lights (power in W, sun strength in W/m^2)
into these units is the job of ``ops``; the factors are documented there and
measured against Cycles in the tests.

* point / spot: radiant intensity ``intensity`` [W/sr] (RGB); a spot also has
  a cone (``spot_size`` full angle, ``spot_blend`` as in Blender) and points
  along ``direction``;
* sun: ``irradiance`` [W/m^2] (RGB) on a plane facing the sun, light
  travelling along ``direction``;
* area: a one-sided Lambertian emitter approximated, far field, as a point
  with intensity ``intensity * max(0, cos)`` around ``direction``;
* environment: uniform radiance [W/(m^2 sr)] (RGB), optionally a real
  spherical-harmonic projection of the world (order 2, 9 x RGB coefficients).

For a distant point source q = E cos(theta) F_t(theta) exactly.  For a uniform
environment with no occlusion, q = L pi (1 - F_dr,ext) exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import LightError
from .fresnel import diffuse_reflectance_external, fresnel_transmittance

KINDS = ("point", "spot", "sun", "area")


def _vec3(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise LightError(f"{what} must be 3 finite numbers, got {v!r}")
    return a


FLOAT32_TINY = float(np.finfo(np.float32).tiny)


@dataclass(frozen=True)
class Light:
    kind: str
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 0.0  # W/sr for point/spot/area (per unit colour)
    irradiance: float = 0.0  # W/m^2 for sun (per unit colour)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[float, float, float] = (0.0, 0.0, -1.0)  # where the light travels
    spot_size: float = np.pi / 4  # full cone angle, radians
    spot_blend: float = 0.15
    name: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise LightError(f"unknown light kind {self.kind!r}; choose one of {', '.join(KINDS)}")
        c = _vec3(self.color, f"light {self.name!r} colour")
        if np.any(c < 0):
            raise LightError(f"light {self.name!r} has a negative colour {c.tolist()}")
        for label, val in (("intensity", self.intensity), ("irradiance", self.irradiance)):
            if not np.isfinite(val) or val < 0:
                raise LightError(f"light {self.name!r} {label} must be finite and >= 0, got {val}")
        _vec3(self.position, f"light {self.name!r} position")
        d = _vec3(self.direction, f"light {self.name!r} direction")
        if np.linalg.norm(d) == 0:
            raise LightError(f"light {self.name!r} has a zero direction")

    @property
    def rgb(self) -> np.ndarray:
        """Colour x intensity (or irradiance) per channel.

        Channels below float32's smallest normal number (1.2e-38, Blender
        stores light colours in float32) are flushed to zero: carried on, they
        would reach the solve as subnormal doubles, whose arithmetic loses
        precision (the fuzz test drew a colour of 2e-311 and got a 2 % power
        imbalance in that channel from rounding alone).
        """
        scale = self.irradiance if self.kind == "sun" else self.intensity
        rgb = np.asarray(self.color, dtype=np.float64) * scale
        return np.where(rgb < FLOAT32_TINY, 0.0, rgb)

    @property
    def unit_direction(self) -> np.ndarray:
        d = np.asarray(self.direction, dtype=np.float64)
        return d / np.linalg.norm(d)


@dataclass(frozen=True)
class Environment:
    radiance: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sh: np.ndarray | None = field(default=None, compare=False)  # (k, 3) real SH radiance, order <= 4

    def __post_init__(self):
        r = _vec3(self.radiance, "environment radiance")
        if np.any(r < 0):
            raise LightError(f"environment radiance is negative: {r.tolist()}")
        if self.sh is not None:
            sh = np.asarray(self.sh, dtype=np.float64)
            if sh.ndim != 2 or sh.shape[1] != 3 or sh.shape[0] not in (1, 4, 9, 16, 25) or not np.all(np.isfinite(sh)):
                raise LightError("environment SH must be a finite (k, 3) array, k in 1, 4, 9, 16, 25")

    @property
    def is_black(self) -> bool:
        return not np.any(np.asarray(self.radiance) > 0) and (self.sh is None or not np.any(self.sh))

    def radiance_at(self, dirs: np.ndarray) -> np.ndarray:
        """Radiance arriving from unit directions (n, 3) -> (n, 3): the uniform part plus the
        real-SH part (``sh`` conventions)."""
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        L = np.broadcast_to(np.asarray(self.radiance, dtype=np.float64), (len(dirs), 3)).copy()
        if self.sh is not None:
            from .sh import evaluate

            L += evaluate(np.asarray(self.sh, dtype=np.float64), dirs)
        return L


def spot_falloff(light: Light, cos_angle: np.ndarray) -> np.ndarray:
    """Blender's spot cone: 0 outside ``spot_size/2``, smoothstep over ``spot_blend``."""
    half = 0.5 * light.spot_size
    cos_half = np.cos(half)
    # Blender: spotmask = smoothstep(0, 1, (cos_angle - cos_half) / (blend * (1 - cos_half)))
    denom = max(light.spot_blend * (1.0 - cos_half), 1e-12)
    t = np.clip((cos_angle - cos_half) / denom, 0.0, 1.0)
    return np.where(cos_angle >= cos_half, t * t * (3.0 - 2.0 * t), 0.0)


def light_irradiance(light: Light, points: np.ndarray, mm_per_unit: float):
    """Irradiance on a plane facing the light, and the unit direction *to* the light.

    Returns ``(E (n, 3) W/m^2, to_light (n, 3), distance (n,) in object units)``;
    distance is ``inf`` for a sun.
    """
    p = np.asarray(points, dtype=np.float64)
    if light.kind == "sun":
        to_light = np.broadcast_to(-light.unit_direction, p.shape).copy()
        E = np.broadcast_to(light.rgb, p.shape).copy()
        return E, to_light, np.full(len(p), np.inf)
    delta = np.asarray(light.position) - p
    dist = np.linalg.norm(delta, axis=1)
    to_light = delta / np.maximum(dist, 1e-300)[:, None]
    r_m = np.maximum(dist * mm_per_unit * 1e-3, 1e-9)  # metres
    I = light.rgb[None, :] / (r_m * r_m)[:, None]
    cos_emit = (-to_light) @ light.unit_direction
    if light.kind == "spot":
        I = I * spot_falloff(light, cos_emit)[:, None]
    elif light.kind == "area":
        I = I * np.maximum(cos_emit, 0.0)[:, None]
    return I, to_light, dist


def incident_flux(
    lights,
    environment: Environment | None,
    points: np.ndarray,
    normals: np.ndarray,
    eta: float,
    mm_per_unit: float,
    visibility=None,
) -> np.ndarray:
    """Diffused incoming light q (eq. 3) at surface points, (n, 3), W/m^2.

    ``visibility(points, normals, to_light, distance) -> bool (n,)`` is called
    once per light to apply shadows (see :func:`shadow_visibility`); ``None``
    means no occlusion.  The environment term is unoccluded.
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    q = np.zeros((len(p), 3))
    for light in lights or ():
        E, to_light, dist = light_irradiance(light, p, mm_per_unit)
        cos_i = np.einsum("ij,ij->i", n, to_light)
        lit = cos_i > 0
        if visibility is not None and lit.any():
            vis = np.zeros(len(p), dtype=bool)
            idx = np.nonzero(lit)[0]
            vis[idx] = visibility(p[idx], n[idx], to_light[idx], dist[idx])
            lit &= vis
        w = np.where(lit, cos_i * fresnel_transmittance(cos_i, eta), 0.0)
        q += E * w[:, None]
    if environment is not None and not environment.is_black:
        q += environment_flux(environment, n, eta)
    return q


def environment_flux(env: Environment, normals: np.ndarray, eta: float) -> np.ndarray:
    """q from a uniform (plus optional SH) environment, unoccluded.

    Uniform part: ``L * pi * (1 - F_dr,ext)``.  SH part: the Funk-Hecke
    convolution of the radiance with the zonal kernel ``cos(theta) F_t(theta)``
    (``sh.transmitted_flux_from_sh``), which is exact for band-limited
    radiance -- the Fresnel factor is integrated, not averaged.
    """
    t_mean = 1.0 - diffuse_reflectance_external(eta)
    q = np.broadcast_to(np.asarray(env.radiance) * np.pi * t_mean, (len(normals), 3)).copy()
    if env.sh is not None:
        from .sh import transmitted_flux_from_sh

        q += transmitted_flux_from_sh(np.asarray(env.sh), normals, eta)
    return q


def shadow_visibility(bvh, offset: float):
    """A ``visibility`` callback for :func:`incident_flux` that casts shadow rays.

    Rays start ``offset`` (object units) along the normal, so a surface does
    not shadow itself, and stop at the light (suns: no limit).
    """

    def visible(points, normals, to_light, distance):
        origins = points + offset * normals
        tmax = np.where(np.isfinite(distance), distance - offset, np.inf)
        return ~bvh.occluded(origins, to_light, tmax)

    return visible
