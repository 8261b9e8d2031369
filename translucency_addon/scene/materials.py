"""Optical materials: measured presets, heterogeneous mixes, per-node coefficients.

Units: every coefficient is per millimetre.  Geometry is in object units and
is converted with the bake's ``mm_per_unit`` where a length meets a
coefficient, never here.

Diffusion quantities (Ishimaru 1978; Jensen et al. 2001; Kang & Kim eq. 3
with g = 0):

* diffusion coefficient   ``kappa = 1 / (3 (sigma_a + sigma_s'))``   [mm]
* effective transport     ``sigma_tr = sqrt(3 sigma_a (sigma_a + sigma_s'))``  [1/mm]
* reduced albedo          ``alpha' = sigma_s' / (sigma_a + sigma_s')``

The extracted text of Wang et al. prints ``kappa = [3 mu + sigma_s']^-1``;
that is a transcription error: the standard diffusion coefficient is the one
above (Kang & Kim 2013 eq. 3 with g = 0; Jensen et al. 2001), so we use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import MaterialError
from .fresnel import check_eta

# Upper bound on any coefficient: 1e4 / mm is a mean free path of 0.1 um,
# far beyond any real translucent material; larger values are a units mistake.
MAX_COEFFICIENT_PER_MM = 1.0e4


@dataclass(frozen=True)
class Medium:
    """A homogeneous medium: RGB absorption and reduced scattering, per mm."""

    sigma_a: tuple[float, float, float]
    sigma_s: tuple[float, float, float]  # reduced scattering sigma_s' (g = 0)
    name: str = "custom"

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.sigma_a, dtype=np.float64), np.asarray(self.sigma_s, dtype=np.float64)


# Jensen, Marschner, Levoy, Hanrahan, "A Practical Model for Subsurface Light
# Transport", SIGGRAPH 2001, Fig. 5 table, as tabulated in pbrt-v3
# (src/core/medium.cpp, SubsurfaceParameterTable): sigma_s' and sigma_a in 1/mm,
# measured with eta = 1.3.
PRESETS: dict[str, Medium] = {
    m.name: m
    for m in (
        Medium((0.0030, 0.0034, 0.046), (2.29, 2.39, 1.97), "apple"),
        Medium((0.015, 0.077, 0.19), (0.15, 0.21, 0.38), "chicken1"),
        Medium((0.018, 0.088, 0.20), (0.19, 0.25, 0.32), "chicken2"),
        Medium((0.0002, 0.0028, 0.0163), (7.38, 5.47, 3.15), "cream"),
        Medium((0.061, 0.97, 1.45), (0.18, 0.07, 0.03), "ketchup"),
        Medium((0.0021, 0.0041, 0.0071), (2.19, 2.62, 3.00), "marble"),
        Medium((0.0024, 0.0090, 0.12), (0.68, 0.70, 0.55), "potato"),
        Medium((0.0014, 0.0025, 0.0142), (0.70, 1.22, 1.90), "skimmilk"),
        Medium((0.032, 0.17, 0.48), (0.74, 0.88, 1.01), "skin1"),
        Medium((0.013, 0.070, 0.145), (1.09, 1.59, 1.79), "skin2"),
        Medium((0.0011, 0.0024, 0.014), (2.55, 3.21, 3.77), "wholemilk"),
    )
}
PRESET_ETA = 1.3
# Friendly aliases used by the CLI and the panel.
ALIASES = {"skim_milk": "skimmilk", "skim-milk": "skimmilk", "whole_milk": "wholemilk", "whole-milk": "wholemilk", "chicken": "chicken1", "skin": "skin1"}


def preset(name: str) -> Medium:
    key = ALIASES.get(name.lower(), name.lower())
    if key not in PRESETS:
        raise MaterialError(f"unknown material preset {name!r}; choose one of {', '.join(sorted(PRESETS))}")
    return PRESETS[key]


def check_positive(value, what: str, error=MaterialError) -> float:
    """``value`` as a float, or ``error`` naming ``what`` and the value: a finite number > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise error(f"{what} must be a number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise error(f"{what} must be a finite number > 0 (positive), got {v:g}")
    return v


def check_mm_per_unit(value, error=MaterialError) -> float:
    """The scene scale as a float, or ``error`` naming the value: a finite number > 0 of millimetres per
    object unit (the length every coefficient per mm is converted with)."""
    return check_positive(value, "mm_per_unit (millimetres per object unit)", error)


def check_medium(m: Medium) -> Medium:
    """Raise :class:`MaterialError` naming the problem for NaN, negative or absurd values."""
    sa, ss = m.arrays()
    for label, arr in (("sigma_a", sa), ("sigma_s", ss)):
        if arr.shape != (3,):
            raise MaterialError(f"{m.name}: {label} must have 3 (RGB) values, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise MaterialError(f"{m.name}: {label} contains NaN or Inf: {arr.tolist()}")
        if np.any(arr < 0):
            raise MaterialError(f"{m.name}: {label} is negative: {arr.tolist()} (coefficients are >= 0, per mm)")
        if np.any(arr > MAX_COEFFICIENT_PER_MM):
            raise MaterialError(
                f"{m.name}: {label} = {arr.max():.3g}/mm is absurd (> {MAX_COEFFICIENT_PER_MM:g}/mm); "
                "coefficients are per millimetre"
            )
    if np.any(sa + ss <= 0):
        raise MaterialError(f"{m.name}: sigma_a + sigma_s is zero in some channel: the medium is empty there")
    return m


@dataclass(frozen=True)
class Material:
    """A translucent object's material: medium A, optionally mixed with B by a field.

    The mix at a point with field value ``f`` in [0, 1] is
    ``sigma = (1 - f) sigma_A + f sigma_B`` (linear in the coefficients, as
    for two interpenetrating media).  The field itself is supplied per node
    by the caller (``ops`` samples a Blender texture; the CLI and tests use
    :mod:`.fields`), so the engine never needs bpy.
    """

    medium_a: Medium
    medium_b: Medium | None = None
    eta: float = PRESET_ETA
    name: str = ""

    def __post_init__(self):
        check_medium(self.medium_a)
        if self.medium_b is not None:
            check_medium(self.medium_b)
        check_eta(self.eta)

    @property
    def heterogeneous(self) -> bool:
        return self.medium_b is not None

    def coefficients(self, field_values=None, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per-point ``(sigma_a, sigma_s')``, each (n, 3), per mm.

        ``field_values`` (n,) in [0, 1] is required for a heterogeneous
        material and ignored otherwise (then ``n`` gives the count).
        """
        sa_a, ss_a = self.medium_a.arrays()
        if self.medium_b is None:
            if n is None:
                n = 0 if field_values is None else len(field_values)
            return np.broadcast_to(sa_a, (n, 3)).copy(), np.broadcast_to(ss_a, (n, 3)).copy()
        if field_values is None:
            raise MaterialError("a heterogeneous material needs field values at the nodes")
        f = np.asarray(field_values, dtype=np.float64).reshape(-1, 1)
        if not np.all(np.isfinite(f)):
            raise MaterialError("the heterogeneity field contains NaN or Inf")
        f = np.clip(f, 0.0, 1.0)
        sa_b, ss_b = self.medium_b.arrays()
        return (1.0 - f) * sa_a + f * sa_b, (1.0 - f) * ss_a + f * ss_b

    def bulk(self) -> Medium:
        """The mean medium (field = 0.5 for a mix); used by the planner's estimates."""
        if self.medium_b is None:
            return self.medium_a
        sa, ss = self.coefficients(np.array([0.5]))
        return Medium(tuple(sa[0]), tuple(ss[0]), f"{self.medium_a.name}+{self.medium_b.name}")


def material_from_preset(name: str, eta: float = PRESET_ETA, mix_with: str | None = None) -> Material:
    return Material(preset(name), preset(mix_with) if mix_with else None, eta, name=name)


def diffusion_coefficient(sigma_a, sigma_s):
    """``kappa = 1 / (3 (sigma_a + sigma_s'))`` in mm (Wang et al. eq. 1, corrected)."""
    return 1.0 / (3.0 * (np.asarray(sigma_a) + np.asarray(sigma_s)))


def reduced_albedo(sigma_a, sigma_s):
    sa = np.asarray(sigma_a)
    ss = np.asarray(sigma_s)
    return ss / (sa + ss)
