"""Single scattering baked beside a QuadGraph :class:`~translucency_addon.quadgraph.bake.Bake`: keys and staleness.

``bake_single_scattering_for(bake, material, field, settings)`` bakes the RBF
optical-depth samples of the bake's mesh at its ``mm_per_unit`` and records
what they were baked from in ``data.stats``:

* ``stats["inputs"]``: ``graph_key`` (the QuadGraph's key), ``settings`` (the
  :class:`SingleScatteringSettings`), ``material`` (the coefficients of the
  media, per mm -- what sigma_t and sigma_s are made of; eta is not baked),
  ``field`` (a fingerprint of the heterogeneity field, None when homogeneous)
  and ``mm_per_unit``;
* ``stats["key"]``: a hash of those inputs.

:func:`attach` returns a copy of the bake holding the data, whose ``key``
combines the QuadGraph key and the single-scattering key (so a cache baked
with other single-scattering settings, material, field or scale has another
key and another file name) and whose ``stats["graph_key"]`` keeps the
QuadGraph key for the mesh-staleness check.

The optical depth tau = integral of sigma_t depends on the material, the
field and the scale, so a change of any of them makes the baked psi_i wrong:
:func:`staleness` lists what changed, and :func:`stale_message` turns that
into the sentence shown to the user ("... re-bake single scattering").  The
run time keeps using the stale data until then.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, replace

import numpy as np

from .bake import SingleScatteringSettings, bake_single_scattering
from .data import FORMAT_VERSION
from .volume import grid_for_mesh, resolution_for

SETTING_LABELS = {"quality": "quality", "n_dirs": "directions", "n_samples": "samples", "sh_order": "SH order"}


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=_plain).encode("utf-8")).hexdigest()


def _plain(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def graph_key(bake) -> str:
    """The QuadGraph key of a bake (its ``key`` unless single scattering was attached)."""
    return str((bake.stats or {}).get("graph_key") or bake.key)


def settings_dict(settings: SingleScatteringSettings | None) -> dict:
    s = (settings or SingleScatteringSettings()).validated()
    d = asdict(s)
    q = d["quality"]
    d["quality"] = q.lower() if isinstance(q, str) else int(q)
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in d.items()}


def _medium(m) -> dict:
    return {"sigma_a": [float(x) for x in m.sigma_a], "sigma_s": [float(x) for x in m.sigma_s]}


def material_fingerprint(material) -> dict:
    """What the optical depth is baked from: the media's coefficients (per mm), not eta."""
    out = {"a": _medium(material.medium_a)}
    if getattr(material, "heterogeneous", False) and material.medium_b is not None:
        out["b"] = _medium(material.medium_b)
    return out


def fingerprint_field(field, material=None):
    """A string for a :class:`~translucency_addon.scene.fields.FieldSpec`, a given string, or None.

    None for a homogeneous material (the field does not enter) and for None.
    Callables have no fingerprint of their own: pass ``field_fingerprint=`` to
    :func:`bake_single_scattering_for` (else a digest of the sampled values is used).
    """
    if material is not None and not getattr(material, "heterogeneous", False):
        return None
    if field is None:
        return None
    if isinstance(field, str):
        return field
    to_dict = getattr(field, "to_dict", None)
    if callable(to_dict):
        return "spec:" + _digest(to_dict())[:32]
    return None


def ss_key(inputs: dict) -> str:
    return _digest({"format": FORMAT_VERSION, **inputs})


def combined_key(graph: str, ss: str) -> str:
    """The key of a bake that holds single-scattering data."""
    return hashlib.sha256(f"{graph}+ss:{ss}".encode()).hexdigest()


def make_inputs(graph: str, settings, material, field_fp, mm_per_unit: float) -> dict:
    return {"graph_key": str(graph), "settings": settings_dict(settings), "material": material_fingerprint(material),
            "field": field_fp, "mm_per_unit": round(float(mm_per_unit), 9)}


def expected_key(bake, settings=None, material=None, field=None, *, field_fp=None, mm_per_unit=None,
                 extra_inputs=None) -> str:
    """The key :func:`attach` will give ``bake`` once single scattering is baked with these inputs
    (known before the bake: used to name the cache file).  ``extra_inputs``: as for
    :func:`bake_single_scattering_for`."""
    material = material if material is not None else _default_material()
    fp = field_fp if field_fp is not None else fingerprint_field(field, material)
    mm = bake.mm_per_unit if mm_per_unit is None else mm_per_unit
    g = graph_key(bake) if not isinstance(bake, str) else bake
    return combined_key(g, ss_key({**make_inputs(g, settings, material, fp, mm), **(extra_inputs or {})}))


def _default_material():
    from ..scene.materials import material_from_preset

    return material_from_preset("marble")


class GridField:
    """A field sampled beforehand at the voxel-grid centres (e.g. by Blender on its main thread).

    ``values`` has the grid's shape; calling it with voxel centres (what
    :func:`~.volume.voxelise` does) looks them up.  Bpy-free and thread-safe.
    """

    def __init__(self, origin, h: float, shape, values):
        self.origin = np.asarray(origin, dtype=np.float64)
        self.h = float(h)
        self.shape = tuple(int(s) for s in shape)
        self.values = np.asarray(values, dtype=np.float64).reshape(self.shape)

    @classmethod
    def grid_points(cls, V, quality) -> tuple:
        """``(origin, h, shape, centres (n, 3))`` of the voxel grid the bake will use for mesh ``V``."""
        origin, h, shape = grid_for_mesh(np.asarray(V, dtype=np.float64), resolution_for(quality))
        ijk = np.stack(np.unravel_index(np.arange(int(np.prod(shape))), shape), axis=1)
        return origin, h, shape, origin + (ijk + 0.5) * h

    def __call__(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = np.clip(np.rint((p - self.origin) / self.h - 0.5).astype(np.int64), 0, np.asarray(self.shape) - 1)
        return self.values[ijk[:, 0], ijk[:, 1], ijk[:, 2]]


def bake_single_scattering_for(bake, material=None, field=None, settings: SingleScatteringSettings | None = None,
                               progress=None, *, field_fingerprint: str | None = None, blockers=(), bvh=None,
                               volume=None, mesh=None, extra_inputs=None):
    """Bake single scattering for the mesh and scale of a QuadGraph ``bake``.

    ``material``: a :class:`~translucency_addon.scene.materials.Material` (default:
    the marble preset).  ``field``: None, a
    :class:`~translucency_addon.scene.fields.FieldSpec`, or ``field(points) ->
    values`` (give ``field_fingerprint=`` to make its staleness checkable;
    otherwise a digest of the values it returns is recorded).  ``progress``,
    ``blockers``, ``volume``: as :func:`~.bake.bake_single_scattering` (an object with inner
    parts passes the volume of ``voxelise_composite``, whose voxels know the parts).  ``mesh``:
    ``(V, F)`` to bake for instead of the bake's own (an object with inner parts: its outer
    mesh, without the cavity walls that follow it in ``bake.mesh_vertices``).
    ``extra_inputs``: more of what the optical depth was baked from (JSON values, e.g. the inner
    parts' media), recorded in ``stats["inputs"]`` and hashed into the key.  Returns the
    :class:`~.data.SingleScatteringData` with ``stats["inputs"]`` and
    ``stats["key"]`` filled in; :func:`attach` puts it into the bake.
    """
    from ..scene.fields import evaluate_field

    material = material if material is not None else _default_material()
    s = (settings or SingleScatteringSettings()).validated()
    fp = field_fingerprint if field_fingerprint is not None else fingerprint_field(field, material)
    fn = field
    if field is not None and callable(getattr(field, "to_dict", None)):
        spec = field
        fn = lambda p: evaluate_field(spec, p)  # noqa: E731
    recorded = {}
    if fn is not None and fp is None and material.heterogeneous:
        inner = fn

        def fn(p):  # noqa: F811 - record a digest of what the field returned
            v = np.asarray(inner(p), dtype=np.float64)
            recorded["digest"] = "values:" + hashlib.sha256(np.round(v, 9).tobytes()).hexdigest()[:32]
            return v

    V, F = mesh if mesh is not None else (bake.mesh_vertices, bake.mesh_faces)
    data = bake_single_scattering(np.asarray(V), np.asarray(F), material, fn, s, mm_per_unit=float(bake.mm_per_unit),
                                  blockers=blockers, progress=progress, bvh=bvh, volume=volume)
    if fp is None:
        fp = recorded.get("digest")
    inputs = {**make_inputs(graph_key(bake), s, material, fp, bake.mm_per_unit), **(extra_inputs or {})}
    data.stats["inputs"] = inputs
    data.stats["key"] = ss_key(inputs)
    return data


def attach(bake, data):
    """A copy of ``bake`` holding ``data`` (or none, with ``data=None``), with the key that says so."""
    g = graph_key(bake)
    stats = dict(bake.stats or {})
    if data is None:
        stats.pop("graph_key", None)
        return replace(bake, single_scattering=None, key=g, stats=stats)
    key = (data.stats or {}).get("key")
    if not key:
        inputs = (data.stats or {}).get("inputs")
        key = ss_key(inputs) if inputs else _digest({"n": data.n_samples, "c": float(np.sum(data.centers))})
    stats["graph_key"] = g
    return replace(bake, single_scattering=data, key=combined_key(g, key), stats=stats)


def staleness(data, *, settings=None, material=None, field_fp=..., mm_per_unit=None, graph=None) -> list[str]:
    """What changed since ``data`` was baked (empty: still valid).  Only the given inputs are checked.

    ``settings``: the wanted :class:`SingleScatteringSettings` (a lower SH
    order than baked is not a change: the run time truncates the series).
    ``field_fp``: the current field fingerprint (``...``: do not check).
    """
    inputs = (data.stats or {}).get("inputs")
    if not inputs:
        return ["the single-scattering data does not record what it was baked from"]
    out = []
    if graph is not None and inputs.get("graph_key") not in (None, graph):
        out.append("the mesh was re-baked")
    if material is not None:
        now = material_fingerprint(material)
        if now != inputs.get("material"):
            out.append(f"the material changed (baked: {_describe(inputs.get('material'))}; now: {_describe(now)})")
    if field_fp is not ... and (material is None or material.heterogeneous or inputs.get("field") is not None):
        if field_fp != inputs.get("field"):
            out.append("the heterogeneity field changed")
    if mm_per_unit is not None and abs(float(mm_per_unit) - float(inputs.get("mm_per_unit", 0))) > 1e-6 * max(
            1.0, abs(float(mm_per_unit))):
        out.append(f"the scale changed (baked at {inputs.get('mm_per_unit'):.6g} mm per unit, now {mm_per_unit:.6g})")
    if settings is not None:
        want = settings_dict(settings)
        have = inputs.get("settings", {})
        diffs = []
        for k, label in SETTING_LABELS.items():
            if k == "sh_order":
                if int(want[k]) > int(have.get(k, 0)):
                    diffs.append(f"{label} {have.get(k)} -> {want[k]}")
            elif want.get(k) != have.get(k):
                diffs.append(f"{label} {have.get(k)} -> {want[k]}")
        if diffs:
            out.append("the single-scattering settings changed (" + ", ".join(diffs) + ")")
    return out


def _describe(m) -> str:
    if not m:
        return "?"

    def med(x):
        return "sigma_a " + "/".join(f"{v:.4g}" for v in x["sigma_a"]) + ", sigma_s " + "/".join(
            f"{v:.4g}" for v in x["sigma_s"])

    return med(m["a"]) + (f" mixed with {med(m['b'])}" if "b" in m else "")


def stale_message(reasons) -> str:
    """The user-facing sentence for :func:`staleness` reasons ('' when there are none)."""
    if not reasons:
        return ""
    return ("single scattering needs a re-bake: " + "; ".join(reasons)
            + ". The optical depth was baked from sigma_t (material, field and scale), so the single-scattering "
              "term still shows the old bake until you re-bake single scattering")
