"""The command line's arguments: each option's type (a value checked at the door: one line and exit
status 2 naming the option), and the arguments turned into the engine's inputs (material, field, lights)
and checked files.  ``__main__`` builds the parser from these; ``cli_solve`` and ``__main__`` read them."""

from __future__ import annotations

import argparse
import os

import numpy as np

from .errors import TranslucencyError


def checked(check, what: str, cast=float):
    """An argparse type: ``cast(text)`` passed through the engine's ``check`` (its message on failure)."""
    kind = "a whole number" if cast is int else "a number"

    def parse(text):
        try:
            return check(cast(text))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}: expected {kind}, got {text!r}") from None
        except TranslucencyError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    parse.__name__ = what
    return parse


def in_range(lo: float, hi: float, what: str, cast=float, lo_open: bool = False, hi_open: bool = False):
    """An argparse type: a finite number in [lo, hi] (open ends where asked)."""
    def check(v):
        if not (np.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)):
            ends = ("(" if lo_open else "[") + f"{lo:g}, {hi:g}" + (")" if hi_open else "]")
            raise TranslucencyError(f"expected a finite number in {ends}, got {v:g}")
        return v
    return checked(check, what, cast)


def mm_per_unit(text):
    from .scene.materials import check_mm_per_unit

    return checked(check_mm_per_unit, "--mm-per-unit")(text)


def radius(text):
    from .fluid.particles import check_radius

    return checked(check_radius, "--radius")(text)


def eta(text):
    from .scene.fresnel import check_eta

    return checked(check_eta, "--eta")(text)


tolerance = in_range(0.0, 1.0, "--tol", lo_open=True, hi_open=True)


def floats(text: str, n: int, what: str) -> tuple:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n:
        raise argparse.ArgumentTypeError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    if not all(np.isfinite(vals)):
        raise argparse.ArgumentTypeError(f"{what}: expected {n} finite numbers (no NaN or Inf), got {text!r}")
    return vals


def rgb(text):
    return floats(text, 3, "R,G,B")


def camera(text):
    return floats(text, 3, "--camera X,Y,Z")


def sun(text):
    try:
        d, e = text.split(":")
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sun: expected DX,DY,DZ:E, got {text!r}") from None
    return floats(d, 3, "--sun direction"), floats(e, 1, "--sun irradiance")[0]


def point(text):
    """``X,Y,Z:W[:R]``: position, power and (optional) radius in object units (Blender's Radius)."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(f"--point: expected X,Y,Z:W or X,Y,Z:W:R, got {text!r}")
    radius = floats(parts[2], 1, "--point radius")[0] if len(parts) == 3 else 0.0
    if radius < 0:
        raise argparse.ArgumentTypeError(f"--point radius must be >= 0, got {radius}")
    return floats(parts[0], 3, "--point position"), floats(parts[1], 1, "--point power")[0], radius


def spot(text):
    """``X,Y,Z:DX,DY,DZ:W:SIZE[:BLEND[:R]]``: position, the direction it points, power in W, Blender's Spot
    Size (the full cone angle) in degrees, Spot Blend (default 0.15) and Radius (object units, default 0)."""
    parts = text.split(":")
    if len(parts) not in (4, 5, 6):
        raise argparse.ArgumentTypeError(f"--spot: expected X,Y,Z:DX,DY,DZ:W:SIZE[:BLEND[:R]], got {text!r}")
    pos = floats(parts[0], 3, "--spot position")
    d = floats(parts[1], 3, "--spot direction")
    if not any(d):
        raise argparse.ArgumentTypeError("--spot direction must not be 0,0,0")
    watts = floats(parts[2], 1, "--spot power")[0]
    size = floats(parts[3], 1, "--spot size")[0]
    if not 1.0 <= size <= 180.0:  # Blender's range for Spot Size
        raise argparse.ArgumentTypeError(f"--spot size is the full cone angle in degrees, 1 to 180, got {size}")
    blend = floats(parts[4], 1, "--spot blend")[0] if len(parts) > 4 else 0.15
    if not 0.0 <= blend <= 1.0:
        raise argparse.ArgumentTypeError(f"--spot blend must be in [0, 1], got {blend}")
    radius = floats(parts[5], 1, "--spot radius")[0] if len(parts) > 5 else 0.0
    if radius < 0:
        raise argparse.ArgumentTypeError(f"--spot radius must be >= 0, got {radius}")
    return pos, d, watts, size, blend, radius


def area(text):
    """``X,Y,Z:EX,EY,EZ:FX,FY,FZ:W[:disk]``: centre, the emitter's two full edges (object units; it emits
    along F x E, Blender's local -Z for edges along its local X and Y), power in W (Blender's, normalised),
    and ``disk`` for Disk/Ellipse (default: Square/Rectangle)."""
    parts = text.split(":")
    if len(parts) not in (4, 5) or (len(parts) == 5 and parts[4].lower() not in ("disk", "square")):
        raise argparse.ArgumentTypeError(f"--area: expected X,Y,Z:EX,EY,EZ:FX,FY,FZ:W[:disk], got {text!r}")
    pos = floats(parts[0], 3, "--area position")
    ex, ey = floats(parts[1], 3, "--area first edge"), floats(parts[2], 3, "--area second edge")
    if np.linalg.norm(np.cross(ey, ex)) <= 0:
        raise argparse.ArgumentTypeError("--area edges must be non-zero and not parallel")
    watts = floats(parts[3], 1, "--area power")[0]
    return pos, ex, ey, watts, len(parts) == 5 and parts[4].lower() == "disk"


def field(text):
    kind, _, scale = text.partition(":")
    if not scale:
        return kind, 1.0
    return kind, in_range(0.0, np.inf, "--field SCALE", lo_open=True, hi_open=True)(scale)



def material_args(parser, prefix: str) -> None:
    parser.add_argument("--material", default=None, help=prefix + "preset name (marble, skimmilk, skin1, ketchup, ...)")
    parser.add_argument("--mix-with", default=None, help=prefix + "second preset mixed in by --field")
    parser.add_argument("--field", type=field, default=None,
                        help=prefix + "mixing field KIND[:SCALE], SCALE in object units > 0, e.g. marble:0.05 "
                                      "(default marble, a quarter of the size)")
    parser.add_argument("--sigma-a", type=rgb, default=None,
                        help=prefix + "absorption R,G,B per mm, each >= 0 (custom material)")
    parser.add_argument("--sigma-s", type=rgb, default=None,
                        help=prefix + "reduced scattering R,G,B per mm, each >= 0 (custom material)")
    parser.add_argument("--eta", type=eta, default=1.3,
                        help=prefix + "relative refractive index, in [1, 4] (default 1.3)")


def field_spec_from_args(a, V):
    """The mixing field of a heterogeneous material: --field, or marble at a quarter of the mesh size."""
    from .scene.fields import FieldSpec

    kind, scale = a.field or ("marble", 0.25 * float(np.max(np.ptp(np.asarray(V), axis=0))))
    return FieldSpec(kind=kind, scale=scale)


def material_from_args(a):
    from .scene.materials import Material, Medium, material_from_preset, preset

    if a.sigma_a is not None or a.sigma_s is not None:
        if a.sigma_a is None or a.sigma_s is None:
            raise TranslucencyError("a custom material needs both --sigma-a and --sigma-s")
        return Material(Medium(a.sigma_a, a.sigma_s, "custom"), preset(a.mix_with) if a.mix_with else None, a.eta)
    return material_from_preset(a.material or "marble", eta=a.eta, mix_with=a.mix_with)


def lights_from_args(a):
    from .scene.lights import Environment, Light

    lights = []
    for d, e in a.sun:
        lights.append(Light("sun", irradiance=e, direction=d, name="sun"))
    for pos, watts, radius in a.point:
        lights.append(Light("point", intensity=watts / (4.0 * np.pi), position=pos, radius=radius, name="point"))
    for pos, d, watts, size, blend, radius in getattr(a, "spot", ()):  # Blender's units, as ops.scene_inputs
        lights.append(Light("spot", intensity=watts / (4.0 * np.pi), position=pos, direction=d,
                            spot_size=float(np.radians(size)), spot_blend=blend, radius=radius, name="spot"))
    for pos, ex, ey, watts, disk in getattr(a, "area", ()):
        normal = np.cross(ey, ex)
        lights.append(Light("area", intensity=watts / np.pi, position=pos,
                            direction=tuple(float(x) for x in normal / np.linalg.norm(normal)),
                            shape="ellipse" if disk else "rectangle", edge_x=ex, edge_y=ey, name="area"))
    env = Environment(a.env) if a.env is not None else None
    return lights, env


def check_files(inputs=(), outputs=()) -> None:
    """Refuse, before any work, an input that is not a readable file or an output that cannot be written.

    ``inputs`` and ``outputs`` are ``(option, path)`` pairs (``path`` None: not given).  An output's folder
    must exist and be writable (nothing creates it), the output must not be a folder, and no two outputs
    may be the same file.  Raises :class:`InputError` naming the option and the file."""
    from .errors import InputError

    for option, path in inputs:
        if path is None:
            continue
        if not os.path.exists(path):
            raise InputError(f"{option} {path}: no such file")
        if not os.path.isfile(path):
            raise InputError(f"{option} {path}: is a folder, not a file")
        if not os.access(path, os.R_OK):
            raise InputError(f"{option} {path}: cannot be read (no read permission for this user)")
    seen = {}
    for option, path in outputs:
        if path is None:
            continue
        full = os.path.realpath(path)
        folder = os.path.dirname(full)
        if full in seen:
            raise InputError(f"{option} and {seen[full]} are the same file {path}; give each output its own name")
        seen[full] = option
        if os.path.isdir(full):
            raise InputError(f"{option} {path}: is a folder; give a file name inside it")
        if not os.path.isdir(folder):
            raise InputError(f"{option} {path}: the folder {os.path.dirname(os.path.abspath(path))} does not exist; "
                             "create it first")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise InputError(f"{option} {path}: the folder {folder} is not writable for this user")
        if os.path.exists(full) and not os.access(full, os.W_OK) and not os.access(folder, os.W_OK):
            raise InputError(f"{option} {path}: cannot be replaced (no write permission)")


def inner_paths(specs) -> list:
    """The files of ``--inner PART.obj:ROLE`` (malformed specs are refused later, with the spec)."""
    return [("--inner", str(spec).rpartition(":")[0]) for spec in specs if str(spec).rpartition(":")[0]]


