"""The named hard cases of issue 9, one fixture each (the builders live in ``cases.py``).

A fixture returns a list: :class:`cases.Scenario` for a case that must solve
(one per variant), :class:`cases.Rejection` for one that must be refused.
Bakes are memoised in ``cases`` for the whole session.  Meshes come from
``primitives`` or the repository's ``data/meshes`` (through ``data.mesh_path``, like
``tests/bakes.py``).

This directory is a package (``__init__.py``) so that this file is imported
as ``hard_cases.conftest`` and never shadows ``tests/conftest.py``, which
other test modules import as ``conftest``.
"""

from __future__ import annotations

import pytest

from . import cases


@pytest.fixture(scope="session")
def thin_shell():
    """1: a sphere with a wall of 1 % of its radius."""
    return cases.build_thin_shell()


@pytest.fixture(scope="session")
def thin_fin():
    """2: fandisk (creases, thin fins)."""
    return cases.build_thin_fin()


@pytest.fixture(scope="session")
def high_genus():
    """3: rocker-arm (genus 1) and a 3 x 2 grid of fused tori (genus >= 6)."""
    return cases.build_high_genus()


@pytest.fixture(scope="session")
def slivers():
    """4: the raw bunny tetrahedralized with optimize=False."""
    return cases.build_slivers()


@pytest.fixture(scope="session")
def kappa_contrast():
    """5: a checkerboard whose cells' kappa differs 1e4-fold."""
    return cases.build_kappa_contrast()


@pytest.fixture(scope="session")
def albedo_near_1():
    """6: sigma_a = 1e-6 sigma_s'."""
    return cases.build_albedo_near_1()


@pytest.fixture(scope="session")
def albedo_near_0():
    """7: reduced albedo ~0.01 (diffusion invalid)."""
    return cases.build_albedo_near_0()


@pytest.fixture(scope="session")
def tiny_and_huge():
    """8: the same sphere at 0.1 mm and at 100 m."""
    return cases.build_tiny_and_huge()


@pytest.fixture(scope="session")
def fp16_scale():
    """9: GPU fp16 storage at both ends of the scale."""
    return cases.build_fp16_scale()


@pytest.fixture(scope="session")
def grazing_light():
    """10: lights grazing a face (cos = 1e-6 and exactly 0)."""
    return cases.build_grazing_light()


@pytest.fixture(scope="session")
def light_inside():
    """11: a point light inside the object (sphere, torus; with and without shadows)."""
    return cases.build_light_inside()


@pytest.fixture(scope="session")
def no_lights():
    """12: no lights at all (and a black world)."""
    return cases.build_no_lights()


@pytest.fixture(scope="session")
def occluded_light():
    """13: lights behind occluders."""
    return cases.build_occluded_light()


@pytest.fixture(scope="session")
def open_mesh():
    """14: the raw bunny, open, with holes."""
    return cases.build_open_mesh()


@pytest.fixture(scope="session")
def degenerate():
    """15: duplicate vertices and zero-area triangles."""
    return cases.build_degenerate()


@pytest.fixture(scope="session")
def disjoint():
    """16: two disjoint pieces in one object."""
    return cases.build_disjoint()


@pytest.fixture(scope="session")
def flat_mesh():
    """17: flat / zero-volume meshes (refused)."""
    return cases.build_flat_mesh()


@pytest.fixture(scope="session")
def nan_input():
    """18: NaN coordinates, NaN or negative coefficients (refused)."""
    return cases.build_nan_input()


@pytest.fixture(scope="session")
def bad_cache(tmp_path_factory):
    """19: corrupt, truncated, wrong-version caches (refused)."""
    return cases.build_bad_cache(str(tmp_path_factory.mktemp("bad-caches")))


@pytest.fixture(scope="session")
def texture_limit():
    """20: a graph larger than the GPU texture limit (refused; split in the tests)."""
    return cases.build_texture_limit()


@pytest.fixture
def case(request):
    """Indirect parametrisation by case name: the named fixture's value."""
    return request.getfixturevalue(request.param)
