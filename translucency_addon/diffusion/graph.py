"""The graph contract: what every discretisation hands to the diffusion solver.

One solver serves every graph.  A QuadGraph level (Wang et al. 2010 sec. 4.1,
:class:`.quadgraph.GraphLevel`) implements this contract today; Voronoi-fluid
cells (Kang & Kim 2013 sec. 4.1), a deformed QuadGraph (Wang et al. sec. 6.4)
and cavity exchange will implement it too, and hand themselves to the same
assembly (:mod:`.assembly`), solvers (:mod:`.iterative`), multi-level driver
(:mod:`.diffusion`) and output (:mod:`.radiance`).

Per node ``i`` (inner nodes ``0 .. n_inner-1`` first, then surface nodes):

* ``position (N, 3)``: object units.
* ``neighbors (N, K) int``: up to K links per node, ``-1`` where a slot is
  empty (K = 4 for the QuadGraph, whose inner nodes are tets).  A surface
  node has exactly one link, in slot 0, to the inner node it closes.
* ``edge_length (N, K)``: the link length d_ij (the two-point flux distance),
  object units; ``face_area (N, K)``: the area A_ij of the face the link
  crosses, units^2.  Their ratio is the link's geometric factor: the FV
  coupling is ``T_ij = kappa_ij A_ij / d_ij`` (eq. 5 in conservative form).
  Both are symmetric: slot of j in i and slot of i in j carry the same values.
* ``volume (n_inner,)``: the cell volume V_i (absorption ``mu_i V_i``), units^3.

Per surface node ``s``: ``area (n_surface,)`` (the boundary area a_s it
carries, units^2) and ``normal (n_surface, 3)`` (outward): the inputs of the
diffusive-source boundary condition (eq. 2, 6) and of the light pass (eq. 3).

Between levels (where there are levels) the transfer is the Shepard
interpolation of eq. 10, ``(idx, w)`` arrays per pair of consecutive levels
(``Bake.shepard``); the solver needs nothing else of a level.

:func:`check_graph` verifies the contract (shapes, index ranges, symmetric
links, positive geometry) and names the first thing that breaks it.

:class:`SolverInput` is what the multi-level driver
(:class:`.diffusion.DiffusionSolver`) reads of the object it solves: a baked
QuadGraph (:class:`.bake.Bake`) or one frame of a particle fluid
(:class:`.fluid.FluidFrame`, a single level).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..errors import TranslucencyError


class DiffusionGraph(Protocol):
    """The arrays a graph kind provides (see the module docstring)."""

    n_inner: int
    n_surface: int
    position: np.ndarray
    neighbors: np.ndarray
    edge_length: np.ndarray
    face_area: np.ndarray
    volume: np.ndarray
    normal: np.ndarray
    area: np.ndarray

    @property
    def n_nodes(self) -> int: ...

    @property
    def surface_position(self) -> np.ndarray: ...


class SolverInput(Protocol):
    """What :class:`.diffusion.DiffusionSolver` reads of a bake (or of any other set of graphs).

    ``levels`` coarse to fine (graphs of the contract above), ``shepard`` the
    eq. 10 transfers between consecutive levels (empty for one level),
    ``mm_per_unit``, the surface the light pass and the output use --
    ``mesh_vertices``/``mesh_faces`` (shadow rays and the inside test of
    lights, unless the solver overrides ``shadow_bvh``/``lights_inside``),
    ``mesh_normals`` and ``vertex_map`` (``vertex_radiance``) -- ``sky``
    (sky visibility or None) and ``surface_bvh`` (a prebuilt
    :class:`.raycast.TriangleBVH` of the mesh, e.g. a deformed bake's refitted
    one, or None to build it on the first shadow ray).
    """

    levels: list
    shepard: list
    mm_per_unit: float
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    mesh_normals: np.ndarray
    vertex_map: tuple
    sky: object
    surface_bvh: object


def check_graph(graph: DiffusionGraph, name: str = "graph") -> None:
    """Raise :class:`TranslucencyError` naming the first way ``graph`` breaks the contract."""
    n, ni, ns = graph.n_nodes, graph.n_inner, graph.n_surface
    nbr = np.asarray(graph.neighbors)
    if nbr.ndim != 2 or nbr.shape[0] != n:
        raise TranslucencyError(f"{name}: neighbors must be (N, K) with N = {n} nodes, got {nbr.shape}")
    for attr in ("edge_length", "face_area"):
        shape = np.shape(getattr(graph, attr))
        if shape != nbr.shape:
            raise TranslucencyError(f"{name}: {attr} must have the shape of neighbors {nbr.shape}, got {shape}")
    for attr, want in (("position", (n, 3)), ("volume", (ni,)), ("area", (ns,)), ("normal", (ns, 3))):
        shape = np.shape(getattr(graph, attr))
        if shape != want:
            raise TranslucencyError(f"{name}: {attr} must be {want}, got {shape}")
    if nbr.size and (nbr.min() < -1 or nbr.max() >= n):
        raise TranslucencyError(f"{name}: a neighbour index lies outside 0..{n - 1} (and -1 for none)")
    if ns and np.any(nbr[ni:, 0] < 0) or ns and np.any(nbr[ni:, 0] >= max(ni, 1)):
        raise TranslucencyError(f"{name}: every surface node needs its inner node in link slot 0")
    has = nbr >= 0
    d, a = np.asarray(graph.edge_length), np.asarray(graph.face_area)
    ok = (d > 0) & (d < np.inf) & (a >= 0) & (a < np.inf)  # NaN fails every comparison
    if np.any(has & ~ok):  # without gathering the links (d[has]: a copy of every link, per frame for a fluid)
        raise TranslucencyError(f"{name}: every link needs a finite length > 0 and a face area >= 0")
    if np.any(np.asarray(graph.volume) <= 0) or np.any(np.asarray(graph.area) < 0):
        raise TranslucencyError(f"{name}: cell volumes must be > 0 and surface areas >= 0")


def graph_components(graph: DiffusionGraph) -> np.ndarray:
    """Connected-component label of every node (surface nodes with their inner node); scipy's csgraph."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = graph.n_nodes
    nbr = np.asarray(graph.neighbors)
    i = np.repeat(np.arange(n), nbr.shape[1])
    j = nbr.ravel().astype(np.int64)
    m = j >= 0
    g = coo_matrix((np.ones(int(m.sum())), (i[m], j[m])), shape=(n, n))
    return connected_components(g, directed=False)[1]
