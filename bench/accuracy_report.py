# SPDX-License-Identifier: GPL-3.0-or-later
"""Plots and tables of ``bench/accuracy.py`` (docs/accuracy.md); ``accuracy_text`` writes the text around them and imports this module, never the reverse."""

from __future__ import annotations

import math

import numpy as np

KNOB_TITLES = {
    "preset": "quality preset (Draft, Preview, Final)",
    "K": "K (inner / surface tet size - 1), Preview surface",
    "K_final": "Final surface with Preview's K",
    "levels": "levels (multi-resolution), Preview",
    "tol": "tolerance, Preview",
    "iterations": "fixed steps per level, Preview",
    "solver": "solver, Preview",
    "precision": "GPU fp16 / fp32 (llvmpipe), Preview",
    "ss": "single scattering, Preview",
}
COLORS = {"preset": "k", "K": "tab:blue", "K_final": "tab:cyan", "levels": "tab:orange", "tol": "tab:green", "iterations": "tab:olive",
          "solver": "tab:red", "precision": "tab:purple", "ss": "tab:brown"}


def pct(x, digits=1):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{100.0 * x:.{digits}f} %"


def ms(x):
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:,.0f}" if x >= 10 else f"{x:.1f}"


def sec(x):
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:.1f}"


def rows(b, knob=None, scene=None):
    return [r for r in b.records if (knob is None or r["knob"] == knob) and (scene is None or r["scene"] == scene)]


def one(b, knob, scene, label):
    for r in rows(b, knob, scene):
        if r["label"] == label:
            return r
    return None


def pareto(points):
    """Indices of the Pareto-optimal (time, error) points (both minimised)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    best = math.inf
    keep = []
    for i in order:
        if points[i][1] < best:
            keep.append(i)
            best = points[i][1]
    return keep


# --- plots --------------------------------------------------------------------------------

def plot_pareto(b, scene, path):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 9))
    recs = [r for r in rows(b, scene=scene) if r["knob"] in KNOB_TITLES and not r.get("diverged") and "err_ref" in r]
    for col, (tkey, tlabel) in enumerate((("first_ms", "time of a first frame: all levels from zero (ms, CPU)"),
                                          ("bake_s", "bake time (s, CPU)"))):
        for row, (ekey, elabel) in enumerate((("err_ref", "(b) relative RMS vs path tracer"),
                                              ("err_conv", "(a) relative RMS vs converged Final solve"))):
            ax = axes[row, col]
            pts = []
            for knob in KNOB_TITLES:
                kr = [r for r in recs if r["knob"] == knob and ekey in r]
                if not kr:
                    continue
                xs = [r[tkey] for r in kr]
                ys = [max(r[ekey], 1e-5) for r in kr]
                if knob in ("preset", "K", "levels", "tol", "iterations"):
                    o = np.argsort(xs)
                    ax.plot(np.array(xs)[o], np.array(ys)[o], "-o", color=COLORS[knob], ms=4, label=KNOB_TITLES[knob])
                else:
                    ax.plot(xs, ys, "o", color=COLORS[knob], ms=5, label=KNOB_TITLES[knob])
                for r, x, y in zip(kr, xs, ys):
                    if knob in ("preset", "solver", "precision", "ss", "K_final"):
                        ax.annotate(r["label"], (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
                pts += list(zip(xs, ys))
            if pts:
                keep = pareto(pts)
                P = np.array([pts[i] for i in keep])
                ax.step(P[:, 0], P[:, 1], where="post", color="k", lw=0.8, alpha=0.6)
                ax.plot(P[:, 0], P[:, 1], "s", mfc="none", mec="k", ms=10, label="Pareto front")
            if ekey == "err_ref":
                floor = next((r["noise_floor"] for r in recs if "noise_floor" in r), None)
                conv = one(b, "converged", scene, next((r["label"] for r in rows(b, "converged", scene)), ""))
                if floor:
                    ax.axhline(floor, color="gray", ls=":", lw=1, label=f"reference noise floor {pct(floor)}")
                if conv:
                    ax.axhline(conv["err_ref"], color="tab:cyan", ls="--", lw=1,
                               label=f"converged Final solve (model error) {pct(conv['err_ref'])}")
                for q, t in (("preview", 0.05), ("final", 0.02)):
                    ax.axhline(t, color="r", lw=0.6, alpha=0.4)
                    ax.text(ax.get_xlim()[0] if ax.lines else 1, t, f" target {q}", fontsize=7, color="r", va="bottom")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(tlabel)
            ax.set_ylabel(elabel)
            ax.grid(True, which="both", alpha=0.3)
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="lower center", ncol=3, fontsize=8)
    fig.suptitle(f"Accuracy against time, one curve per knob: {scene.replace('_', ' ')}")
    fig.tight_layout(rect=(0, 0.1, 1, 0.97))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_headline(b, path):
    """README plot: error of the presets on every scene against frame time."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name in b.scenes:
        pr = [one(b, "preset", name, q) for q in ("draft", "preview", "final")]
        pr = [r for r in pr if r and "err_ref" in r]
        if not pr:
            continue
        x = [r["first_ms"] for r in pr]
        y = [r["err_ref"] for r in pr]
        ls = "-" if name.startswith("bunny") else "--"
        ax.plot(x, y, ls + "o", ms=4, label=name.replace("_", " "))
    ax.axhline(0.05, color="r", lw=0.6, alpha=0.5)
    ax.axhline(0.02, color="r", lw=0.6, alpha=0.5)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("first frame (all levels from zero), ms on 2 CPU cores; points: Draft, Preview, Final")
    ax.set_ylabel("relative RMS vs path tracer")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _exposure(ref):
    v = ref.image[ref.mask]
    return 1.0 / max(float(np.percentile(v, 99)), 1e-6)


def plot_images(b, path):
    import matplotlib.pyplot as plt

    names = list(b.scenes)
    quals = [q for q in ("draft", "preview", "final") if (names[0], q) in b.images]
    shown = [q for q in ("preview", "final") if q in quals] or quals
    cols = ["reference"] + [f"ours {q}" for q in shown] + [f"ours {shown[-1]} - reference"]
    fig, axes = plt.subplots(len(names), len(cols), figsize=(2.2 * len(cols), 2.2 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        ref = b.refs[name]
        k = _exposure(ref)
        axes[i, 0].imshow(np.clip(ref.image * k, 0, 1), interpolation="nearest")
        for j, q in enumerate(shown):
            img, mask = b.images[(name, q)]
            axes[i, 1 + j].imshow(np.clip(img * k, 0, 1), interpolation="nearest")
        img, mask = b.images[(name, shown[-1])]
        d = (img - ref.image).mean(axis=-1) * k
        d[~(mask & ref.mask)] = 0
        im = axes[i, -1].imshow(d, cmap="RdBu_r", vmin=-0.2, vmax=0.2, interpolation="nearest")
        axes[i, 0].set_ylabel(name.replace("_", "\n"), fontsize=8)
    for j, c in enumerate(cols):
        axes[0, j].set_title(c, fontsize=9)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=axes[:, -1].tolist(), shrink=0.5, label="difference / 99th percentile of reference")
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)


def plot_scanlines(b, path):
    """Fig. 11 of the paper: two scan lines, reference in black, ours in colour."""
    import matplotlib.pyplot as plt

    from bench.reference.metrics import scanline

    names = [n for n in ("bunny_marble_sky", "sphere_marble_sky", "bunny_hetero_sky", "bunny_skin1_sky")
             if n in b.scenes] or list(b.scenes)[:2]
    fig, axes = plt.subplots(len(names), 2, figsize=(11, 2.8 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        ref = b.refs[name]
        H = ref.image.shape[0]
        for j, row in enumerate((int(0.4 * H), int(0.65 * H))):
            ax = axes[i, j]
            x, v, e = scanline(ref.image.mean(axis=-1), ref.mask, row=row, stderr=np.sqrt((ref.stderr**2).mean(-1) / 3))
            ax.fill_between(x, v - 2 * e, v + 2 * e, color="0.8", step="mid", label="reference +- 2 s.e.")
            ax.plot(x, v, "k-", drawstyle="steps-mid", label="path tracer (Mitsuba)")
            for q, c in (("draft", "tab:orange"), ("preview", "tab:blue"), ("final", "tab:green")):
                if (name, q) in b.images:
                    img, mask = b.images[(name, q)]
                    _, vo, _ = scanline(img.mean(axis=-1), mask, row=row)
                    ax.plot(x, vo, color=c, drawstyle="steps-mid", label=f"ours {q}")
            ax.set_title(f"{name.replace('_', ' ')}, row {row} of {H}", fontsize=9)
            ax.set_xlabel("pixel column")
            ax.set_ylabel("radiance (RGB mean)")
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_K(b, path):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name in b.scenes:
        kr = sorted(rows(b, "K", name), key=lambda r: r["K"])
        if not kr:
            continue
        K = [r["K"] for r in kr]
        ax.plot(K, [r["err_ref"] for r in kr], "-o", label=f"{name.replace('_', ' ')}: (b) vs path tracer")
        ax.plot(K, [max(r.get("err_conv", np.nan), 1e-5) for r in kr], "--s",
                label=f"{name.replace('_', ' ')}: (a) vs converged Final")
    ax.set_xlabel("K")
    ax.set_ylabel("relative RMS")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("Error against K (cf. the paper's Fig. 13)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_kappa(b, path):
    import matplotlib.pyplot as plt

    kr = getattr(b, "kappa_rows", [])
    if not kr:
        return False
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for r in kr:
        h = np.asarray(r.get("history_finest", r["history"]), dtype=float)
        it = np.arange(len(h)) * 8
        ax.semilogy(it, np.where(np.isfinite(h), h, np.nan),
                    label={"fast": "ours: finite volumes + CG / Chebyshev", "paper": "paper: eq. 5-6 + Jacobi"}[r["solver"]])
    ax.axhline(1e-4, color="gray", ls=":", lw=1)
    ax.set_xlabel("iterations (finest level alone, from zero)")
    ax.set_ylabel("relative residual (max over RGB)")
    ax.set_title("Marble veined with ketchup (kappa jumps ~100x): convergence", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


# --- markdown -----------------------------------------------------------------------------

def table(head, body):
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in body]
    return "\n".join(out)


def headline_table(b, scene="bunny_marble_sky"):
    body = []
    conv = rows(b, "converged", scene)
    for q in ("draft", "preview", "final"):
        r = one(b, "preset", scene, q)
        if r is None:
            continue
        t = {"preview": 0.05, "final": 0.02}.get(q)
        met = "-" if t is None else ("met" if r["err_ref"] <= t else
                                     ("met after noise" if r["err_ref_debiased"] <= t else "**missed**"))
        body.append([q.capitalize(), f"{r['nodes'][0]:,} / {r['nodes'][1]:,}", sec(r["bake_s"]), ms(r["first_ms"]),
                     ms(r["frame_ms"]), pct(r.get("err_conv"), 2), pct(r["err_ref"]), pct(r["err_ref_debiased"]),
                     "-" if t is None else f"<= {pct(t, 0)}", met])
    for r in conv:
        body.append([f"converged ({r['label']})", f"{r['nodes'][0]:,} / {r['nodes'][1]:,}", "-", "-", "-",
                     "0", pct(r["err_ref"]), pct(r["err_ref_debiased"]), "-", "model error"])
    return table(["preset", "finest graph: surface / inner nodes", "bake s", "first frame ms", "frame ms (warm)",
                  "(a) vs converged", "(b) vs path tracer", "(b) debiased", "target", ""], body)


def reference_table(b):
    body = []
    for name, ref in b.refs.items():
        from bench.reference.metrics import relative_rms

        fl = relative_rms(ref.image, ref.image, ref.mask, stderr=ref.stderr)
        m = ref.image[ref.mask].mean(axis=0)
        body.append([name, f"{ref.image.shape[1]}x{ref.image.shape[0]}", f"{ref.spp:,}", f"{ref.seconds:,.0f}",
                     ", ".join(f"{v:.3f}" for v in m), pct(fl.noise_floor, 2),
                     ", ".join(pct(v, 1) for v in fl.noise_floor_rgb)])
    return table(["scene", "pixels", "spp per channel", "render s", "mean RGB (object)", "noise floor",
                  "noise floor R, G, B"], body)


def scenes_table(b):
    body = []
    for name in b.scenes:
        conv = rows(b, "converged", name)
        c = conv[0] if conv else None
        cells = [name, pct(next((r["noise_floor"] for r in rows(b, scene=name) if "noise_floor" in r), None))]
        for q in ("draft", "preview", "final"):
            r = one(b, "preset", name, q)
            cells.append("-" if r is None else f"{pct(r['err_ref'])} ({pct(r['err_ref_debiased'])}) / {pct(r.get('err_conv'), 2)}")
        cells.append("-" if c is None else f"{pct(c['err_ref'])} ({pct(c['err_ref_debiased'])})")
        cells.append("-" if c is None else ", ".join(pct(v) for v in c["err_ref_rgb"]))
        body.append(cells)
    return table(["scene", "noise floor", "Draft: (b) (debiased) / (a)", "Preview", "Final",
                  "converged: model error (b) (debiased)", "model error R, G, B"], body)


def knob_table(b, knob, extra=()):
    body = []
    for r in rows(b, knob):
        cells = [r["scene"], r["label"], f"{sum(r['nodes']):,}" if r.get("nodes") else "-", sec(r.get("bake_s")),
                 ms(r.get("first_ms")), str(r.get("level_iterations") or r.get("iterations", "-")),
                 "**diverged**" if r.get("diverged") else pct(r.get("err_conv"), 2),
                 "-" if r.get("diverged") else pct(r.get("err_ref"))]
        for _, key, fmt in extra:
            cells.append(fmt(r.get(key)))
        body.append(cells)
    head = ["scene", "setting", "nodes (finest)", "bake s", "first frame ms", "iterations per level",
            "(a) vs converged", "(b) vs path tracer"] + [e[0] for e in extra]
    return table(head, body)


# issue 17's targets: (scene, target on the converged Final graph's debiased error, the issue's "today")
TRANSPORT_TARGETS = (("bunny_marble_sky", 0.020, "3.3 %"), ("bunny_skimmilk_sky", 0.030, "4.7 %"),
                     ("bunny_hetero_sky", 0.040, "7.6 %"), ("bunny_skin1_sky", 0.080, "15.9 % (blue 42 %)"))
BLUE_TARGET = ("bunny_skin1_sky", 0.15)


def transport_targets_table(b):
    """Issue 17's target table from this run: the converged Final graph (debiased) per scene against its
    target; every term against diffusion alone (the ss knob, Preview); Preview's distance from converged."""
    body = []
    for name, target, before in TRANSPORT_TARGETS:
        r = rows(b, "converged", name)
        if not r:
            continue
        err = r[0]["err_ref_debiased"]
        cell, ok = pct(err), err <= target
        if name == BLUE_TARGET[0]:
            blue = raw = r[0]["err_ref_rgb"][2]
            ref = getattr(b, "refs", {}).get(name)
            if ref is not None:  # the blue channel's own noise floor (the reference table's)
                from bench.reference.metrics import relative_rms

                floor = relative_rms(ref.image, ref.image, ref.mask, stderr=ref.stderr).noise_floor_rgb[2]
                blue = math.sqrt(max(raw**2 - floor**2, 0.0))
                cell += f" (blue {pct(blue)} debiased, {pct(raw)} raw)"
            else:
                cell += f" (blue {pct(raw)}, not debiased)"
            ok = ok and blue <= BLUE_TARGET[1]
            tgt = f"<= {pct(target)} (blue <= {pct(BLUE_TARGET[1])})"
        else:
            tgt = f"<= {pct(target)}"
        body.append([f"{name}, converged Final", tgt, before, cell, "met" if ok else "**missed**"])
    pairs = []
    for name in b.scenes:
        alone, every = one(b, "ss", name, "diffusion only"), one(b, "ss", name, "every term (split)")
        if alone and every:
            pairs.append((name, alone, every))
    if pairs:
        worse = [n for n, a, e in pairs if e["err_ref_debiased"] > a["err_ref_debiased"]]
        cell = "; ".join(f"{n} {pct(a['err_ref_debiased'])} -> {pct(e['err_ref_debiased'])}" for n, a, e in pairs)
        body.append(["every term on against diffusion alone (Preview, debiased)", "never worse",
                     "worse on every scene", cell, "met" if not worse else f"**missed** on {', '.join(worse)}"])
        cost = "; ".join(f"{n} {ms(e['frame_ms'])} against {ms(a['frame_ms'])} ms" for n, a, e in pairs)
        over = [n for n, a, e in pairs if e["frame_ms"] > 1.3 * a["frame_ms"]]
        body.append(["Preview warm frame, every term on against diffusion alone (same run, faster of two)", "<= 1.3x",
                     "-", cost,
                     "met" if not over else f"**missed** on {', '.join(over)}"])
    gaps = []
    for name in b.scenes:
        pv, c = one(b, "preset", name, "preview"), rows(b, "converged", name)
        if pv and c:
            gaps.append((pv["err_ref_debiased"] - c[0]["err_ref_debiased"], name))
    if gaps:
        g, n = max(gaps)
        body.append(["Preview within 1.5 points of the converged Final, every scene", "<= 1.5 points", "-",
                     f"largest gap {100 * g:.1f} points ({n})", "met" if g <= 0.015 else "**missed**"])
    return table(["scene", "target", "issue 17's today", "this run", ""], body)
