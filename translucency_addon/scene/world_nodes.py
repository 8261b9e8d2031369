"""A World's shader nodes evaluated as Cycles sees them from an object (bpy-free).

``ops/world.py`` reads the World's node tree into this small description
(:class:`WorldGraph`: nodes by name, their properties, unlinked input values,
links, and the pixels of every image or baked Sky Texture); :func:`evaluate`
returns the radiance [W/(m^2 sr)] arriving from any set of world directions.
Keeping it bpy-free lets the tests check each node against its closed form.

Nodes and what they do (Cycles' SVM semantics, ``intern/cycles/kernel/svm``):

* ``OUTPUT_WORLD`` (the active one), ``REROUTE``;
* ``BACKGROUND`` / ``EMISSION``: Color x Strength;
* ``MIX_SHADER`` ``(1 - Fac) A + Fac B``, ``ADD_SHADER`` ``A + B``;
* ``LIGHT_PATH``: light reaching the object is never a camera ray, so
  ``Is Camera Ray`` is 0 (the camera-only branch, e.g. a plain backdrop, is not
  what lights the object); the other outputs depend on the bounce and are refused;
* ``TEX_ENVIRONMENT`` (equirectangular) and ``TEX_SKY`` (baked by Blender into an
  equirectangular map, see ``ops/world.py``): the map sampled in the direction
  its Vector input gives (default: the view direction);
* ``TEX_COORD``: Generated, Object and Normal are the direction itself for a world
  without an object set;
* ``MAPPING`` (POINT, TEXTURE, VECTOR, NORMAL; Euler XYZ rotation
  ``R = Rz Ry Rx``; for directions the Location does not matter after normalising
  only for VECTOR/NORMAL: POINT and TEXTURE keep it, as Cycles does);
* ``RGB``, ``VALUE``; ``MATH`` (ADD, SUBTRACT, MULTIPLY, DIVIDE, POWER, MINIMUM, MAXIMUM);
  ``MIX`` on colours (MIX, MULTIPLY, ADD) and the legacy ``MIX_RGB``.

Anything else (a Script/OSL node, a node group, an image that did not load,
another projection) raises :class:`WorldNodeError` naming the node, so the
caller can fall back and say why.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .environment_map import sample_equirect
from ..errors import TranslucencyError


class WorldNodeError(TranslucencyError):
    """The World's node tree holds something this evaluator cannot reproduce exactly."""


@dataclass
class WorldNode:
    name: str
    type: str
    props: dict = field(default_factory=dict)
    values: dict = field(default_factory=dict)  # input identifier -> default value (unlinked)
    links: dict = field(default_factory=dict)  # input identifier -> (node name, output name)


@dataclass
class WorldGraph:
    nodes: dict  # name -> WorldNode
    output: str  # the active World Output's name
    images: dict = field(default_factory=dict)  # node name -> (h, w, 3) float32 equirect radiance


def euler_matrix(rot) -> np.ndarray:
    """Blender's Euler XYZ rotation matrix ``Rz @ Ry @ Rx``."""
    x, y, z = (float(a) for a in rot)
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _normalise(v):
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.maximum(n, 1e-300)


class _Evaluator:
    def __init__(self, graph: WorldGraph, dirs: np.ndarray):
        self.g = graph
        self.dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        self.n = len(self.dirs)
        self.memo = {}
        self.active = []

    # -- inputs

    def input(self, node: WorldNode, ident: str, kind: str):
        """An input as an array broadcastable to (n, 3) ('color', 'vector', 'shader') or (n, 1) ('float')."""
        if ident in node.links:
            src, out = node.links[ident]
            v = self.output(src, out)
        elif ident in node.values:
            v = np.atleast_1d(np.asarray(node.values[ident], dtype=np.float64))[None, :]
        else:
            v = None
        if v is None:
            if kind == "vector":
                return self.dirs
            return np.zeros((1, 3 if kind in ("color", "shader") else 1))
        if kind == "float":
            return v if v.shape[1] == 1 else (v[:, :3] @ np.array([0.2126, 0.7152, 0.0722]))[:, None]
        if v.shape[1] == 1:
            return np.repeat(v, 3, axis=1)
        return v[:, :3]

    def output(self, name: str, out: str):
        key = (name, out)
        if key not in self.memo:
            node = self.g.nodes.get(name)
            if node is None:
                raise WorldNodeError(f"the World links from a node '{name}' that is not in its tree")
            if name in self.active:
                raise WorldNodeError(f"the World's nodes form a loop through '{name}'")
            self.active.append(name)
            try:
                self.memo[key] = np.asarray(self.node(node, out), dtype=np.float64)
            finally:
                self.active.pop()
        return self.memo[key]

    # -- nodes

    def node(self, nd: WorldNode, out: str):
        t = nd.type
        if t == "REROUTE":
            ident = next(iter(nd.links), None)
            return self.output(*nd.links[ident]) if ident else np.zeros((1, 3))
        if t in ("BACKGROUND", "EMISSION"):
            return self.input(nd, "Color", "color") * self.input(nd, "Strength", "float")
        if t == "MIX_SHADER":
            f = np.clip(self.input(nd, "Fac", "float"), 0.0, 1.0)
            a = self.input(nd, "Shader", "shader")
            b = self.input(nd, "Shader_001", "shader")
            return (1.0 - f) * a + f * b
        if t == "ADD_SHADER":
            return self.input(nd, "Shader", "shader") + self.input(nd, "Shader_001", "shader")
        if t == "LIGHT_PATH":
            if out == "Is Camera Ray":
                return np.zeros((1, 1))
            raise WorldNodeError(f"Light Path node '{nd.name}': its '{out}' output depends on the bounce, "
                                 "so no single world lights the object; only 'Is Camera Ray' (0 for light "
                                 "reaching the object) is evaluated")
        if t in ("TEX_ENVIRONMENT", "TEX_SKY"):
            img = self.g.images.get(nd.name)
            if img is None:
                raise WorldNodeError(f"{t.title().replace('_', ' ')} node '{nd.name}' has no pixels to sample")
            v = _normalise(self.input(nd, "Vector", "vector"))
            rgb = sample_equirect(img, v, nd.props.get("interpolation", "Linear"))
            return rgb if out != "Alpha" else np.ones((len(rgb), 1))
        if t == "TEX_COORD":
            if out in ("Generated", "Object", "Normal"):
                if nd.props.get("object"):
                    raise WorldNodeError(f"Texture Coordinate node '{nd.name}' uses the object "
                                         f"'{nd.props['object']}'; only world directions are evaluated")
                return self.dirs
            raise WorldNodeError(f"Texture Coordinate node '{nd.name}': the '{out}' output has no meaning "
                                 "for light reaching an object; use Generated")
        if t == "MAPPING":
            return self.mapping(nd)
        if t == "RGB":
            return np.asarray(nd.props["color"], dtype=np.float64)[None, :3]
        if t == "VALUE":
            return np.array([[float(nd.props["value"])]])
        if t == "MATH":
            return self.math(nd)
        if t in ("MIX", "MIX_RGB"):
            return self.mix(nd)
        if t == "SCRIPT":
            raise WorldNodeError(f"Script (OSL) node '{nd.name}': an OSL shader runs only inside Cycles' OSL "
                                 "back end and cannot be evaluated by the add-on")
        if t == "GROUP":
            raise WorldNodeError(f"node group '{nd.name}' in the World: ungroup it (Ctrl+Alt+G) so its nodes "
                                 "can be evaluated")
        raise WorldNodeError(f"node '{nd.name}' ({t}) in the World is not evaluated by the add-on")

    def mapping(self, nd: WorldNode):
        kind = nd.props.get("vector_type", "POINT")
        v = self.input(nd, "Vector", "vector")
        loc = np.asarray(nd.values.get("Location", (0, 0, 0)), dtype=np.float64)
        scale = np.asarray(nd.values.get("Scale", (1, 1, 1)), dtype=np.float64)
        for ident in ("Location", "Rotation", "Scale"):
            if ident in nd.links:
                raise WorldNodeError(f"Mapping node '{nd.name}': a linked {ident} input is not evaluated; "
                                     "set it as a value")
        R = euler_matrix(nd.values.get("Rotation", (0, 0, 0)))
        if kind == "POINT":
            return (v * scale) @ R.T + loc
        if kind == "TEXTURE":
            return ((v - loc) @ R) / np.where(scale == 0, 1e-30, scale)
        if kind == "VECTOR":
            return (v * scale) @ R.T
        if kind == "NORMAL":
            return _normalise((v / np.where(scale == 0, 1e-30, scale)) @ R.T)
        raise WorldNodeError(f"Mapping node '{nd.name}': type {kind} is not evaluated")

    def math(self, nd: WorldNode):
        op = nd.props.get("operation", "ADD")
        a = self.input(nd, "Value", "float")
        b = self.input(nd, "Value_001", "float")
        fns = {"ADD": np.add, "SUBTRACT": np.subtract, "MULTIPLY": np.multiply,
               "DIVIDE": lambda x, y: np.where(y != 0, x / np.where(y == 0, 1, y), 0.0),
               "POWER": lambda x, y: np.where(x >= 0, np.power(np.maximum(x, 0), y), 0.0),
               "MINIMUM": np.minimum, "MAXIMUM": np.maximum}
        if op not in fns:
            raise WorldNodeError(f"Math node '{nd.name}': operation {op} is not evaluated")
        r = fns[op](a, b)
        return np.clip(r, 0, 1) if nd.props.get("use_clamp") else r

    def mix(self, nd: WorldNode):
        blend = nd.props.get("blend_type", "MIX")
        if nd.type == "MIX":
            if nd.props.get("data_type", "RGBA") != "RGBA":
                raise WorldNodeError(f"Mix node '{nd.name}': only colour mixes are evaluated")
            f, a, b = (self.input(nd, "Factor_Float", "float"), self.input(nd, "A_Color", "color"),
                       self.input(nd, "B_Color", "color"))
        else:
            f, a, b = (self.input(nd, "Fac", "float"), self.input(nd, "Color1", "color"),
                       self.input(nd, "Color2", "color"))
        if nd.props.get("clamp_factor", True):
            f = np.clip(f, 0.0, 1.0)
        if blend == "MIX":
            r = (1 - f) * a + f * b
        elif blend == "MULTIPLY":
            r = a * ((1 - f) + f * b)
        elif blend == "ADD":
            r = a + f * b
        else:
            raise WorldNodeError(f"Mix node '{nd.name}': blend {blend} is not evaluated")
        return np.clip(r, 0, 1) if nd.props.get("clamp_result") else r


def evaluate(graph: WorldGraph, dirs: np.ndarray) -> np.ndarray:
    """Radiance (n, 3) the World sends along world directions ``dirs`` (n, 3), light reaching an object."""
    ev = _Evaluator(graph, dirs)
    out = graph.nodes.get(graph.output)
    if out is None:
        raise WorldNodeError("the World has no World Output node")
    if "Surface" not in out.links:
        return np.zeros((len(ev.dirs), 3))
    L = ev.output(*out.links["Surface"])
    L = np.broadcast_to(L, (ev.n, 3)) if L.shape[1] == 3 else np.repeat(L, 3, axis=1)
    if not np.all(np.isfinite(L)):
        raise WorldNodeError("the World evaluates to non-finite radiance (NaN or inf pixels in an image?)")
    return np.array(L)


def sample_grid(graph: WorldGraph, max_width: int = 2048, min_width: int = 256) -> tuple[int, int]:
    """The equirectangular grid (h, w) to evaluate the world on: the widest map's resolution (so a small sun
    is resolved), at least ``min_width`` wide (smooth worlds), at most ``max_width``."""
    w = max([img.shape[1] for img in graph.images.values()] + [min_width])
    w = min(w, max_width)
    w -= w % 2
    return w // 2, w


def content_hash(graph: WorldGraph) -> str:
    """A digest of the nodes, values and links (not the pixels: images are keyed by the caller)."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    h.update(graph.output.encode())
    for name in sorted(graph.nodes):
        nd = graph.nodes[name]
        h.update(repr((nd.name, nd.type, sorted(nd.props.items()), sorted(nd.values.items()),
                       sorted(nd.links.items()))).encode())
    return h.hexdigest()
