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
* area: a one-sided Lambertian emitter of intensity ``intensity * max(0, cos)``
  around ``direction`` (W/sr along the normal, = L A); with its edges
  ``edge_x``, ``edge_y`` (object units; ``shape`` rectangle or ellipse) it is
  integrated over its surface (:func:`emitter_samples`), else a point;
* point / spot with ``radius`` > 0: a sphere; its irradiance is the point's (exact wherever the sphere is
  above the horizon), its shadow and its horizon soft (:func:`sphere_visibility`);
* environment: uniform radiance [W/(m^2 sr)] (RGB), optionally a real
  spherical-harmonic projection of the world (order 2, 9 x RGB coefficients).

For a distant point source q = E cos(theta) F_t(theta) exactly.  For a uniform
environment with no occlusion, q = L pi (1 - F_dr,ext) exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

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
EMITTER_SAMPLES = 16  # points over an area light's surface (Light.samples)


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
    shape: str = "rectangle"  # area: "rectangle" (Blender's Square, Rectangle) or "ellipse" (Disk, Ellipse)
    edge_x: tuple[float, float, float] = (0.0, 0.0, 0.0)  # area: its full edges in object units; 0 = a point
    edge_y: tuple[float, float, float] = (0.0, 0.0, 0.0)
    samples: int = EMITTER_SAMPLES  # points over the emitter's surface (emitter_samples)
    radius: float = 0.0  # point / spot: the sphere's radius (Blender's Radius), object units; 0 = a point

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
        if self.shape not in ("rectangle", "ellipse"):
            raise LightError(f"light {self.name!r} shape must be 'rectangle' or 'ellipse', got {self.shape!r}")
        if not (np.isfinite(self.radius) and self.radius >= 0):
            raise LightError(f"light {self.name!r} radius must be finite and >= 0, got {self.radius}")
        _vec3(self.edge_x, f"light {self.name!r} edge_x")
        _vec3(self.edge_y, f"light {self.name!r} edge_y")
        if not (isinstance(self.samples, (int, np.integer)) and 1 <= self.samples <= 4096):
            raise LightError(f"light {self.name!r} samples must be an integer from 1 to 4096, got {self.samples!r}")

    @property
    def is_extended(self) -> bool:
        """Whether :func:`emitter_samples` integrates it over its surface (an area light with edges)."""
        return (self.samples >= 2 and self.kind == "area" and bool(np.any(self.edge_x))
                and bool(np.any(self.edge_y)))

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


def emitter_samples(lights) -> list:
    """The lights with every extended emitter replaced by ``light.samples`` point emitters over its
    surface, each an ``area`` light (a Lambertian patch) carrying its share of the intensity; others as
    they are.  Every pass that lights the object (q of eq. 3, single scattering's light term, the Voxel
    Number Map's) sums over these, so the near field follows from the sum; q casts one shadow ray per
    quadrant of patches (:func:`shadow_groups`), the Voxel Number Map one per patch.

    * area light, edges ``edge_x``/``edge_y``: a rectangle by a k x m Gauss-Legendre rule (k m =
      samples, as square as the edges allow), an ellipse by Gauss rings (:func:`_ellipse_points`); each
      patch its weight's share of ``intensity`` along the light's normal.  16 patches are within 1 % of
      the integral wherever the receiver is farther than half the emitter's size (tests/test_area_lights.py),
      about 3 % at a third; nearer, raise ``Light.samples``.  The far-field point it replaced was
      25 % too bright 18 mm from a square of 16 mm side (docs/accuracy.md, local lights).
    * a point or spot light stays one point here: a uniform sphere's irradiance is exactly the point's
      wherever the sphere lies wholly above the surface's horizon, and patches over a sphere converge
      slowly near it (16 patches: 19 % low 1.5 radii from its centre); its radius softens q's horizon
      and shadow instead (:func:`sphere_visibility`).

    Deterministic (no random numbers): a frame depends on the frame only.
    """
    out = []
    for light in lights or ():
        if not light.is_extended:
            out.append(light)
            continue
        n = int(light.samples)
        p0 = np.asarray(light.position, dtype=np.float64)
        ex, ey = np.asarray(light.edge_x, dtype=np.float64), np.asarray(light.edge_y, dtype=np.float64)
        uv = _ellipse_points(n) if light.shape == "ellipse" else _rectangle_points(
            n, np.linalg.norm(ex) / max(np.linalg.norm(ey), 1e-300))
        for u, v, w in uv:
            out.append(replace(light, position=tuple(p0 + u * ex + v * ey), intensity=light.intensity * w,
                               edge_x=(0.0, 0.0, 0.0), edge_y=(0.0, 0.0, 0.0), samples=1))
    return out


def sphere_visibility(light, p, n, to_light, dist, eta: float, visibility=None) -> np.ndarray:
    """``cos F_t`` of eq. 3 for a sphere light of ``light.radius``, (n,): the mean over SHADOW_GROUPS
    points of the sphere's disc facing each receiver (at the disc's area-median radius, a quarter turn
    apart) of ``max(0, cos_k) F_t(cos_k)`` times the shadow ray's answer towards that point.

    Wherever the whole sphere is above the horizon and unshadowed this is the point light's
    ``cos F_t`` (the points' mean cosine, scaled by their distance over the centre's, is the centre's;
    only F_t's variation across the disc is second order), which is exact for a uniform sphere.  A
    sphere partly below the horizon still lights the receiver (the terminator moves past 90 degrees by
    atan(0.5 radius / distance) to atan(0.71 radius / distance), about half the sphere's angular
    radius, as the four points lie), and an occluder that hides part of the disc gives a penumbra in
    four steps.  Four shadow rays per light, as an area light's.  Single scattering and the Voxel
    Number Map light with the point.
    """
    k = np.arange(SHADOW_GROUPS) + 0.5
    phi = 2.0 * np.pi * k / SHADOW_GROUPS
    rho = light.radius * np.sqrt(0.5)
    # an orthonormal basis of the plane facing each receiver
    helper = np.where(np.abs(to_light[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(to_light, helper)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    v = np.cross(to_light, u)
    centre = np.asarray(light.position, dtype=np.float64)
    w = np.zeros(len(p))
    for f in phi:
        d = centre + rho * (np.cos(f) * u + np.sin(f) * v) - p
        r = np.linalg.norm(d, axis=1)
        dk = d / np.maximum(r, 1e-300)[:, None]
        cos_k = np.einsum("ij,ij->i", n, dk)
        lit = (cos_k > 0) & (r > 0)
        if visibility is not None and lit.any():
            idx = np.nonzero(lit)[0]
            lit[idx] = visibility(p[idx], n[idx], dk[idx], r[idx])
        w += np.where(lit, cos_k * fresnel_transmittance(np.clip(cos_k, 0.0, 1.0), eta), 0.0)
    # The points lie sqrt(D^2 + rho^2) away, off the axis by rho: the mean of their cosines is exactly
    # cos_0 D / sqrt(D^2 + rho^2), which this undoes, so an unshadowed receiver gets the point's law.
    w *= np.sqrt(dist * dist + rho * rho) / np.maximum(dist, 1e-300)
    inside = dist <= light.radius  # a receiver within the sphere: the point's law, unshadowed
    if inside.any():
        c = np.einsum("ij,ij->i", n[inside], to_light[inside])
        w[inside] = SHADOW_GROUPS * np.where(c > 0, c * fresnel_transmittance(np.clip(c, 0.0, 1.0), eta), 0.0)
    return w / SHADOW_GROUPS


SHADOW_GROUPS = 4  # shadow rays per extended emitter in q (incident_flux): one per quadrant of its patches


def shadow_groups(light) -> list:
    """``[(representative, patches)]``: an extended emitter's patches (:func:`emitter_samples`) in
    SHADOW_GROUPS quadrants of the emitter, each with a representative point light at its patches'
    intensity-weighted centre.  :func:`incident_flux` sums every patch's irradiance (the near field) but
    casts one shadow ray per group (the penumbra in four steps): 16 shadow passes per light cost 5x a
    frame's whole light pass at Preview."""
    patches = emitter_samples([light])
    if len(patches) <= SHADOW_GROUPS:
        return [(x, [x]) for x in patches]
    p0 = np.asarray(light.position, dtype=np.float64)
    ex, ey = np.asarray(light.edge_x, dtype=np.float64), np.asarray(light.edge_y, dtype=np.float64)
    rel = np.array([x.position for x in patches]) - p0
    quadrant = 2 * (rel @ ex > 0) + (rel @ ey > 0)
    out = []
    for g in np.unique(quadrant):
        members = [x for x, k in zip(patches, quadrant) if k == g]
        w = np.array([x.intensity for x in members])
        centre = (np.array([x.position for x in members]) * w[:, None]).sum(axis=0) / w.sum()
        out.append((replace(members[0], position=tuple(centre), intensity=float(w.sum())), members))
    return out


def _rectangle_points(n: int, aspect: float) -> list:
    """``(u, v, weight)`` over [-1/2, 1/2]^2: the tensor Gauss-Legendre rule of k x m nodes, k m <= n
    as close to n as the aspect ratio (x over y) allows (16 nodes, half a side from a square: 0.3 %
    where the midpoint rule of a 4 x 4 grid is 1.6 % off)."""
    best = None
    for k in range(1, n + 1):
        m = max(1, n // k)
        score = (k * m, -abs(np.log(max(aspect, 1e-9) * m / k)))
        if best is None or score > best[0]:
            best = (score, k, m)
    _, k, m = best
    (xu, wu), (xv, wv) = np.polynomial.legendre.leggauss(k), np.polynomial.legendre.leggauss(m)
    return [(0.5 * a, 0.5 * b, 0.25 * wa * wb) for a, wa in zip(xu, wu) for b, wb in zip(xv, wv)]


def _ellipse_points(n: int) -> list:
    """``(u, v, weight)`` over the ellipse inscribed in [-1/2, 1/2]^2: K rings (K ~ sqrt(n / pi)) at the
    Gauss-Legendre nodes of the area coordinate s = r^2 with its weights, points in each ring in
    proportion to its radius, alternate rings turned by half a step.  Seen from the axis the integrand
    is a function of s alone, which Gauss integrates well where a midpoint rule or a sunflower pattern
    does not (16 points, 0.64 diameters away, off the axis: 0.4 % against 7 % for the sunflower)."""
    K = max(1, int(round(np.sqrt(n / np.pi))))
    x, w = np.polynomial.legendre.leggauss(K)
    sk, wk = 0.5 * (x + 1.0), 0.5 * w  # nodes and weights in s = (r / R)^2 over [0, 1]
    rk = np.sqrt(sk)
    counts = np.maximum(1, np.round(n * rk / rk.sum()).astype(int))
    counts[-1] = max(1, counts[-1] + n - int(counts.sum()))
    out = []
    for k, (r, c) in enumerate(zip(rk, counts)):
        t = (np.arange(c) + 0.5 * (k % 2)) / c * 2.0 * np.pi
        out += [(0.5 * r * np.cos(a), 0.5 * r * np.sin(a), wk[k] / c) for a in t]
    return out


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


def weighted_direction(dir_q) -> np.ndarray:
    """The lamps' q-weighted mean unit direction from its weighted sum ``dir_q`` (n, 3); 0 where no lamp's
    light arrives."""
    norm = np.linalg.norm(dir_q, axis=1, keepdims=True)
    return np.where(norm > 0, dir_q / np.where(norm > 0, norm, 1.0), 0.0)


def weighted_cosine(mu_q, q_mean) -> np.ndarray:
    """The lamps' q-weighted mean incidence cosine from its weighted sum ``mu_q`` and the weight ``q_mean``
    (their q, mean over the channels); 1 where no lamp's light arrives."""
    lit = q_mean > 0
    return np.where(lit, mu_q / np.where(lit, q_mean, 1.0), 1.0)


@dataclass
class LampBeams:
    """The part of q that came from lamps, (n, 3), ``mu_q`` (n,): the sum over lamps of each one's q
    (mean over the channels) times its outside incidence cosine, and ``dir_q`` (n, 3): the same sum of
    their unit directions towards the lamp -- what the incidence-aware split (``diffusion.split`` eq. 6)
    and the lamps' volume source (``diffusion.beam_source``) need of a frame's lamps.  Filled by
    :func:`incident_flux`."""

    q: np.ndarray
    mu_q: np.ndarray
    dir_q: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> "LampBeams":
        return cls(np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3)))

    def add(self, dq: np.ndarray, cos_i: np.ndarray, to_light: np.ndarray) -> None:
        self.q += dq
        w = dq.mean(axis=1)
        self.mu_q += w * np.clip(cos_i, 0.0, 1.0)
        self.dir_q += w[:, None] * to_light

    @property
    def mu(self) -> np.ndarray:
        """The lamps' q-weighted mean outside incidence cosine per point (1 where no lamp lights it)."""
        return weighted_cosine(self.mu_q, self.q.mean(axis=1))

    @property
    def direction(self) -> np.ndarray:
        """The lamps' q-weighted mean unit direction towards them per point (0 where no lamp lights it)."""
        return weighted_direction(self.dir_q)

    def parts(self) -> tuple:
        """``(q_beam, mu, to_light)``: the form ``diffusion.split.HalfSpaceSplit`` (the first two) and
        ``diffusion.beam_source`` take."""
        return self.q, self.mu, self.direction


def incident_flux(
    lights,
    environment: Environment | None,
    points: np.ndarray,
    normals: np.ndarray,
    eta: float,
    mm_per_unit: float,
    visibility=None,
    beams: LampBeams | None = None,
) -> np.ndarray:
    """Diffused incoming light q (eq. 3) at surface points, (n, 3), W/m^2.

    ``visibility(points, normals, to_light, distance) -> bool (n,)`` is called
    once per light to apply shadows (see :func:`shadow_visibility`); ``None``
    means no occlusion.  The environment term is unoccluded.  ``beams``: a
    :class:`LampBeams` that also receives the lamps' part of q with their
    incidence cosines.
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    q = np.zeros((len(p), 3))

    def visible(to_light, dist):
        """Where the light towards ``to_light`` (a point, or a group's representative) is above the
        horizon and not shadowed, and its cosine there."""
        cos_i = np.einsum("ij,ij->i", n, to_light)
        lit = cos_i > 0
        if visibility is not None and lit.any():
            idx = np.nonzero(lit)[0]
            lit[idx] = visibility(p[idx], n[idx], to_light[idx], dist[idx])
        return lit, cos_i

    for light in lights or ():
        if light.kind in ("point", "spot") and light.radius > 0 and light.samples >= 2:
            E, to_light, dist = light_irradiance(light, p, mm_per_unit)
            dq = E * sphere_visibility(light, p, n, to_light, dist, eta, visibility)[:, None]
            q += dq
            if beams is not None:
                beams.add(dq, np.einsum("ij,ij->i", n, to_light), to_light)
            continue
        # An extended emitter: every patch's irradiance, shadowed by the ray of its group (shadow_groups)
        groups = shadow_groups(light) if light.is_extended else [(light, [light])]
        for rep, patches in groups:
            shadow_free = visible(*light_irradiance(rep, p, mm_per_unit)[1:])[0] if len(patches) > 1 else None
            for patch in patches:
                E, to_light, dist = light_irradiance(patch, p, mm_per_unit)
                if shadow_free is None:
                    lit, cos_i = visible(to_light, dist)
                else:
                    cos_i = np.einsum("ij,ij->i", n, to_light)
                    lit = (cos_i > 0) & shadow_free
                dq = E * np.where(lit, cos_i * fresnel_transmittance(cos_i, eta), 0.0)[:, None]
                q += dq
                if beams is not None:
                    beams.add(dq, cos_i, to_light)
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
