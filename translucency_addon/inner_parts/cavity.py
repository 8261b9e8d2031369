r"""Cavities in the diffusion solve: light that leaves a cavity's wall enters the wall elsewhere.

**The graph.**  A cavity is carved into the QuadGraph bake: the mesh handed to
the bake is the outer surface plus each cavity's surface turned inside out
(``CompositeObject.diffusion_mesh``); fTetWild fills by winding number, so no
tetrahedron lies in the hollow, and the cavity's wall carries ordinary surface
nodes (outward normals pointing into the hollow).  The graph is the same
contract as any other (``graph.py``); nothing in the solver changes.

**The exchange.**  Without more, the wall's surface nodes lose their light to
the hollow as if it were the outside.  Inside a closed cavity that light
crosses the air (no extinction: tau = 0, the Voxel Number Map's cavity rule)
and lands on the wall again.  With J+ the in-medium outgoing partial current
of wall node t, the exitance into the air is ``(1 - F_dr) J+_t`` (F_dr the
internal diffuse reflectance of the boundary condition); the irradiance it
makes at wall node s is the radiosity form factor

    K_st = V_st cos th_s cos th_t A_t / (pi R_st^2)                          (diffuse exchange)

(V: visibility, by ray casts; each cavity's rows are normalised to sum to 1,
because a closed cavity's wall sees nothing but itself), and of the
irradiance E_s arriving at s the boundary transmits ``(1 - F_dr,ext) E_s``
into the medium -- the q of eq. 3 -- and reflects ``F_dr,ext E_s`` back into
the air, where it is exchanged again.  Summing the reflections,

    q_cav = (1 - F_dr,ext)(1 - F_dr) (I - F_dr,ext K)^-1 K J+                (1)

a dense operator on the wall nodes only (a few hundred per cavity).

**One solver.**  q_cav depends on the solution (through J+), so it is found by
solving the *same* ``DiffusionSolver`` again: ``J+`` is linear in (phi, q)
and phi in q, so (1) is a linear fixed point ``q_cav = M(q_ext + q_cav)`` in
the wall nodes' q alone.  :func:`solve_with_cavities` hands it to scipy's
GMRES; each operator application is one warm-started finest-level
``DiffusionSolver.solve(q=...)`` (the multi-level driver, assembly, Chebyshev
and output are untouched).  With marble walls about 6-8 solves settle it to
1e-4 where plain repetition needs ~20.  Power: what leaves the wall into the
hollow comes back (a closed, non-absorbing cavity); ``exchange_power`` reports
both and the tests hold them equal.

Neglected: the wall's exitance is taken as diffuse (the diffusion model's own
output assumption, ``radiance.outgoing_radiance``); the exchange is applied on
the finest level only (coarser levels only warm-start it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import CacheError, TranslucencyError
from ..scene.fresnel import diffuse_reflectance_external, diffuse_reflectance_internal
from ..diffusion.kernels import partial_current


@dataclass
class CavityExchange:
    """The finest level's cavity-wall surface nodes and their form factors."""

    nodes: np.ndarray  # (m,) indices into the finest level's surface nodes
    cavity: np.ndarray  # (m,) which cavity (0 .. n_cavities-1)
    K: np.ndarray  # (m, m) float32 form factors, rows normalised per cavity
    names: tuple = ()
    level_walls: list | None = None  # per level, the wall's surface-node indices (no outside light reaches them)
    operators: dict = field(default_factory=dict, compare=False, repr=False)  # :meth:`operator`, per eta (the last)

    @property
    def m(self) -> int:
        return int(len(self.nodes))

    def operator(self, eta: float) -> np.ndarray:
        """``(1 - F_dr,ext)(1 - F_dr) (I - F_dr,ext K)^-1 K``: J+ on the wall -> q on the wall (eq. 1)."""
        key = float(eta)
        cache = self.operators
        op = cache.get(key)
        if op is None:
            fe = diffuse_reflectance_external(eta)
            fi = diffuse_reflectance_internal(eta)
            K = self.K.astype(np.float64)
            op = (1.0 - fe) * (1.0 - fi) * np.linalg.solve(np.eye(self.m) - fe * K, K)
            cache.clear()
            cache[key] = op
        return op

    def to_arrays(self, prefix: str = "cavity/") -> dict:
        d = {f"{prefix}nodes": self.nodes.astype(np.int64), f"{prefix}cavity": self.cavity.astype(np.int64),
             f"{prefix}K": self.K.astype(np.float32),
             f"{prefix}names": np.frombuffer("\n".join(self.names).encode("utf-8"), dtype=np.uint8)}
        for i, w in enumerate(self.level_walls or ()):
            d[f"{prefix}walls{i}"] = np.asarray(w, dtype=np.int64)
        return d

    def dark_walls(self, q: list) -> list:
        """``q`` per level (eq. 3 from the scene's lights) with the cavity walls set to 0: no outside light
        reaches a closed hollow (the environment term of eq. 3 is unoccluded, the walls face the hollow)."""
        out = list(q)
        for i, w in enumerate(self.level_walls or ()):
            if out[i] is not None and len(w):
                out[i] = np.array(out[i])
                out[i][w] = 0.0
        return out

    @classmethod
    def from_arrays(cls, d, n_surface: int, prefix: str = "cavity/") -> "CavityExchange":
        try:
            nodes = np.asarray(d[f"{prefix}nodes"], dtype=np.int64)
            cav = np.asarray(d[f"{prefix}cavity"], dtype=np.int64)
            K = np.asarray(d[f"{prefix}K"], dtype=np.float32)
            names = tuple(bytes(np.asarray(d[f"{prefix}names"], dtype=np.uint8)).decode("utf-8").split("\n"))
        except (KeyError, UnicodeDecodeError) as exc:
            raise CacheError(f"cavity exchange data is incomplete or corrupt: {exc}") from None
        m = len(nodes)
        if cav.shape != (m,) or K.shape != (m, m) or (m and (nodes.min() < 0 or nodes.max() >= n_surface)) \
                or not np.all(np.isfinite(K)):
            raise CacheError("cavity exchange data does not match the graph")
        walls, i = [], 0
        while f"{prefix}walls{i}" in d:
            walls.append(np.asarray(d[f"{prefix}walls{i}"], dtype=np.int64))
            i += 1
        if walls and not np.array_equal(walls[-1], nodes):
            raise CacheError("cavity exchange data does not match the graph")
        return cls(nodes=nodes, cavity=cav, K=K, names=names, level_walls=walls or [nodes])


def is_convex(V, F, tol: float = 1e-6) -> bool:
    """Whether a closed, outward-oriented mesh bounds a convex body (every vertex behind every face plane)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    p = V[F]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    scale = float(np.linalg.norm(np.ptp(V, axis=0)))
    off = np.einsum("fj,fj->f", n, p[:, 0])
    for s in range(0, len(F), 2048):
        if np.any(V @ n[s:s + 2048].T - off[s:s + 2048] > tol * scale):
            return False
    return True


def build_cavity_exchange(bake, composite, progress=None) -> CavityExchange:
    """Find the finest level's wall nodes of each cavity and their form factors.

    ``bake``: a QuadGraph bake of ``composite.diffusion_mesh()`` (outer faces
    first, then each cavity's).  Visibility: inside a convex cavity every wall
    point sees every other one that faces it; a non-convex cavity casts one
    ray per pair (m^2 rays, seconds per thousand nodes).
    """
    from ..geometry.raycast import TriangleBVH

    lv = bake.finest
    V, F = np.asarray(bake.mesh_vertices), np.asarray(bake.mesh_faces)
    cavities = composite.cavities
    bvh = TriangleBVH(V, F)
    bounds = np.cumsum([len(composite.F)] + [len(p.F) for p in cavities])

    def walls(level):  # the cavity (-1: the outer surface) each surface node's closest face belongs to
        _, tri, _ = bvh.closest_point(level.surface_position)
        return np.searchsorted(bounds, tri, side="right") - 1

    level_walls = [np.flatnonzero(walls(level) >= 0) for level in bake.levels[:-1]]
    which = walls(lv)
    nodes = np.flatnonzero(which >= 0)
    cav = which[nodes]
    P = lv.surface_position[nodes]
    N = lv.normal[nodes]
    A = lv.area[nodes]
    m = len(nodes)
    K = np.zeros((m, m), dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    for c, part in enumerate(cavities):
        sel = np.flatnonzero(cav == c)
        if len(sel) < 2:
            raise TranslucencyError(f"cavity {part.name!r} has {len(sel)} surface nodes on the finest graph level: "
                                    "it is smaller than the graph's spacing; raise the bake quality or leave it out")
        s, t = np.meshgrid(sel, sel, indexing="ij")
        s, t = s.ravel(), t.ravel()
        off = s != t
        s, t = s[off], t[off]
        d = P[t] - P[s]
        R = np.linalg.norm(d, axis=1)
        # Two wall nodes at one point (a graph that snapped both onto the same spot) have no direction and no
        # form factor (1 / R^2): the pair is left out here, before the division, as it was after 0/0 before.
        apart = R > 0
        s, t, d, R = s[apart], t[apart], d[apart], R[apart]
        u = d / R[:, None]
        cs = np.einsum("ij,ij->i", N[s], u)  # the wall normal points into the hollow
        ct = -np.einsum("ij,ij->i", N[t], u)
        ok = (cs > 0) & (ct > 0)
        s, t, R, u, cs, ct = s[ok], t[ok], R[ok], u[ok], cs[ok], ct[ok]
        if not is_convex(part.V, part.F):
            eps = 1e-4 * diag
            vis = ~bvh.occluded(P[s] + eps * N[s], u, R - 2.0 * eps)
            s, t, R, cs, ct = s[vis], t[vis], R[vis], cs[vis], ct[vis]
        K[s, t] = cs * ct * A[t] / (np.pi * R ** 2)
        # Reciprocity: the power s sends to t, a_s K_st, must equal what t sends to s, or the hollow creates or
        # destroys light (3 % for a wall lit unevenly, found by the fuzz; row normalisation alone keeps only
        # sum_t K_st = 1).  The discrete form factors obey it only roughly, so the exchanged power G = A K is
        # symmetrised and balanced (symmetric Sinkhorn, G -> D G D) until every row sums to its node's area:
        # K = A^-1 D G D then has unit rows and A K symmetric, so sum_s a_s K_st = a_t (power out = back).
        G = A[sel, None] * K[np.ix_(sel, sel)]
        G = 0.5 * (G + G.T)
        a_sel = A[sel]
        d = np.ones(len(sel))
        for _ in range(500):
            r = d * (G @ d)
            d_new = np.sqrt(np.divide(d * a_sel, G @ d, out=d * d, where=r > 0))
            done = np.max(np.abs(d_new - d) / d) < 1e-13
            d = d_new
            if done:
                break
        K[np.ix_(sel, sel)] = d[:, None] * G * d[None, :] / a_sel[:, None]
        rows = K[sel].sum(axis=1)
        K[sel] /= np.where(rows > 0, rows, 1.0)[:, None]
        if progress is not None:
            progress((c + 1) / len(cavities))
    return CavityExchange(nodes=nodes, cavity=cav, K=K.astype(np.float32), names=tuple(p.name for p in cavities),
                          level_walls=level_walls + [nodes])


def wall_partial_current(solver, result, nodes) -> np.ndarray:
    """What leaves the wall nodes into the hollow, as the in-medium current J+ of eq. 1 (linear in the
    solution): the diffusion's unclamped J+ = (phi - 2 q) / (2 (1 + F_dr)), plus, in the first-scatter
    split's channels, the light that leaves after one scattering, ``s(alpha) q_incident`` (the split's
    s; an exitance, so divided by the 1 - F_dr that eq. 1 multiplies J+ by).  Without the second term
    the split's share of the wall's light would vanish in the hollow."""
    lv = solver.bake.finest
    phi_s = result.phi[-1][lv.n_inner + nodes]
    jp = partial_current(phi_s, result.q[-1][nodes], solver.fdr)
    if result.q_incident is not None and any(result.single):
        from ..diffusion.split import half_space_split

        beam = None if result.beams is None or result.beams[-1] is None else tuple(
            np.asarray(b)[nodes] for b in result.beams[-1])
        s = half_space_split(solver.eta).single_escapes(solver.surface_albedo[-1][nodes],
                                                        result.q_incident[-1][nodes], beam)
        jp = jp + np.where(np.array(result.single), s, 0.0) * result.q_incident[-1][nodes] / (1.0 - solver.fdr)
    return jp


def exchange_power(solver, result, exchange: CavityExchange) -> dict:
    """Power (W per channel) leaving the wall into the hollows and re-entering through it."""
    lv = solver.bake.finest
    a = lv.area[exchange.nodes] * (solver.bake.mm_per_unit * 1e-3) ** 2
    jp = wall_partial_current(solver, result, exchange.nodes)
    q_cav = exchange.operator(solver.eta) @ jp
    return {"out": (1.0 - solver.fdr) * (a @ jp), "back": a @ q_cav}


def hollow_lights(solver, lights) -> list:
    """The point, spot and area lights inside a cavity: inside the outer mesh (its faces come first in the
    bake's mesh, ``CompositeObject.diffusion_mesh``) but not inside the medium (``DiffusionSolver.lights_inside``,
    whose ray parity counts the cavity's wall too)."""
    from ..geometry.raycast import TriangleBVH, inside_mesh

    cand = [light for light in lights or () if light.kind != "sun"]
    n_outer = getattr(getattr(solver.bake, "composite", None), "n_outer_vertices", None)
    if not cand or n_outer is None:
        return []
    V, F = np.asarray(solver.bake.mesh_vertices), np.asarray(solver.bake.mesh_faces)
    outer = inside_mesh(TriangleBVH(V[:n_outer], F[np.all(F < n_outer, axis=1)]),
                        np.array([light.position for light in cand], dtype=np.float64))
    in_medium = {id(light) for light in solver.lights_inside(cand)}
    return [light for light, o in zip(cand, outer) if o and id(light) not in in_medium]


def solve_with_cavities(solver, exchange: CavityExchange | None, lights=(), environment=None, *, tol: float = 1e-4,
                        max_solves: int = 40, warm_start=None, **kw):
    """Solve with the cavity exchange: ``(SolveResult, info)`` (see the module docstring).

    The light pass and the first solve are the solver's own; the exchange is
    the solution's linear response to a q on the wall nodes alone, found by
    GMRES whose every step is one ``solver.solve(q=...)`` of that response
    (warm-started from the previous one; its tolerance is relative to the
    response itself, which a solve of the full q would swamp).  The result is
    the first solution plus the response, on the finest level.
    ``info``: ``{"solves", "seconds", "residual", "exchange_power"}``.
    ``warm_start``: a previous result of this function (the last frame): the
    exchange then starts from its wall q and follows it (:func:`_follow`).
    The light pass is the solver's own (``incident``), with the walls dark:
    outside light reaches a closed hollow only through the medium.
    Without an exchange (no cavity) this is one :meth:`DiffusionSolver.solve`.
    """
    import scipy.sparse.linalg as spla

    t0 = time.perf_counter()
    if exchange is None or exchange.m == 0:
        first = solver.solve(lights, environment, warm_start=warm_start, **kw)
        return first, {"solves": 1, "seconds": time.perf_counter() - t0, "residual": 0.0}
    light_kw = {k: kw.pop(k) for k in ("shadows", "occluders") if k in kw}
    usable = solver.can_warm_start(warm_start) or solver.options.levels == "finest"
    levels_needed = [len(solver.bake.levels) - 1] if usable else None
    beams = [None] * len(solver.bake.levels)  # the lamps' part, for the incidence-aware split
    q = exchange.dark_walls(solver.incident(lights, environment, levels=levels_needed, beams=beams, **light_kw))
    inner = hollow_lights(solver, lights)
    if inner:
        # A light inside a hollow shines on its wall from the air, as an outside light on the outer surface:
        # eq. 3's q on the wall nodes (the shadow rays, against the bake's mesh, keep it in its own hollow).
        # dark_walls above removed it with the outside light, so such a light added nothing, without a word.
        said = list(solver.warnings)
        q_in = solver.incident(inner, None, levels=levels_needed, **light_kw)
        solver.warnings = said
        for i, w in enumerate(exchange.level_walls or ()):
            if q[i] is not None and q_in[i] is not None and len(w):
                q[i][w] += q_in[i][w]
    first = solver.solve(q=q, warm_start=warm_start, beams=beams, **kw)
    first.warnings = list(solver.warnings) + list(first.warnings)
    nodes = exchange.nodes
    op = exchange.operator(solver.eta)
    m = exchange.m
    levels = solver.bake.levels
    prev_q = getattr(warm_start, "cavity_q", None)  # a previous frame's wall q: follow it (_follow)
    state = {"last": None, "solves": 1}
    kw = {k: v for k, v in kw.items() if k not in ("q", "bounce")}

    def response(v):
        """The solve of q = v on the wall nodes (0 elsewhere, every level)."""
        q = [np.zeros((lv.n_surface, 3)) for lv in levels]
        q[-1][nodes] = v
        res = solver.solve(q=q, warm_start=state["last"], **kw)
        state["last"] = res
        state["solves"] += 1
        return res

    if prev_q is not None and np.shape(prev_q) == (m, 3):
        return _follow(solver, exchange, first, np.asarray(prev_q, dtype=np.float64), op, tol, max_solves, t0, kw)
    jp0 = wall_partial_current(solver, first, nodes)
    b = op @ jp0

    # Each channel scaled by its own largest source: the channels do not couple, and one GMRES over the
    # stacked vector with a single scale met its tolerance on the brightest channel only -- a channel lit
    # 1e7 times more weakly was left at 4.8x its input power (the inner-parts fuzz).
    scale = np.abs(b).max(axis=0)
    scale = np.where(scale > 1e-300, scale, 1.0)

    def matvec(x):
        x = x.reshape(m, 3) * scale
        # J+ of the response includes the -2 v / (2 (1 + F_dr)) of its own q (result.q holds it)
        return ((x - op @ wall_partial_current(solver, response(x), nodes)) / scale).ravel()

    A = spla.LinearOperator((3 * m, 3 * m), matvec=matvec, dtype=np.float64)
    x, code = spla.gmres(A, (b / scale).ravel(), rtol=tol, atol=0.0, restart=max_solves, maxiter=1)
    q_cav = x.reshape(m, 3) * scale
    final = first.plus_finest(response(q_cav))
    rel = float(np.abs(op @ wall_partial_current(solver, final, nodes) - q_cav).max()
                / max(float(np.abs(q_cav).max()), 1e-300))
    info = {"solves": state["solves"], "seconds": time.perf_counter() - t0, "residual": rel, "gmres_code": int(code),
            "exchange_power": {k: v.tolist() for k, v in exchange_power(solver, final, exchange).items()},
            "wall_nodes": m}
    final.seconds["cavity_exchange"] = info["seconds"]
    final.cavity_q = q_cav
    return final, info


def _follow(solver, exchange, first, q_cav, op, tol, max_solves, t0, kw):
    """Frame to frame: start from the previous frame's wall q and repeat ``q_cav = op J+(solve(q_ext + q_cav))``,
    each solve of the whole q warm-started from the last.  A small change of the lights needs a few cheap
    solves where GMRES would start over; the contraction per step is the wall's return ratio (< 1)."""
    nodes = exchange.nodes
    # the light that entered, before the first-scatter split (each solve below splits its own q again)
    q_ext = list(first.q if first.q_incident is None else first.q_incident)
    last, solves, change = first, 1, np.inf
    scale = max(float(np.abs(q_cav).max()), 1e-300)
    while solves < max_solves:
        q = list(q_ext)
        q[-1] = q_ext[-1].copy()
        q[-1][nodes] += q_cav
        last = solver.solve(q=q, warm_start=last, beams=first.beams, **kw)
        solves += 1
        new = op @ wall_partial_current(solver, last, nodes)
        change = float(np.abs(new - q_cav).max()) / max(float(np.abs(new).max()), scale * 1e-12)
        q_cav = new
        if change <= tol:
            break
    final = replace(last, seconds=dict(first.seconds), warnings=list(first.warnings))
    info = {"solves": solves, "seconds": time.perf_counter() - t0, "residual": change, "gmres_code": None,
            "exchange_power": {k: v.tolist() for k, v in exchange_power(solver, final, exchange).items()},
            "wall_nodes": exchange.m, "mode": "followed the previous frame"}
    final.seconds["cavity_exchange"] = info["seconds"]
    final.cavity_q = q_cav
    return final, info
