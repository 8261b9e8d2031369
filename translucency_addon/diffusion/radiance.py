"""Output query: J+ at the surface nodes and the radiance that leaves (Wang et al. 2010 eq. 4, 7 corrected).

From the boundary condition (derived in :mod:`.diffusion`)::

    J+ = (phi - 2 q) / (2 (1 + F_dr))
    L_o(w_o) = F_t(w_o) J+ / (pi eta^2)

with the clamp of negative J+ kept from creating power (:func:`clamp_scale`).
The numpy twin of the GPU's J+ kernel is ``kernels.outgoing_partial_current``.
"""

from __future__ import annotations

import numpy as np

from ..scene.fresnel import fresnel_transmittance
from .kernels import partial_current


def clamp_scale(phi_s: np.ndarray, q: np.ndarray, area: np.ndarray, fdr: float) -> np.ndarray:
    """Per-channel factor (<= 1) that keeps the clamp of J+ from creating power.

    The exact discrete balance gives ``sum_s a_s (1 - F_dr) J+_s = in - absorbed``
    with the unclamped J+.  Clamping its negative values to 0 raises that sum,
    and where the diffusion model fails -- an object much thinner than a
    transport mean free path lit on one side, where the surface node's phi is
    below 2q -- the output then emitted more than came in (fuzz test: 8 % at
    a 4 um sphere with 1 mm mean free paths).  When the unclamped total is
    positive and smaller than the clamped one, the clamped J+ is scaled down
    to it, so the output emits exactly ``in - absorbed``; otherwise (nothing
    was clamped, or the model gives a net inflow: an absorber, where the
    clamped output is already below the light that came in) the factor is 1.
    """
    j = partial_current(phi_s, q, fdr)
    a = np.asarray(area, dtype=np.float64)
    unclamped = a @ j
    clamped = a @ np.maximum(j, 0.0)
    ok = (unclamped > 0) & (clamped > unclamped)
    return np.where(ok, unclamped / np.where(ok, clamped, 1.0), 1.0)


def outgoing_radiance(jplus: np.ndarray, cos_o, eta: float) -> np.ndarray:
    """L_o = F_t(w_o) J+ / (pi eta^2) (corrected eq. 4 / 7).

    Rule for phi - 2q < 0: J+ is clamped to 0 before this (kernels.outgoing_partial_current).
    A negative J+ would mean light flowing *into* the object through the
    exitant half-space, which the diffusion approximation cannot resolve; it
    occurs where a link is shorter than 2 kappa (the FV row gives
    ``phi_s - 2q >= 0`` whenever ``phi_k >= q (2 - d_sk/kappa)``), i.e. on
    graphs finer than a transport mean free path, and in strong absorbers.
    The clamp removes no light from lit regions; the power it would add is
    taken back by :func:`clamp_scale` (every backend's output: ``DiffusionSolver.output_clamp``).
    """
    ft = fresnel_transmittance(np.clip(cos_o, 0.0, 1.0), eta)
    ft = np.where(np.asarray(cos_o) > 0, ft, 0.0)
    return jplus * (ft / (np.pi * eta * eta))[:, None]
