"""The planner's words, in one place: every reason, skip, refusal and advice the panel and the CLI show.

The rules (:mod:`.planner_rules`) decide and keep their reasons as data
(:class:`.planner_rules.Reason`: what, the measured value, the threshold);
this module turns them into the sentences of ``PassDecision.reasons``,
``Plan.reason``, ``Plan.advice`` and :func:`describe_plan`.
"""

from __future__ import annotations

from .planner_rules import (ALBEDO, ALBEDO_MIN, MS_SHARE, NEGLIGIBLE, SHARE, SS_SHARE, THICKNESS, VALID_SHARE, Reason,
                            Region, Why)

CHANNELS = ("R", "G", "B")
# What makes the single-scattering pass available, in Blender and on the command line (plans' hints).
SS_HINT = ("Bake single scattering: in Blender turn on Single Scattering and press Bake (or Bake Single "
           "Scattering); on the command line, bake --single-scattering --material NAME")
# What the accuracy bench measured on the paper's scenes (docs/accuracy.md, "Objects with inner parts"):
# the scattering passes against Mitsuba's scattered light, and their frame time on 2 CPU cores.
MEASURED_INNER_PARTS = ("measured against a path tracer on a cube with a cavity: single scattering 51 %, the Voxel "
                        "Number Map 59 % relative RMS, about 19 against 8 ms per frame; docs/accuracy.md")


def _pct(x: float) -> str:
    v = 100.0 * x
    return "< 0.01 %" if x < 1e-4 else (f"{v:.2g} %" if v < 10 else f"{v:.0f} %")


def _where(region: Region) -> str:
    """The region where diffusion is doubtful in one channel, in numbers."""
    parts = []
    if region.thin_share > 0:
        parts.append(f"thinner than {region.thinner_than_mm:.2g} mm ({region.thick_min:g} transport mean free path)")
    if region.low_share > 0:
        parts.append(f"reduced albedo below {region.albedo_min}")
    text = " or ".join(parts) + f": {_pct(region.fraction)} of the surface" if parts else ""
    if region.blend_share > 0:
        blend = (f"reduced albedo between {region.albedo_min} and {region.albedo_full} (diffusion's weight rising "
                 f"from 0 to 1 across it): {_pct(region.blend_share)} of the surface")
        text = f"{text}; and blended with it where {blend}" if text else blend
    return text


def _invalid(r: Reason) -> str:
    m = r.invalid
    if m.quantity == ALBEDO:
        return f"reduced albedo {m.value:.2f} < {m.threshold}"
    return f"optically thin: {m.value:.1f} transport mean free paths across its thin parts"


def _kinds(parts: dict) -> str:
    return ", ".join(f"{n} {r}{'s' if n > 1 and r != 'opaque' else ''}" for r, n in sorted(parts.items()))


def _text(r: Reason) -> str:
    """One channel's reason, without the channel's letter."""
    w = r.what
    if w is Why.VALID:
        return (f"diffusion valid (reduced albedo {r.value(ALBEDO):.3f}, "
                f"{r.value(THICKNESS):.0f} transport mean free paths thick)")
    if w is Why.VALID_IN_REGION:
        return (f"diffusion valid on {_pct(r.value(VALID_SHARE))} of the surface; single "
                f"scattering replaces it where {_where(r.region)}")
    if w is Why.VALID_BLENDED:
        return f"diffusion valid (reduced albedo {r.value(ALBEDO):.3f}); blended with single scattering where {_where(r.region)}"
    if w is Why.DOUBTFUL_IN_REGION:
        return f"diffusion doubtful where {_where(r.region)}; it runs there too"
    if w is Why.DOUBTFUL_EVERYWHERE:
        return (f"diffusion doubtful everywhere ({_invalid(r)}); it runs because "
                + ("single scattering is not baked or is turned off" if r.single_pass
                   else "a particle fluid has no other pass"))
    if w is Why.INVALID:
        return f"diffusion invalid ({_invalid(r)})"
    if w is Why.INVALID_NEGLIGIBLE:
        # Not "it returns": on a 10 mm sphere of albedo 0.2 the graph's solve returns 3x what a random walk does
        # (issue 30); the half-space is what the share is measured on.
        return (f"diffusion invalid ({_invalid(r)}); left out: its half-space return is "
                f"{_pct(r.value(SHARE))} of the brightest channel, so what it returns on the object is its error")
    if w is Why.INVALID_REST_NEGLIGIBLE:
        cause = "optically thin" if r.region.thin_share > 0 else "low albedo"
        return (f"diffusion invalid ({cause}) where {_where(r.region)}; single scattering replaces it everywhere "
                f"(the rest returns {_pct(r.value(SHARE))} of the brightest channel)")
    if w is Why.NEGLIGIBLE:
        return f"negligible ({_pct(r.value(SHARE))} of the brightest channel)"
    if w is Why.SPLIT:
        return (f"contained in the diffusion term, which splits it off in closed form (first-scatter "
                f"split): single scattering brings {_pct(r.value(SS_SHARE))} and multiple scattering "
                f"{_pct(r.value(MS_SHARE))} of the object's peak (half-space estimate)")
    if w is Why.CONTAINED_SPLIT_OFF:
        return "contained in the diffusion term; not split off (turned off)"
    if w is Why.CONTAINED_NOT_SPLIT:
        return (f"contained in the diffusion term; split off it would bring {_pct(r.value(SS_SHARE))} of the "
                f"object's peak (< {_pct(NEGLIGIBLE)}): not split")
    if w is Why.REPLACES:
        return "the valid term where diffusion is not"
    if w is Why.REPLACES_IN_REGION:
        return f"the valid term where diffusion is not ({_where(r.region)})"
    if w is Why.BLENDS:
        return f"blended with diffusion where {_where(r.region)}"
    if w is Why.NOT_BAKED:
        return "not baked"
    if w is Why.TURNED_OFF:
        return "turned off"
    if w is Why.MAP_REPLACES_IT:
        return (f"the Voxel Number Map replaces it: the object has inner parts ({_kinds(r.parts)}) that the single-"
                f"scattering bake does not know (bake it with the parts to use it; {MEASURED_INNER_PARTS})")
    if w is Why.SINGLE_REPLACES_HERE:
        return ("single scattering replaces diffusion here: " + ("no inner parts" if not r.parts else
                f"baked with the inner parts, it is the more accurate ({MEASURED_INNER_PARTS})"))
    if w is Why.NOTHING_TO_REPLACE:
        return "nothing to replace"
    if w is Why.FORCED:
        return f"forced {'on' if r.on else 'off'} {r.note}"
    raise ValueError(f"no words for a pass's reason {w}")


def reason_text(r: Reason) -> str:
    """One channel's reason as the panel and the CLI show it ("R: diffusion valid (...)")."""
    text = f"{CHANNELS[r.channel]}: {_text(r)}"
    # the replacement's decision handed to the Voxel Number Map names the map instead of single scattering
    return text.replace("single scattering", "the Voxel Number Map") if r.stand_in else text


def reason_texts(why) -> list:
    """``PassDecision.reasons``: one sentence per channel."""
    return [reason_text(r) for r in why]


def advice_text(unbaked: dict, thin_fraction, baked: bool) -> str:
    """What a better result needs: single scattering where diffusion is doubtful (``unbaked``: channel -> the
    share of the surface), baked (``baked``: something is, so it is only turned off) or not."""
    chans = "".join(CHANNELS[c] for c in sorted(unbaked))
    share = max(unbaked.values())
    what = "thin parts" if any(thin_fraction[c] > 0 for c in unbaked) else "low albedo"
    todo = ("bake it to use it (" + SS_HINT[0].lower() + SS_HINT[1:] + ")" if not baked
            else "turn it on to use it (the object's Single Scattering setting)")
    return f"{chans}: single scattering would be more accurate on {_pct(share)} of the surface ({what}); {todo}"


def unlit_text(misses: list, world: str, no_lights: bool) -> str:
    """Why no light reaches an object, light by light in numbers, and what to change (a plan's skip).

    ``misses``: per light that misses, ``(label, kind, rgb)`` for one without power or ``(label, kind, axis_deg,
    covers_deg, reach_deg)`` for a spot or area light aimed away; ``world``: "black", "none" or "lit"."""
    why = []
    for m in misses:
        if len(m) == 3:
            why.append(f"{m[0]} has no power (colour x strength = {m[2]})")
            continue
        label, kind, axis, edge, reach = m
        what = "its cone's half-angle" if kind == "spot" else "the side it emits to"
        why.append(f"{label} is aimed {axis:.0f} deg away from the object's centre; the object covers "
                   f"{edge:.0f} deg around it and {what} is {reach:.0f} deg")
    if world != "lit":
        why.append("the world is black" if world == "black" else "there is no world light")
    if no_lights:
        why.insert(0, "no lights")
    return ("unlit: no light reaches it (" + "; ".join(why) + "). Give a light power, aim a spot or area light "
            "at the object, or give the World a colour and strength")


def plan_reason_text(r: Reason, multiple_reasons=()) -> str:
    """``Plan.reason``: why an object runs or is skipped (``multiple_reasons``: diffusion's, when no pass runs)."""
    if r.what is Why.RUNS:
        return "runs"
    if r.what is Why.DISABLED:
        return "translucency disabled: turn on Enabled in the object's Translucency panel"
    if r.what is Why.OUT_OF_VIEW:
        return ("outside the camera view: nothing to compute (its bounding sphere is outside the "
                "render camera's frustum; it is solved again when the camera sees it)")
    if r.what is Why.UNLIT:
        return unlit_text(*r.detail)
    if r.what is Why.ALL_TURNED_OFF:
        return ("every pass is turned off in the object's settings: turn Multiple Scattering (or Single "
                "Scattering, once baked) back on in its Translucency panel")
    if r.what is Why.NO_LIGHT_RETURNED:
        if r.note != "not baked":
            hint = ("a material with a higher reduced albedo (sigma_s' / (sigma_a + sigma_s')) above "
                    f"{ALBEDO_MIN} returns light by diffusion")
            return "no pass returns light (" + "; ".join(multiple_reasons) + "). " + hint[0].upper() + hint[1:]
        return ("no pass returns light (" + "; ".join(multiple_reasons) + "; single scattering is not baked). "
                + SS_HINT + " to render the light these channels scatter once")
    raise ValueError(f"no words for a plan's reason {r.what}")


def _fluid_validity(plan) -> str:
    """"diffusion valid", or where it is doubtful, for the channels that run (the fluid's first line)."""
    running = [c for c in range(3) if plan.multiple.channels[c]]
    if not running:
        return "diffusion off"
    doubtful = [c for c in running if plan.facts.get("invalid_fraction", (0.0,) * 3)[c] > 0.0]
    if not doubtful:
        return "diffusion valid"
    return "diffusion doubtful in " + "".join(CHANNELS[c] for c in doubtful) + " (see below)"


def describe_plan(plan) -> str:
    """Multi-line, user-facing description (CLI and panel)."""
    if not plan.run:
        lines = [f"{plan.object_name}: skipped -- {plan.reason}"]
    else:
        lines = [f"{plan.object_name}: runs (estimated {plan.estimated_ms:,.0f} ms per frame)"]
    if "particles" in plan.facts:
        lines.insert(1, f"  fluid: {plan.facts['particles']:,} particles" + (
            f", {_fluid_validity(plan)}" if plan.multiple is not None else ""))
    for label, p in (("multiple scattering", plan.multiple), ("single scattering", plan.single),
                     ("Voxel Number Map", plan.voxel_number_map)):
        if p is None:
            continue
        on = "".join(ch if run else "-" for ch, run in zip(CHANNELS, p.channels))
        extra = ""
        if p.name == "multiple" and any(p.split):
            extra = " + closed-form single scattering [" + "".join(
                ch if run else "-" for ch, run in zip(CHANNELS, p.split)) + "]"
        lines.append(f"  {label} [{on}]{extra}{' (forced)' if p.forced else ''}")
        for r in p.reasons:
            lines.append(f"    {r}")
    for a in plan.advice:
        lines.append(f"  better: {a}")
    return "\n".join(lines)
