# SPDX-License-Identifier: GPL-3.0-or-later
"""An analogue random walk of a homogeneous sphere under a uniform white world: the reference the
dark-sphere and albedo-sweep cases are judged against (issue 30).

Independent of the engine on purpose: its own Fresnel formula, its own sphere intersection, no table,
no diffusion.  The walk is the adjoint one: it starts where the camera looks, at a surface point seen
along the outward normal at outside cosine ``cos_view``, and follows the path into the medium.  The
world is uniform with radiance 1, so the radiance that leaves towards the camera is

    L_o = T(mu_o) * E[ prod(albedo at every collision) * prod(R at every internal reflection) * T_exit ]

(the eta^2 of radiance entering the denser medium cancels the 1/eta^2 of leaving it).  At each hit of the
boundary from inside the weight splits: ``T`` of it leaves (and sees the world), ``R = 1 - T`` is
reflected (all of it beyond the critical angle).  Free paths are exponential with unit sigma_t per mm;
after a reflection a new free path is drawn from the boundary (the exponential is memoryless, so this is
the same walk as finishing the old one).  Isotropic phase function.  Russian roulette below 1e-4 of the
starting weight keeps it unbiased.

The result is split by scattering order (0 = seen straight through) and by whether the path was
reflected inside before it left, so that the single-scattering pass -- straight chords, one collision,
no internal reflection -- can be compared with the walk's term of the same kind, and the rest named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def fresnel_unpolarised(cos_i, eta_i: float, eta_t: float) -> np.ndarray:
    """Fresnel reflectance of unpolarised light going from index ``eta_i`` into ``eta_t`` (1 beyond
    the critical angle): the mean of the s and p reflectances."""
    c = np.clip(np.abs(np.asarray(cos_i, dtype=np.float64)), 0.0, 1.0)
    s2 = (eta_i / eta_t) ** 2 * (1.0 - c * c)
    tir = s2 >= 1.0
    ct = np.sqrt(np.clip(1.0 - s2, 0.0, 1.0))
    rs = (eta_i * c - eta_t * ct) / np.maximum(eta_i * c + eta_t * ct, 1e-300)
    rp = (eta_t * c - eta_i * ct) / np.maximum(eta_t * c + eta_i * ct, 1e-300)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp))


def to_boundary(p: np.ndarray, d: np.ndarray, R: float) -> np.ndarray:
    """Distance from points ``p`` inside the sphere of radius ``R`` (centred at 0) along unit ``d`` to its
    surface: the larger root of ``|p + t d| = R``."""
    b = np.einsum("ij,ij->i", p, d)
    c = np.einsum("ij,ij->i", p, p) - R * R
    return -b + np.sqrt(np.maximum(b * b - c, 0.0))


@dataclass
class WalkResult:
    """Radiance towards the camera by order (rows: 0, 1, ..., the last row that order and above) and by
    internal reflection (column 0: none before leaving, column 1: at least one), with its standard error."""

    radiance: np.ndarray  # (orders, 2)
    stderr: float  # of the total
    n_paths: int
    single_light_side: float = 0.0  # one collision, reflected inside only after it (on the light's side)

    @property
    def total(self) -> float:
        return float(self.radiance.sum())

    @property
    def single_straight(self) -> float:
        """One collision, no internal reflection: the single-scattering pass's term."""
        return float(self.radiance[1, 0])

    @property
    def single_light_reflected(self) -> float:
        """One collision, no reflection before it (on the view's side) and at least one after it: the world's
        light reflected inside before it scattered (``single_scattering/entry.py`` eq. 3)."""
        return self.single_light_side - self.single_straight

    @property
    def single(self) -> float:
        return float(self.radiance[1].sum())

    @property
    def higher_orders(self) -> float:
        return float(self.radiance[2:].sum())


def sphere_walk(radius_mfp: float, albedo: float, eta: float, n: int = 200_000, seed: int = 1,
                cos_view: float = 1.0, orders: int = 4, max_events: int = 10_000) -> WalkResult:
    """L_o at a point of a sphere of radius ``radius_mfp`` mean free paths (sigma_t = 1) under a white
    world of radiance 1, seen at outside cosine ``cos_view``; see the module docstring."""
    R = float(radius_mfp)

    def boundary(p, d):
        t = to_boundary(p, d, R)
        pb = p + t[:, None] * d
        return t, pb / np.linalg.norm(pb, axis=1, keepdims=True)

    return _walk(np.array([0.0, 0.0, R]), boundary, albedo, eta, n, seed, cos_view, orders, max_events)


def box_walk(size_mfp, albedo: float, eta: float, n: int = 200_000, seed: int = 1, cos_view: float = 1.0,
             orders: int = 4, max_events: int = 10_000) -> WalkResult:
    """L_o at the centre of the top face (+z) of a box of sides ``size_mfp`` (3,) mean free paths, centred at 0,
    under a white world of radiance 1, seen at outside cosine ``cos_view``: the sphere's walk between six planes
    (a chord past the critical angle at one face meets the next nearly along its normal)."""
    half = 0.5 * np.asarray(size_mfp, dtype=np.float64).reshape(3)

    def boundary(p, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = np.where(d > 0, (half - p) / d, np.where(d < 0, (-half - p) / d, np.inf))
        axis = np.argmin(ts, axis=1)
        nb = np.zeros_like(p)
        nb[np.arange(len(p)), axis] = np.sign(d[np.arange(len(p)), axis])
        return np.maximum(ts[np.arange(len(p)), axis], 0.0), nb

    return _walk(np.array([0.0, 0.0, half[2]]), boundary, albedo, eta, n, seed, cos_view, orders, max_events)


def _walk(start, boundary, albedo, eta, n, seed, cos_view, orders, max_events) -> WalkResult:
    """The adjoint walk from ``start`` (a surface point whose outward normal is +z) in the medium that
    ``boundary(p, d) -> (distance, outward normal)`` bounds (sigma_t = 1)."""
    rng = np.random.default_rng(seed)
    mu_o = float(cos_view)
    sin_in = np.sqrt(max(0.0, 1.0 - mu_o * mu_o)) / eta
    cos_in = np.sqrt(1.0 - sin_in * sin_in)
    p = np.tile(np.asarray(start, dtype=np.float64), (n, 1))
    d = np.tile([sin_in, 0.0, -cos_in], (n, 1))
    w = np.full(n, 1.0 - float(fresnel_unpolarised(mu_o, 1.0, eta)))
    k = np.zeros(n, dtype=np.int64)
    refl = np.zeros(n, dtype=np.int64)
    before = np.zeros(n, dtype=bool)  # reflected inside before the first collision (the adjoint path's view side)
    light_side = np.zeros(n)
    alive = np.ones(n, dtype=bool)
    score = np.zeros((n, orders, 2))
    for _ in range(max_events):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        t_out, n_out = boundary(p[idx], d[idx])
        s = -np.log(rng.random(idx.size))
        coll = s < t_out
        ic, ib = idx[coll], idx[~coll]
        # collision: albedo, isotropic new direction
        p[ic] += s[coll, None] * d[ic]
        w[ic] *= albedo
        k[ic] += 1
        u = rng.uniform(-1.0, 1.0, ic.size)
        phi = rng.uniform(0.0, 2.0 * np.pi, ic.size)
        r = np.sqrt(1.0 - u * u)
        d[ic] = np.stack([r * np.cos(phi), r * np.sin(phi), u], axis=1)
        # boundary: T leaves and sees the world, R is reflected
        pb = p[ib] + t_out[~coll, None] * d[ib]
        nb = n_out[~coll]
        cos_b = np.einsum("ij,ij->i", d[ib], nb)
        Rf = fresnel_unpolarised(cos_b, eta, 1.0)
        np.add.at(score, (ib, np.minimum(k[ib], orders - 1), np.minimum(refl[ib], 1)), w[ib] * (1.0 - Rf))
        once = (k[ib] == 1) & ~before[ib]
        light_side[ib[once]] += w[ib[once]] * (1.0 - Rf[once])
        w[ib] *= Rf
        before[ib] |= k[ib] == 0
        refl[ib] += 1
        d[ib] -= 2.0 * cos_b[:, None] * nb
        p[ib] = pb - 1e-12 * nb
        small = np.flatnonzero(alive & (w < 1e-4))
        keep = rng.random(small.size) < 0.1
        w[small[keep]] *= 10.0
        w[small[~keep]] = 0.0
        alive[small[~keep]] = False
    per_path = score.sum(axis=(1, 2))
    return WalkResult(radiance=score.sum(axis=0) / n, stderr=float(per_path.std() / np.sqrt(n)), n_paths=n,
                      single_light_side=float(light_side.sum() / n))


def spot_mask(cos_angle, size: float, blend: float) -> np.ndarray:
    """Blender's spot cone (its manual and Cycles' spot attenuation without the cosine, which the
    engine's ``scene.lights.spot_falloff`` also leaves out): 0 outside half the Spot Size, a smoothstep
    over the Spot Blend's share of ``1 - cos(size / 2)`` inside the edge."""
    cos_half = np.cos(0.5 * size)
    t = np.clip((np.asarray(cos_angle) - cos_half) / max(blend * (1.0 - cos_half), 1e-12), 0.0, 1.0)
    return np.where(np.asarray(cos_angle) >= cos_half, t * t * (3.0 - 2.0 * t), 0.0)


def sphere_lamp_walk(radius_mm: float, sigma_t: float, albedo: float, theta, *, point_mm: float | None = None,
                     spot: tuple | None = None, disk_mm: float | None = None,
                     n: int = 100_000, seed: int = 1, max_events: int = 100_000) -> tuple:
    """Radiance leaving an index-matched sphere (eta = 1: no boundary at all) of radius ``radius_mm``
    (extinction ``sigma_t`` per mm, single-scattering albedo ``albedo``) lit by one lamp on the +z axis and
    nothing else, seen along the outward normal at the points at polar angle ``theta`` (radians, array)
    from the lit pole; returns ``(radiance, standard error)`` per angle, W/(m^2 sr).

    The lamp: a sun of irradiance 1 W/m^2 from +z (``point_mm`` None), or a point light of intensity
    1 W/sr at ``(0, 0, point_mm)`` (irradiance 1/d^2, d in metres); with ``spot`` = (size, blend) in
    radians that point light is a spot pointing down -z (:func:`spot_mask`); with ``disk_mm`` it is a
    Lambertian disk of that radius centred there, facing -z, of radiance 1/(pi r^2) (intensity 1 W/sr
    along its normal), sampled at one point per collision.

    The adjoint walk of :func:`sphere_walk` with next-event estimation: from the viewed point the path runs
    in along the normal; at every collision the weight takes the albedo and scores the lamp's light
    scattered there towards the path, ``w E(x) e^{-sigma_t d}/(4 pi)`` with d the distance to the boundary
    towards the lamp (isotropic phase function).  A path that reaches the boundary leaves into a black
    world.  Index-matched on purpose: a delta light cannot be reached through a refracting boundary by a
    path tracer (docs/reference.md), while here every order is exact to the walk's noise.
    """
    rng = np.random.default_rng(seed)
    R = float(radius_mm)
    st = float(sigma_t)
    theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
    out, err = np.zeros(len(theta)), np.zeros(len(theta))
    lamp = None if point_mm is None else np.array([0.0, 0.0, float(point_mm)])
    if lamp is not None and point_mm <= R:
        raise ValueError("the point light must lie outside the sphere")
    for j, th in enumerate(theta):
        nrm = np.array([np.sin(th), 0.0, np.cos(th)])
        p = np.tile(R * nrm * (1.0 - 1e-12), (n, 1))
        d = np.tile(-nrm, (n, 1))
        w = np.ones(n)
        alive = np.ones(n, dtype=bool)
        score = np.zeros(n)
        for _ in range(max_events):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            t_out = to_boundary(p[idx], d[idx], R)
            s = -np.log(rng.random(idx.size)) / st
            coll = s < t_out
            alive[idx[~coll]] = False  # left the sphere: a black world
            ic = idx[coll]
            p[ic] += s[coll, None] * d[ic]
            w[ic] *= albedo
            x = p[ic]
            if lamp is None:
                u_l, E = np.tile([0.0, 0.0, 1.0], (len(x), 1)), 1.0
            else:
                target = lamp
                if disk_mm is not None:  # a uniform point on the disk
                    rr = disk_mm * np.sqrt(rng.random(len(x)))
                    ph = rng.uniform(0.0, 2.0 * np.pi, len(x))
                    target = lamp + np.stack([rr * np.cos(ph), rr * np.sin(ph), np.zeros(len(x))], axis=1)
                v = target - x
                dist = np.linalg.norm(v, axis=1)
                u_l, E = v / dist[:, None], 1.0 / (dist * 1e-3) ** 2
                if spot is not None:
                    E = E * spot_mask(u_l[:, 2], *spot)  # the axis is -z: cos = (x - lamp).(-z)/|.| = u_l.z
                if disk_mm is not None:
                    E = E * u_l[:, 2]  # the emitter's cosine (its normal -z); radiance x area = 1 W/sr
            d_l = to_boundary(x, u_l, R)  # to the boundary towards the lamp
            score[ic] += w[ic] * E * np.exp(-st * d_l) / (4.0 * np.pi)
            u = rng.uniform(-1.0, 1.0, ic.size)
            phi = rng.uniform(0.0, 2.0 * np.pi, ic.size)
            r = np.sqrt(1.0 - u * u)
            d[ic] = np.stack([r * np.cos(phi), r * np.sin(phi), u], axis=1)
            small = np.flatnonzero(alive & (w < 1e-4))
            keep = rng.random(small.size) < 0.1
            w[small[keep]] *= 10.0
            w[small[~keep]] = 0.0
            alive[small[~keep]] = False
        out[j] = score.mean()
        err[j] = score.std() / np.sqrt(n)
    return out, err


if __name__ == "__main__":  # a quick look: python -m bench.sphere_walk
    for eta in (1.0, 1.3):
        res = sphere_walk(5.0, 0.2, eta, n=200_000)
        print(f"eta {eta}: total {res.total:.5f} +- {res.stderr:.5f}; single straight {res.single_straight:.5f}, "
              f"single reflected {res.radiance[1, 1]:.5f}, orders >= 2 {res.higher_orders:.5f}")
