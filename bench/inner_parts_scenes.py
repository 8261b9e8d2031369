"""The scenes of Mochida et al. built procedurally (issue 15), shared by the speed and accuracy benches.

* ``cube_cavity``: a 20 mm cube (16 x 16 quads per face) with a spherical cavity of radius 6 mm
  (2,180 vertices; the paper's cube has 2,020), in a single-scattering-dominant medium or in marble;
* ``cube_stone``: the same cube with the sphere opaque (its shadow must show);
* ``bottle``: a sealed bottle 16 cm tall (glass 4 mm thick, a weakly scattering medium) holding wine
  (absorbing, weakly scattering) to 7 cm, air above it (9,926 vertices; the paper's has 10,604).

Coefficients are per mm.  The single-scattering-dominant medium has albedo 0.18-0.20 and an optical
thickness of 2.5-3.9 across the cube; glass and wine are invented (no measured preset exists): a
faintly green glass that scatters 0.02/mm, a red wine that absorbs green and blue.
"""

from __future__ import annotations

import numpy as np

from translucency_addon.geometry import primitives
from translucency_addon.scene.composite import CompositeObject, InnerPart
from translucency_addon.scene.materials import Material, Medium, preset

SS_MEDIUM = Medium((0.10, 0.12, 0.16), (0.025, 0.03, 0.035), "single-scattering")
GLASS = Medium((0.004, 0.001, 0.004), (0.02, 0.02, 0.02), "glass")
WINE = Medium((0.02, 0.35, 0.30), (0.05, 0.05, 0.05), "wine")
GLASS_ETA = 1.5


def cube_parts(role: str):
    (Vb, Fb), (Vs, Fs) = primitives.cube_with_sphere(20.0, 6.0, n=16, subdivisions=3)
    return (Vb, Fb), [InnerPart("sphere", Vs, Fs, role)]


def cube_cavity(medium: str = "single-scattering") -> tuple:
    """``(CompositeObject, mm_per_unit)``: the cube with its cavity, in the named medium."""
    (V, F), parts = cube_parts("cavity")
    mat = Material(SS_MEDIUM) if medium == "single-scattering" else Material(preset(medium))
    return CompositeObject(V, F, mat, parts), 1.0


def cube_stone() -> tuple:
    (V, F), parts = cube_parts("opaque")
    return CompositeObject(V, F, Material(SS_MEDIUM), parts), 1.0


def bottle() -> tuple:
    b = primitives.bottle_with_wine()
    parts = [InnerPart("inside", *b["inside"], "cavity"), InnerPart("wine", *b["wine"], "medium", WINE)]
    return CompositeObject(*b["outer"], Material(GLASS, eta=GLASS_ETA), parts), 10.0


SCENES = {
    "cube_cavity_ss": lambda: cube_cavity("single-scattering"),
    "cube_cavity_marble": lambda: cube_cavity("marble"),
    "cube_stone": cube_stone,
    "bottle": bottle,
}


def n_vertices(comp) -> int:
    return int(len(comp.V) + sum(len(p.V) for p in comp.parts))


def quality_for(name: str) -> str:
    """The Voxel Number Map quality each scene needs: the bottle's 4 mm wall needs voxels below 4 mm."""
    return "final" if name == "bottle" else "preview"


def sky_to_light():
    return np.array([0.6, 0.45, 0.66])
