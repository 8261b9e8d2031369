"""The planner's rules: one small decision per pass, its reasons as data (no text here).

Each rule reads the object's facts (:class:`ObjectFacts`, measured once per
object and frame by :func:`measure`) and returns a :class:`Decision`: the
channels that run, where (per-node weights) and, per channel, a
:class:`Reason` -- what the rule found, the measured value and the threshold
it was compared with.  The words are made from the reasons in
:mod:`.planner_messages`; :mod:`.planner` assembles the plan.  The physics
behind each threshold (and what the path tracer measured) is in
:mod:`.planner`'s docstring.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from .scene.materials import reduced_albedo
from .diffusion.split import half_space_split, semi_infinite_albedo

ALBEDO_MIN = 0.5  # diffusion needs on average one scattering event before absorption (reduced albedo)
# From ALBEDO_MIN to ALBEDO_FULL diffusion is blended with the pass that replaces it below ALBEDO_MIN, its weight
# rising linearly from 0 to 1 (:func:`diffusion_weight`): on a 10 mm sphere (eta 1.3) against a random walk,
# diffusion alone is +7.9 % at 0.51, +5.5 % at 0.55 and +2.7 % at 0.6, single scattering with the orders after
# the first -3.6 % at 0.49 (docs/accuracy.md); the blend makes the frame continuous across ALBEDO_MIN.
ALBEDO_FULL = 0.6
THICK_MIN = 1.0  # ... and a local thickness of at least one transport mean free path
NEGLIGIBLE = 0.01  # a pass whose estimate is below 1 % of the brightest estimate is not run
# The quantities the rules measure (Measure.quantity)
ALBEDO = "reduced albedo"
THICKNESS = "optical thickness"  # in transport mean free paths
SHARE = "share of the brightest channel"
VALID_SHARE = "valid share of the surface"
SS_SHARE = "single scattering's share of the peak"
MS_SHARE = "multiple scattering's share of the peak"


class Why(Enum):
    """What a rule found, per channel (a pass's reasons) or for the whole object (the plan's)."""

    # diffusion (multiple scattering)
    VALID = "valid"
    VALID_IN_REGION = "valid in a region; replaced elsewhere"
    VALID_BLENDED = "valid; blended with its replacement near its albedo limit"
    DOUBTFUL_IN_REGION = "doubtful in a region; runs there too"
    DOUBTFUL_EVERYWHERE = "doubtful everywhere; runs (no other pass)"
    INVALID = "invalid; replaced"
    INVALID_NEGLIGIBLE = "invalid and negligible"
    INVALID_REST_NEGLIGIBLE = "invalid in a region, negligible in the rest; replaced everywhere"
    NEGLIGIBLE = "negligible"
    # single scattering where diffusion runs (the first-scatter split)
    SPLIT = "contained in diffusion, split off"
    CONTAINED_SPLIT_OFF = "contained in diffusion, the split turned off"
    CONTAINED_NOT_SPLIT = "contained in diffusion, the split negligible"
    # the pass that replaces diffusion (single scattering or the Voxel Number Map)
    REPLACES = "replaces diffusion"
    REPLACES_IN_REGION = "replaces diffusion in a region"
    BLENDS = "blended with diffusion near its albedo limit"
    NOT_BAKED = "not baked"
    TURNED_OFF = "turned off"
    MAP_REPLACES_IT = "the Voxel Number Map replaces single scattering"
    SINGLE_REPLACES_HERE = "single scattering replaces diffusion, not the map"
    NOTHING_TO_REPLACE = "nothing to replace"
    FORCED = "forced by an override"
    # the whole object (Plan.reason)
    RUNS = "runs"
    DISABLED = "translucency disabled"
    OUT_OF_VIEW = "outside the camera view"
    UNLIT = "no light reaches it"
    ALL_TURNED_OFF = "every pass turned off"
    NO_LIGHT_RETURNED = "no pass returns light"


@dataclass(frozen=True)
class Measure:
    """One number a rule compared: ``quantity`` (e.g. "reduced albedo"), its ``value``, the ``threshold``."""

    quantity: str
    value: float
    threshold: float | None = None


@dataclass(frozen=True)
class Region:
    """Where diffusion is invalid in one channel: the share of the surface (area), and which test fails there
    (``thin_share``: the share thinner than ``thinner_than_mm`` = THICK_MIN transport mean free paths;
    ``low_share``: the share whose reduced albedo is below ALBEDO_MIN; ``blend_share``: the share where
    it is valid but below ALBEDO_FULL, blended with the pass that replaces it)."""

    fraction: float
    thin_share: float
    low_share: float
    thinner_than_mm: float
    thick_min: float = THICK_MIN
    albedo_min: float = ALBEDO_MIN
    blend_share: float = 0.0
    albedo_full: float = ALBEDO_FULL


@dataclass(frozen=True)
class Reason:
    """Why one pass runs or not in one channel, as data.

    ``measures``: the numbers the rule compared (:class:`Measure`); ``invalid``: why diffusion is invalid
    over the whole object (the reduced albedo or the thickness, against its threshold); ``region``: where it is
    invalid; ``note``: context that is already words (an override's source, what blocks the split);
    ``parts``: the inner parts ({role: count}); ``stand_in``: the decision was made for the pass that replaces
    diffusion and handed to the Voxel Number Map (its words name the map); ``single_pass``: the object has a
    single-scattering pass at all (a particle fluid has not); ``detail``: more numbers, per ``what``.
    """

    what: Why
    channel: int = -1
    measures: tuple = ()
    invalid: Measure | None = None
    region: Region | None = None
    note: str = ""
    on: bool = False  # FORCED: forced on (True) or off
    parts: dict = field(default_factory=dict)
    stand_in: bool = False
    single_pass: bool = True
    detail: tuple = ()  # UNLIT: planner_facts.unlit_misses (light by light, the world, whether there are lights)

    def value(self, quantity: str) -> float:
        return next(m.value for m in self.measures if m.quantity == quantity)


@dataclass
class Decision:
    """One pass's decision: channels, per-channel :class:`Reason`, the single-scattering bound, the
    per-node weights (None: everywhere), the split's channels (diffusion only) and whether it was forced."""

    channels: tuple
    why: tuple
    bound: tuple = (0.0, 0.0, 0.0)
    weights: np.ndarray | None = None
    split: tuple = (False, False, False)
    forced: bool = False

    @property
    def runs(self) -> bool:
        return any(self.channels)


@dataclass(frozen=True)
class ObjectFacts:
    """What the rules read about one object this frame (per channel; lengths in mm; node arrays (n_surface, 3)).

    ``irradiance`` E: what the lights bring (:func:`.planner.light_reaching`); ``ms_estimate`` = R_ms E
    (``ms_albedo`` R_ms: the semi-infinite albedo, the module docstring's equation); ``ss_estimate`` =
    (1 - ln 2)/2 alpha min(1, sigma_t thin) E; ``brightest``: the larger of both over the channels;
    ``ss_closed_form`` / ``ms_closed_form``: the half-space split's two terms times E, ``peak`` their largest
    sum; ``valid_node``: diffusion's validity per surface node, ``*_fraction`` its area shares;
    ``diffusion_node``: diffusion's weight per node where a replacement can take the rest
    (:func:`diffusion_weight`; 0 where invalid), ``blend_fraction`` the area share where it is between 0 and 1.
    """

    irradiance: np.ndarray
    reduced_albedo: np.ndarray
    transport_mfp_mm: np.ndarray
    optical_thickness: np.ndarray
    ms_albedo: np.ndarray
    ms_estimate: np.ndarray
    ss_estimate: np.ndarray
    brightest: float
    valid_node: np.ndarray
    invalid_fraction: np.ndarray
    thin_fraction: np.ndarray
    low_albedo_fraction: np.ndarray
    ss_closed_form: np.ndarray
    ms_closed_form: np.ndarray
    peak: float
    diffusion_node: np.ndarray
    blend_fraction: np.ndarray

    def as_facts(self) -> dict:
        """The numbers a plan shows (``Plan.facts``), in their order there."""
        return {"reduced_albedo": self.reduced_albedo.tolist(), "optical_thickness": self.optical_thickness.tolist(),
                "ms_albedo": self.ms_albedo.tolist(), "transport_mfp_mm": self.transport_mfp_mm.tolist(),
                "invalid_fraction": self.invalid_fraction.tolist(), "thin_fraction": self.thin_fraction.tolist(),
                "low_albedo_fraction": self.low_albedo_fraction.tolist(), "ms_estimate": self.ms_estimate.tolist(),
                "ss_estimate": self.ss_estimate.tolist(), "ss_closed_form": self.ss_closed_form.tolist(),
                "ms_closed_form": self.ms_closed_form.tolist(), "blend_fraction": self.blend_fraction.tolist()}

    def region(self, c: int, blended: bool = False) -> Region:
        """Where diffusion is invalid in channel c, and (``blended``) where it is blended with its replacement."""
        return Region(float(self.invalid_fraction[c]), float(self.thin_fraction[c]),
                      float(self.low_albedo_fraction[c]), THICK_MIN * self.transport_mfp_mm[c],
                      blend_share=float(self.blend_fraction[c]) if blended else 0.0)


def diffusion_weight(alpha) -> np.ndarray:
    """Diffusion's weight at reduced albedo ``alpha'`` where a pass can replace it: 0 below ALBEDO_MIN, 1 from
    ALBEDO_FULL, linear between; the replacement (with the orders after the first) takes ``1 - weight``.

    Both sides estimate the whole transport, with opposite errors near the threshold (the constant's
    comment), so the weighted sum is continuous in alpha' and closer to transport than either side there.
    """
    return np.clip((np.asarray(alpha, dtype=np.float64) - ALBEDO_MIN) / (ALBEDO_FULL - ALBEDO_MIN), 0.0, 1.0)


def measure(geo: dict, area, eta: float, bulk, surface, E) -> ObjectFacts:
    """The rules' facts from the geometry (``geo``: :func:`.planner.object_thickness`, per-node ``area``), the
    bulk and surface-node coefficients (sigma_a, sigma_s' in 1/mm) and the irradiance E."""
    sa, ss = bulk
    sa_s, ss_s = surface
    st = sa + ss
    alpha = reduced_albedo(sa, ss)
    l_tr = 1.0 / st
    thin = geo["thin_mm"]
    R_ms = semi_infinite_albedo(alpha, eta)
    ms_estimate = R_ms * E
    # Validity per surface node: local thickness in transport mean free paths, local albedo.
    area = area / max(area.sum(), 1e-300)
    tau_node = geo["node_mm"][:, None] * (sa_s + ss_s)
    thin_node = tau_node < THICK_MIN
    alpha_node = reduced_albedo(sa_s, ss_s)
    low_node = alpha_node < ALBEDO_MIN
    valid_node = ~(thin_node | low_node)
    diffusion_node = np.where(valid_node, diffusion_weight(alpha_node), 0.0)
    blend_node = valid_node & (diffusion_node < 1.0)
    everywhere = ~valid_node.any(axis=0)  # exact, not a sum of areas that rounds below 1
    # Single-scattering estimate: a half-space returns (1 - ln 2)/2 alpha = 0.153 alpha of the
    # light once scattered (isotropic phase); a thin part at most its optical thickness' share.
    ss_estimate = 0.5 * (1.0 - np.log(2.0)) * (ss / st) * np.minimum(1.0, st * thin) * E
    split_model = half_space_split(eta)
    ss_cf = split_model.single_escape(ss / st) * E
    ms_cf = split_model.multiple_escape(ss / st) * E
    return ObjectFacts(
        irradiance=E, reduced_albedo=alpha, transport_mfp_mm=l_tr, optical_thickness=thin / l_tr, ms_albedo=R_ms,
        ms_estimate=ms_estimate, ss_estimate=ss_estimate,
        brightest=max(float(np.max(np.maximum(ms_estimate, ss_estimate))), 1e-300), valid_node=valid_node,
        invalid_fraction=np.where(everywhere, 1.0, np.minimum(area @ (~valid_node), 1.0)),
        thin_fraction=np.where(thin_node.all(axis=0), 1.0, area @ thin_node),
        low_albedo_fraction=np.where(low_node.all(axis=0), 1.0, area @ low_node),
        ss_closed_form=ss_cf, ms_closed_form=ms_cf, peak=max(float(np.max(ss_cf + ms_cf)), 1e-300),
        diffusion_node=diffusion_node, blend_fraction=np.minimum(area @ blend_node, 1.0))


def is_lit(E, overrides: dict) -> bool:
    """An object is planned only if some light reaches it (E > 0 in a channel) or a pass is forced on."""
    return bool(np.any(E > 0) or any(overrides.values()))


def skip_object(enabled: bool, in_view: bool) -> Why | None:
    """An object is skipped when its translucency is disabled or it is outside the camera's view."""
    if not enabled:
        return Why.DISABLED
    if not in_view:
        return Why.OUT_OF_VIEW
    return None


# ----------------------------------------------------------------- multiple scattering (diffusion)
@dataclass
class DiffusionDecision(Decision):
    """Diffusion's :class:`Decision`, and what the other passes need from it: the channels in which the
    replacement pass takes over (``replaced``), and the share of the surface per channel where it would be
    more accurate but is not available (``unbaked``: the plan's advice)."""

    replaced: tuple = (False, False, False)
    unbaked: dict = field(default_factory=dict)


def _invalid_measure(f: ObjectFacts, c: int) -> Measure:
    """What makes diffusion invalid over the whole object in channel c: its albedo, or else its thin parts."""
    if f.reduced_albedo[c] < ALBEDO_MIN or f.low_albedo_fraction[c] >= 1.0:
        return Measure(ALBEDO, f.reduced_albedo[c], ALBEDO_MIN)
    return Measure(THICKNESS, f.optical_thickness[c], THICK_MIN)


def decide_diffusion(f: ObjectFacts, ss_available: bool, single_pass: bool = True) -> DiffusionDecision:
    """Diffusion runs in a channel where it is valid and returns light; where it is invalid a replacement
    takes over, but it is never turned off when it is the only pass.

    Valid per surface node: reduced albedo alpha' >= ALBEDO_MIN and local thickness >= THICK_MIN transport mean
    free paths (invalid share p of the surface).  It returns light where R_ms E >= NEGLIGIBLE of the brightest
    estimate.  Per channel: invalid on part of the surface and the valid rest returns < NEGLIGIBLE -> the
    replacement takes all of it; invalid everywhere -> the replacement (if available), else off if negligible,
    else doubtful but running; negligible -> off; invalid on part -> runs on the valid part (the replacement on
    the rest) or everywhere, doubtful; else valid.  Where a replacement is available, diffusion's weight per
    node is :func:`diffusion_weight` (0 where invalid, rising from 0 to 1 between ALBEDO_MIN and ALBEDO_FULL):
    the replacement takes the rest.  ``ss_available``: a pass can replace it; ``single_pass`` False: the object
    has no such pass at all (a particle fluid).
    """
    n_surface = f.valid_node.shape[0]
    channels, why, weights = [], [], np.ones((n_surface, 3))
    replaced = [False, False, False]
    unbaked = {}  # channel -> share of the surface where single scattering would be better, not available
    for c in range(3):
        inv, ms, brightest = f.invalid_fraction[c], f.ms_estimate[c], f.brightest
        negligible = ms < NEGLIGIBLE * brightest
        # where it is valid, diffusion returns too little to be worth a solve: single scattering takes it all
        rest_negligible = (1.0 - inv) * ms < NEGLIGIBLE * brightest
        share = Measure(SHARE, ms / brightest, NEGLIGIBLE)
        if ss_available and 0.0 < inv < 1.0 and rest_negligible and not negligible:
            runs, replaced[c] = False, True
            r = Reason(Why.INVALID_REST_NEGLIGIBLE, c, (Measure(SHARE,
                                                                (1.0 - inv) * ms / brightest, NEGLIGIBLE),),
                       region=f.region(c))
        elif inv >= 1.0:
            if ss_available:
                runs, replaced[c] = False, True
                r = Reason(Why.INVALID, c, invalid=_invalid_measure(f, c))
            elif negligible:
                runs, unbaked[c] = False, 1.0
                r = Reason(Why.INVALID_NEGLIGIBLE, c, (share,), invalid=_invalid_measure(f, c))
            else:
                runs, unbaked[c] = True, 1.0
                r = Reason(Why.DOUBTFUL_EVERYWHERE, c, invalid=_invalid_measure(f, c), single_pass=single_pass)
        elif negligible:
            runs, r = False, Reason(Why.NEGLIGIBLE, c, (share,))
        elif inv > 0.0:
            runs = True
            if ss_available:
                weights[:, c] = f.diffusion_node[:, c]
                replaced[c] = True
                r = Reason(Why.VALID_IN_REGION, c, (Measure(VALID_SHARE, 1.0 - inv),),
                           region=f.region(c, blended=True))
            else:
                r = Reason(Why.DOUBTFUL_IN_REGION, c, region=f.region(c))
                unbaked[c] = float(inv)
        elif f.blend_fraction[c] > 0.0 and ss_available:
            runs, replaced[c] = True, True
            weights[:, c] = f.diffusion_node[:, c]
            r = Reason(Why.VALID_BLENDED, c, (Measure(ALBEDO, f.reduced_albedo[c], ALBEDO_FULL),),
                       region=f.region(c, blended=True))
        else:
            runs = True
            r = Reason(Why.VALID, c, (Measure(ALBEDO, f.reduced_albedo[c], ALBEDO_MIN),
                                      Measure(THICKNESS, f.optical_thickness[c], THICK_MIN)))
            if f.blend_fraction[c] > 0.0:  # near its albedo limit, without the pass it would be blended with
                unbaked[c] = float(f.blend_fraction[c])
        channels.append(runs)
        why.append(r)
    return DiffusionDecision(tuple(channels), tuple(why), weights=None if np.all(weights == 1.0) else weights,
                             replaced=tuple(replaced), unbaked=unbaked)


def decide_split(f: ObjectFacts, diffusion: Decision, split_on: bool) -> tuple:
    """The first-scatter split runs in a channel where diffusion runs and its closed-form single scattering
    brings at least NEGLIGIBLE of the object's peak: s(alpha) E >= NEGLIGIBLE max_c (s + M)(alpha) E (the
    half-space's once-scattered and multiply-scattered returns, :func:`.diffusion.split.
    half_space_split`).  ``split_on``: not turned off, and the object has single scattering at all."""
    return tuple(bool(split_on and diffusion.channels[c] and f.ss_closed_form[c] >= NEGLIGIBLE * f.peak)
                 for c in range(3))


def split_reason(f: ObjectFacts, c: int, split: tuple, split_on: bool) -> Reason:
    """Single scattering where diffusion runs is contained in it: what the split does with it in channel c."""
    shares = (Measure(SS_SHARE, f.ss_closed_form[c] / f.peak, NEGLIGIBLE),
              Measure(MS_SHARE, f.ms_closed_form[c] / f.peak))
    if split[c]:
        return Reason(Why.SPLIT, c, shares)
    if not split_on:
        return Reason(Why.CONTAINED_SPLIT_OFF, c)
    return Reason(Why.CONTAINED_NOT_SPLIT, c, shares[:1])


# ----------------------------------------------------------------- single scattering (the replacement)
def decide_single(f: ObjectFacts, diffusion: DiffusionDecision, has_pass: bool, ss_available: bool,
                  split_on: bool) -> Decision:
    """The pass that replaces diffusion runs in a channel only where diffusion is replaced, and only if it
    returns light: (1 - ln 2)/2 alpha min(1, sigma_t thin) E >= NEGLIGIBLE of the brightest estimate (it is
    contained in diffusion where diffusion runs: counted twice, 7.5 % off on the path-traced marble sphere).
    Where diffusion still runs on part of the surface it covers the rest only (weights = 1 - diffusion's:
    1 on invalid nodes, between 0 and 1 where the two are blended near diffusion's albedo limit).
    ``has_pass``: it is baked (single scattering or the map); ``ss_available``: and not turned off."""
    n_surface = f.valid_node.shape[0]
    channels, why, bound, weights = [], [], [], np.zeros((n_surface, 3))
    ms_ch, replaced = diffusion.channels, diffusion.replaced
    for c in range(3):
        bound.append(float(f.ss_estimate[c] / max(f.ms_estimate[c], 1e-300)) if ms_ch[c] else 0.0)
        contained = split_reason(f, c, diffusion.split, split_on)
        runs = False
        if not has_pass:
            r = contained if ms_ch[c] and not replaced[c] and split_on else Reason(Why.NOT_BAKED, c)
        elif not ss_available:
            r = contained if ms_ch[c] and split_on else Reason(Why.TURNED_OFF, c)
        elif ms_ch[c] and not replaced[c]:
            r = contained
        elif f.ss_estimate[c] < NEGLIGIBLE * f.brightest:
            r = Reason(Why.NEGLIGIBLE, c, (Measure(SHARE, f.ss_estimate[c] / f.brightest,
                                                   NEGLIGIBLE),))
        elif ms_ch[c]:
            runs = True
            weights[:, c] = 1.0 - f.diffusion_node[:, c]
            r = Reason(Why.REPLACES_IN_REGION if f.invalid_fraction[c] > 0.0 else Why.BLENDS, c,
                       region=f.region(c, blended=True))
        else:
            runs = True
            weights[:, c] = 1.0
            r = Reason(Why.REPLACES, c)
        channels.append(runs)
        why.append(r)
    everywhere = all(np.all(weights[:, c] == 1.0) for c in range(3) if channels[c])
    return Decision(tuple(channels), tuple(why), tuple(bound), weights=None if everywhere else weights)


# ----------------------------------------------------------------- objects with inner parts
def replacement_pass(ss_available: bool, vnm_available: bool, parts: dict, ss_knows_parts: bool = False):
    """Which pass replaces diffusion where it is invalid: ``"voxel_number_map"``, ``"single"`` or None.

    Measured on the paper's scenes against Mitsuba's scattered light
    (docs/accuracy.md, "Objects with inner parts"): single scattering baked
    with the inner parts (``voxelise_composite``) is the more accurate of the
    two everywhere (8 points of relative RMS on the cubes and on the bottle;
    both miss what they do not model: multiple scattering and the light the
    boundary reflects back inside), the Voxel Number Map about 2x faster per
    frame.  So: single scattering when it is baked and knows the parts (or
    there are none); otherwise the Voxel Number Map, whose chords cross
    cavities, inner media and opaque parts as they are; single scattering
    that does not know the parts only when there is no map.
    """
    if ss_available and (not parts or ss_knows_parts):
        return "single"
    if vnm_available:
        return "voxel_number_map"
    if ss_available:
        return "single"
    return None


def hand_over(single: Decision, replacement, baked_ss: bool, ss_on: bool, baked_vnm: bool, vnm_on: bool,
              parts: dict) -> tuple[Decision, Decision]:
    """(single scattering, Voxel Number Map): the replacement's decision (:func:`decide_single`) goes to the pass
    :func:`replacement_pass` chose; the other says why not (not baked, turned off, or the other replaces)."""
    if replacement == "voxel_number_map":
        vnm = Decision(single.channels, tuple(replace(r, stand_in=True) for r in single.why), single.bound,
                       weights=single.weights)
        if not baked_ss:
            why = Why.NOT_BAKED
        elif not ss_on:
            why = Why.TURNED_OFF
        else:
            why = Why.MAP_REPLACES_IT
        return Decision((False,) * 3, tuple(Reason(why, c, parts=parts) for c in range(3))), vnm
    if not baked_vnm:
        why = Why.NOT_BAKED
    elif not vnm_on:
        why = Why.TURNED_OFF
    elif replacement == "single":
        why = Why.SINGLE_REPLACES_HERE
    else:
        why = Why.NOTHING_TO_REPLACE
    if replacement is None or not baked_ss and replacement != "single":
        single = Decision((False,) * 3, tuple(Reason(Why.NOT_BAKED if not baked_ss else Why.TURNED_OFF, c)
                                              for c in range(3)))
    return single, Decision((False,) * 3, tuple(Reason(why, c, parts=parts) for c in range(3)))


# ----------------------------------------------------------------- overrides, and when nothing runs
def force(decision: Decision, on: bool, note: str) -> None:
    """An override forces a pass on or off in every channel, everywhere (``note``: what forced it)."""
    decision.channels = (bool(on),) * 3
    decision.why = tuple(Reason(Why.FORCED, c, note=note, on=bool(on)) for c in range(3))
    decision.forced = True
    decision.weights = None


def nothing_runs(multiple: Decision, single: Decision | None, ss_available: bool) -> Reason:
    """Why no pass runs: every pass turned off by the user, or none returns light (``note``: "not baked" when
    single scattering could have rendered what diffusion cannot)."""
    if multiple.forced and not any(multiple.channels) and (single is None or single.forced or not ss_available):
        return Reason(Why.ALL_TURNED_OFF)
    return Reason(Why.NO_LIGHT_RETURNED, note="" if ss_available or single is None else "not baked")
