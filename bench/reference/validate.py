# SPDX-License-Identifier: GPL-3.0-or-later
"""Validation of the reference renderer; prints the numbers quoted in ``docs/reference.md``.

    python -m bench.reference.validate furnace [--spp 1024] [--res 32] [--smooth]
    python -m bench.reference.validate marble  [--spp 4096] [--res 32] [--analytic]
    python -m bench.reference.validate masks
    python -m bench.reference.validate sky     [--spp 256]
    python -m bench.reference.validate hetero  [--spp 256]

Run from the repository root with the project's virtual environment.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.reference import metrics  # noqa: E402
from bench.reference.mitsuba_ref import render_mask, render_reference  # noqa: E402
from bench.reference.raster import rasterize  # noqa: E402
from bench.reference.scene import Camera, mesh_sky, mesh_sun, sky_environment, sphere_env  # noqa: E402
from data import mesh_path  # noqa: E402
from translucency_addon.scene.fields import FieldSpec  # noqa: E402
from translucency_addon.scene.materials import Material, Medium, material_from_preset, preset  # noqa: E402

WHITE = Medium((0.0, 0.0, 0.0), (2.19, 2.62, 3.00), "white-marble")  # albedo 1, marble's sigma_s'


def _fmt(v, nd=4):
    return "(" + ", ".join(f"{x:.{nd}f}" for x in np.ravel(v)) + ")"


def _centre(img, k=2):
    H, W = img.shape[:2]
    return img[H // 2 - k // 2:H // 2 + (k + 1) // 2, W // 2 - k // 2:W // 2 + (k + 1) // 2]


def _progress(msg):
    print("  ", msg, file=sys.stderr, flush=True)


def cmd_furnace(a):
    sc = sphere_env(Material(WHITE, eta=1.3), image_res=a.res, spp=a.spp, analytic=a.analytic)
    sc.smooth_normals = a.smooth
    res = render_reference(sc, progress=_progress if a.verbose else None)
    P = metrics.comparison_mask(res.mask)
    full = res.full
    print(f"furnace: sphere R=12 mm, eta 1.3, albedo 1, sigma_s'={WHITE.sigma_s}/mm, env 1, "
          f"{a.res}x{a.res}, {res.spp} spp/channel x 3, {res.batches} batches, variant {res.variant}, "
          f"{'analytic sphere' if a.analytic else ('smooth' if a.smooth else 'flat') + ' mesh'}: {res.seconds:.1f} s")
    print(f"  interior pixels: {P.sum()}")
    print(f"  translucency + reflection, mean over pixels: {_fmt(full[P].mean(0))}")
    print(f"  ... min / max pixel: {full[P].min():.4f} / {full[P].max():.4f}")
    print(f"  ... standard error of that mean: {_fmt(np.sqrt((res.stderr[P] ** 2).sum(0)) / P.sum())}")
    print(f"  translucency alone, mean: {_fmt(res.image[P].mean(0))}; reflection alone, mean: {_fmt(res.reflection[P].mean(0))}")
    print(f"  per-pixel stderr (mean over pixels): {_fmt(res.stderr[P].mean(0))}")
    print(f"  centre 2x2 translucency: {_fmt(_centre(res.image).mean((0, 1)))}, reflection: {_fmt(_centre(res.reflection).mean((0, 1)))}")


def cmd_marble(a):
    sc = sphere_env(material_from_preset("marble"), image_res=a.res, spp=a.spp, analytic=a.analytic, seed=a.seed)
    sc.smooth_normals = a.smooth
    res = render_reference(sc, progress=_progress if a.verbose else None)
    c = _centre(res.image)
    cs = np.sqrt((_centre(res.stderr) ** 2).sum((0, 1))) / 4
    print(f"marble sphere: R=12 mm, eta 1.3, env 1, {a.res}x{a.res}, {res.spp} spp/channel x 3, {res.batches} batches, "
          f"variant {res.variant}, {'analytic sphere' if a.analytic else ('smooth' if a.smooth else 'flat') + ' mesh'}: {res.seconds:.1f} s")
    print(f"  centre 2x2 translucency: {_fmt(c.mean((0, 1)))} +- {_fmt(cs)} (1 sigma)")
    print(f"  centre 2x2 reflection:   {_fmt(_centre(res.reflection).mean((0, 1)))}")
    H, W = res.image.shape[:2]
    yy, xx = np.mgrid[:H, :W]
    r_mm = np.hypot(xx + 0.5 - W / 2, yy + 0.5 - H / 2) * (sc.camera.width * sc.mm_per_unit / W)
    for lo, hi in ((0, 3), (3, 6), (6, 9), (9, 11)):
        sel = (r_mm >= lo) & (r_mm < hi) & res.mask
        print(f"  ring {lo:2d}-{hi:2d} mm ({sel.sum():4d} px): {_fmt(res.image[sel].mean(0))} "
              f"+- {_fmt(np.sqrt((res.stderr[sel] ** 2).sum(0)) / sel.sum())}")
    P = metrics.comparison_mask(res.mask)
    print(f"  noise floor of rel. RMS over {P.sum()} px: {metrics.noise_floor(res.image, res.stderr, res.mask):.4f}")
    print(f"  per-pixel relative stderr (median): {_fmt(np.median(res.stderr[P] / res.image[P], axis=0))}")
    if a.save:
        np.savez_compressed(a.save, image=res.image, stderr=res.stderr, mask=res.mask, reflection=res.reflection)


def cmd_masks(a):
    m = material_from_preset("marble")
    scenes = [("sphere 32 seg, 32x32", sphere_env(m, image_res=32)),
              ("sphere 64 seg, 128x128", sphere_env(m, res=64, image_res=128))]
    scenes.append(("bunny, 256x256 ortho", mesh_sun(mesh_path("stanford-bunny"), m, image_res=256)))
    s = mesh_sun(mesh_path("spot"), m, image_res=64, view_direction=(1, -0.3, -1))
    s.resolution = (96, 64)
    scenes.append(("spot, 96x64 ortho oblique", s))
    s2 = mesh_sun(mesh_path("spot"), m, image_res=64)
    lo, hi = s2.bbox
    c, d = 0.5 * (lo + hi), np.linalg.norm(hi - lo)
    s2.camera = Camera.perspective(c + np.array([0.5, 0.3, 0.9]) * d, c, (0, 1, 0), 50.0)
    s2.resolution = (80, 60)
    scenes.append(("spot, 80x60 perspective", s2))
    for label, sc in scenes:
        t = time.perf_counter()
        mm = render_mask(sc)
        t1 = time.perf_counter() - t
        t = time.perf_counter()
        r = rasterize(sc.V, sc.F, np.ones(len(sc.V)), sc.camera, sc.resolution)
        t2 = time.perf_counter() - t
        print(f"{label}: {len(sc.F)} tris, Mitsuba mask {mm.sum()} px, raster mask {r.mask.sum()} px, "
              f"differ {(mm ^ r.mask).sum()} px; raster {t2 * 1e3:.0f} ms, Mitsuba mask {t1 * 1e3:.0f} ms")


def cmd_sky(a):
    """The SH-sky path: a constant sky equals the uniform environment; a lobe lights its side."""
    m = material_from_preset("marble")
    uni = render_reference(sphere_env(m, image_res=a.res, spp=a.spp))
    sc = sphere_env(m, image_res=a.res, spp=a.spp)
    sc.environment = sky_environment(lobe=0)  # radiance 1 everywhere, through envmap + SH
    const = render_reference(sc)
    rep = metrics.relative_rms(const.image, uni.image, const.mask, uni.mask,
                               stderr=np.sqrt(const.stderr**2 + uni.stderr**2))
    print(f"constant SH sky vs uniform environment: {rep} ({uni.seconds:.1f} s, {const.seconds:.1f} s)")
    sc.environment = sky_environment(to_light=(1.0, 0.0, 0.0), lobe=2)
    lobe = render_reference(sc)
    P = metrics.comparison_mask(lobe.mask)
    img = np.where(P[..., None], lobe.image, np.nan)
    W = a.res
    print(f"lobe-2 sky from +x: right third {_fmt(np.nanmean(img[:, 2 * W // 3:], axis=(0, 1)))}, "
          f"left third {_fmt(np.nanmean(img[:, :W // 3], axis=(0, 1)))} ({lobe.seconds:.1f} s)")
    b = mesh_sky(mesh_path("stanford-bunny"), m, image_res=a.res, spp=a.spp)
    res = render_reference(b)
    P = metrics.comparison_mask(res.mask)
    print(f"bunny under the lobe-2 sky ({b.mm_per_unit:.1f} mm/unit, {a.res}x{a.res}, {res.spp} spp): "
          f"{res.seconds:.1f} s, mean {_fmt(res.image[P].mean(0))}, noise floor "
          f"{metrics.noise_floor(res.image, res.stderr, res.mask):.4f}")


def cmd_hetero(a):
    """The grid path: a heterogeneous material whose field is 0 (1) everywhere must equal medium A (B)."""
    A, B = preset("marble"), preset("skimmilk")
    out = {}
    for label, mat, fld in (("homogeneous marble", Material(A), None),
                            ("grid, field 0 -> marble", Material(A, B), FieldSpec("uniform")),
                            ("homogeneous skim milk", Material(B), None),
                            ("grid, field 1 -> skim milk", Material(A, B), FieldSpec("sphere", scale=100.0)),
                            ("grid, checker 6 mm", Material(A, B), FieldSpec("checker", scale=6.0))):
        sc = sphere_env(mat, image_res=a.res, spp=a.spp, field=fld)
        res = render_reference(sc)
        out[label] = res
        P = metrics.comparison_mask(res.mask)
        print(f"{label}: mean {_fmt(res.image[P].mean(0))}, {res.seconds:.1f} s")
    for x, y in (("grid, field 0 -> marble", "homogeneous marble"), ("grid, field 1 -> skim milk", "homogeneous skim milk")):
        rep = metrics.relative_rms(out[x].image, out[y].image, out[x].mask, out[y].mask,
                                   stderr=np.sqrt(out[x].stderr**2 + out[y].stderr**2))
        print(f"{x} vs {y}: {rep}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["furnace", "marble", "masks", "sky", "hetero"])
    ap.add_argument("--spp", type=int, default=None)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--smooth", action="store_true", help="interpolated shading normals")
    ap.add_argument("--analytic", action="store_true", help="render the exact sphere instead of the mesh")
    ap.add_argument("--save", default=None, help="marble: save the result to this .npz")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    if a.spp is None:
        a.spp = {"furnace": 1024, "marble": 4096}.get(a.what, 256)
    {"furnace": cmd_furnace, "marble": cmd_marble, "masks": cmd_masks, "sky": cmd_sky, "hetero": cmd_hetero}[a.what](a)


if __name__ == "__main__":
    main()
