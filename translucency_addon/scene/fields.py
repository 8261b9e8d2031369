"""Built-in procedural heterogeneity fields, bpy-free.

In Blender the mixing field comes from a texture (``Texture.evaluate``), a
mesh attribute or a vertex group, sampled by ``ops`` at node positions.  The
command line, the tests and the benchmarks need fields without Blender, and
the path-traced reference needs the *same* field exported as a grid volume;
these are they.  All fields map object-space points (n, 3) to values in [0, 1].
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import MaterialError

KINDS = ("uniform", "checker", "layers", "marble", "sphere", "noise")


@dataclass(frozen=True)
class FieldSpec:
    kind: str = "uniform"
    scale: float = 1.0  # feature size in object units (cell, period, radius)
    axis: int = 2  # for layers and marble
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turbulence: float = 1.0  # marble only
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "FieldSpec":
        d = dict(d)
        if "offset" in d:
            d["offset"] = tuple(d["offset"])
        return cls(**d)


def _hash3(ix, iy, iz, seed):
    h = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ (seed * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFFFF).astype(np.float64) / float(0xFFFFFF)


def value_noise(p: np.ndarray, seed: int = 0) -> np.ndarray:
    """Trilinearly interpolated lattice noise in [0, 1] with a smoothstep fade."""
    p = np.asarray(p, dtype=np.float64)
    i0 = np.floor(p).astype(np.int64)
    t = p - i0
    t = t * t * (3.0 - 2.0 * t)
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = t[:, 0] if dx else 1.0 - t[:, 0]
        for dy in (0, 1):
            wy = t[:, 1] if dy else 1.0 - t[:, 1]
            for dz in (0, 1):
                wz = t[:, 2] if dz else 1.0 - t[:, 2]
                out += wx * wy * wz * _hash3(i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz, seed)
    return out


def turbulence(p: np.ndarray, octaves: int = 4, seed: int = 0) -> np.ndarray:
    """Sum of |2 noise - 1| over octaves, normalised to [0, 1]."""
    total = np.zeros(len(p))
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += amp * np.abs(2.0 * value_noise(p * (2.0**o), seed + o) - 1.0)
        norm += amp
        amp *= 0.5
    return total / norm


def evaluate_field(spec: FieldSpec, points) -> np.ndarray:
    """Field values in [0, 1] at object-space ``points`` (n, 3)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if spec.kind not in KINDS:
        raise MaterialError(f"unknown field kind {spec.kind!r}; choose one of {', '.join(KINDS)}")
    if not np.isfinite(spec.scale) or spec.scale <= 0:
        raise MaterialError(f"field scale must be positive, got {spec.scale}")
    q = (p - np.asarray(spec.offset)) / spec.scale
    if spec.kind == "uniform":
        return np.zeros(len(p))
    if spec.kind == "checker":
        return (np.floor(q).astype(np.int64).sum(axis=1) % 2).astype(np.float64)
    if spec.kind == "layers":
        return (np.floor(q[:, spec.axis]).astype(np.int64) % 2).astype(np.float64)
    if spec.kind == "sphere":
        return (np.linalg.norm(q, axis=1) <= 1.0).astype(np.float64)
    if spec.kind == "noise":
        return value_noise(q, spec.seed)
    # marble: veins where sin(x + turbulence) is near zero, like Blender's Marble (sharp)
    s = np.sin(np.pi * (q[:, spec.axis] + spec.turbulence * turbulence(q, 4, spec.seed)))
    return np.clip(1.0 - np.abs(s) ** 0.5, 0.0, 1.0)


def vertex_field_at_nodes(positions, values, nodes, k: int = 4) -> np.ndarray:
    """A field given at mesh vertices, carried to graph nodes: Shepard (inverse-square-distance)
    interpolation over the ``k`` nearest vertices, clipped to [0, 1]; a node on a vertex takes its value.

    The add-on's attribute and vertex-group fields (``ops.scene_inputs``) and the command line's
    ``--field-values`` both go through here, so the two sample the same field at the same nodes.
    """
    from scipy.spatial import cKDTree

    positions = np.asarray(positions, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    nodes = np.asarray(nodes, dtype=np.float64)
    if len(positions) == 0:
        return np.zeros(len(nodes))
    k = min(k, len(positions))
    dist, idx = cKDTree(positions).query(nodes, k=k)
    if k == 1:
        return np.clip(values[idx], 0.0, 1.0)
    w = 1.0 / np.maximum(dist * dist, 1e-24)
    exact = dist[:, 0] <= 1e-12
    w[exact] = 0.0
    w[exact, 0] = 1.0
    out = (w * values[idx]).sum(axis=1) / w.sum(axis=1)
    return np.clip(np.nan_to_num(out, nan=0.0), 0.0, 1.0)


def load_vertex_field(path: str, n_vertices: int) -> np.ndarray:
    """The per-vertex mixing weights in a ``.npy`` file (``numpy.save`` of an (n_vertices,) float array,
    0 to 1, in the baked mesh's vertex order: a mesh attribute or vertex group exported from Blender).

    Refused with one line naming the file: not a readable ``.npy`` (never unpickled), another shape,
    NaN or Inf, or weights outside [0, 1] (the count and the worst value are said)."""
    import tokenize

    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, SyntaxError, tokenize.TokenError) as exc:
        raise MaterialError(f"--field-values {path}: not a readable .npy array ({exc}); it should hold one "
                            f"weight from 0 to 1 per vertex of the baked mesh ({n_vertices:,})") from None
    numeric = np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)
    if values.shape != (n_vertices,) or not numeric:
        raise MaterialError(f"--field-values {path} holds a {values.dtype} array of shape {values.shape}; it "
                            f"should hold one weight from 0 to 1 per vertex of the baked mesh: shape ({n_vertices},)")
    values = values.astype(np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        raise MaterialError(f"--field-values {path}: {int(bad.sum()):,} of {n_vertices:,} weights are NaN or Inf")
    out = (values < 0.0) | (values > 1.0)
    if out.any():
        worst = values[out][np.argmax(np.abs(values[out] - 0.5))]
        raise MaterialError(f"--field-values {path}: {int(out.sum()):,} of {n_vertices:,} weights lie outside "
                            f"[0, 1] (worst {worst:g}); the field mixes two media, 0 the first and 1 the second")
    return values
