"""The fit's policy: the default plan, and the rules that change it for a build (one table,
:data:`RULES`), resolved into the plan a fit runs (:func:`resolve`).

A rule is a condition on the build's profile (:class:`~.profile.BuildProfile`), the plan fields it
sets (dotted paths into the plan: ``"classes.PC.highpass_hz"``) and the reason, measured on the
builds of docs/fitting.md. Two rules that set the same field have conditions no profile meets at
once (checked when the table is built), so no rule silently beats another. Fields the profile is
measured with (:data:`MEASURED_WITH`) are set by the defaults and the recipe alone.

Resolution: the defaults (:func:`default_plan`), then every rule whose condition the profile meets
(a field of a class not fitted is skipped), then the recipe's overrides.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field
from typing import Any, Callable, Literal, Mapping, Sequence

from ..params import default_params
from ..settings import CLASSES
from .plan import ClassPlan, FitPlan, leaves, nested
from .profile import MEASURES, BuildProfile

Op = Literal["<", "<=", ">", ">="]
_OPS: dict[str, Callable[[float, float], bool]] = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge}

#: plan fields the profile is measured with (the preprocessing window, the trials): no rule may set them
MEASURED_WITH = ("window_ms", "max_ramp_conditions")


@dataclass(frozen=True)
class Bound:
    """``measure op value``: a bound on one measure of the profile (``value`` in the measure's unit:
    the SNR as a ratio, the noise in N)."""

    measure: str
    op: Op
    value: float

    def holds(self, profile: BuildProfile) -> bool:
        """Whether the profile's measure meets the bound (never when it was not measured)."""
        x = getattr(profile, self.measure)
        return x is not None and _OPS[self.op](x, self.value)

    def interval(self) -> tuple[float, bool, float, bool]:
        """(low, low included, high, high included) of the values that meet the bound."""
        if self.op in ("<", "<="):
            return -math.inf, False, self.value, self.op == "<="
        return self.value, self.op == ">=", math.inf, False


@dataclass(frozen=True)
class Rule:
    """A row of the policy: when the profile meets every bound of ``when``, the plan fields of
    ``sets`` (dotted paths) get their values, because of ``why``."""

    name: str
    when: tuple[Bound, ...]
    sets: Mapping[str, Any]
    why: str

    def applies(self, profile: BuildProfile) -> bool:
        """Whether the profile meets every bound of the rule's condition."""
        return all(b.holds(profile) for b in self.when)

    def condition(self) -> str:
        """The condition as text, a measure's bounds together: ``"35 <= contact SNR < 50"``."""
        parts = []
        for measure in dict.fromkeys(b.measure for b in self.when):
            label, scale, unit = MEASURES[measure]
            bounds = [b for b in self.when if b.measure == measure]
            lows = [b for b in bounds if b.op in (">", ">=")]
            highs = [b for b in bounds if b.op in ("<", "<=")]
            if len(lows) == len(highs) == 1:  # a band: low <= measure < high
                flip = {">": "<", ">=": "<="}[lows[0].op]
                parts.append(f"{lows[0].value * scale:g}{unit} {flip} {label} {highs[0].op} {highs[0].value * scale:g}{unit}")
            else:
                parts.append(" and ".join(f"{label} {b.op} {b.value * scale:g}{unit}" for b in bounds))
        return " and ".join(parts)


def _exclusive(a: Rule, b: Rule) -> bool:
    """Whether no profile meets both rules' conditions (some measure's bounds leave no value)."""
    bounds = (*a.when, *b.when)
    for measure in {x.measure for x in bounds}:
        lo, lo_in, hi, hi_in = -math.inf, False, math.inf, False
        for low, low_in, high, high_in in (x.interval() for x in bounds if x.measure == measure):
            if (low, not low_in) > (lo, not lo_in):  # a higher low, or the same one excluded
                lo, lo_in = low, low_in
            if (high, high_in) < (hi, hi_in):  # a lower high, or the same one excluded
                hi, hi_in = high, high_in
        if lo > hi or (lo == hi and not (lo_in and hi_in)):
            return True
    return False


def checked(rules: Sequence[Rule]) -> tuple[Rule, ...]:
    """The rules, after checking that they form a policy: known measures, no field the profile is
    measured with, and no field set by two rules that can apply together."""
    for r in rules:
        unknown = [b.measure for b in r.when if b.measure not in MEASURES]
        if unknown or not r.when:
            raise ValueError(f"rule {r.name!r}: a condition on the profile's measures ({', '.join(MEASURES)}) is needed, got {unknown}")
        bad = [p for p in r.sets if p in MEASURED_WITH]
        if bad:
            raise ValueError(f"rule {r.name!r} sets {bad}, which the profile is measured with")
    for i, a in enumerate(rules):
        for b in rules[i + 1 :]:
            common = sorted(set(a.sets) & set(b.sets))
            if common and not _exclusive(a, b):
                raise ValueError(f"rules {a.name!r} and {b.name!r} both set {common} and can apply together")
    return tuple(rules)


# --------------------------------------------------------------------------------------- defaults

#: every class's plan that differs from :class:`~.plan.ClassPlan`'s defaults, the window aside (the
#: shipped one): RA and PC fit their input stage (TouchSim low-passes its input per model; without it
#: RA cannot peak at 100 Hz); RA's film weights are held >= 0 (every TouchSim RA model fires on
#: pressing and on releasing); PC's search counts per turning point (TouchSim's PC fires about one
#: spike per turning point); RA and PC are refined (RA's count and PC's VR ratio are the targets
#: other builds miss first), PC on the VR-normalised distance
CLASS_DEFAULTS: Mapping[str, Mapping[str, Any]] = {
    "SA1": {},
    "RA": {"input_stage": True, "excitatory": True, "refine": {"count_weight": 3.0}},
    "PC": {"input_stage": True, "segmented_count": True, "refine": {"count_weight": 5.0, "vr_distance": True}},
}


def shipped_windows_ms() -> dict[str, float]:
    """Per class, the causal PVDF window (ms) it runs at in the shipped defaults (SA1 and RA on the
    16 ms fast path, PC on 128 ms): the windows a fit uses unless told otherwise."""
    p = default_params()
    return {c: p.window_ms(c) for c in CLASSES if c in p.classes}


def default_plan(classes: Sequence[str]) -> FitPlan:
    """The plan of a fit of ``classes`` before any rule: :class:`~.plan.FitPlan`'s defaults, each
    class at its shipped window with :data:`CLASS_DEFAULTS`."""
    base = FitPlan.model_fields["window_ms"].default
    windows = shipped_windows_ms()
    return FitPlan(classes={c: ClassPlan(window_ms=windows.get(c, base), **CLASS_DEFAULTS[c]) for c in classes})


# ------------------------------------------------------------------------------------------ rules

#: the rules, one per kind of build the defaults do not fit (docs/fitting.md, "Across sensor builds")
RULES: tuple[Rule, ...] = checked((
    Rule(
        name="weak-signal",
        when=(Bound("contact_snr", ">=", 35.0), Bound("contact_snr", "<", 50.0)),
        sets={"gate_factor": 2.0, "classes.PC.refine.sine_count_weight": 10.0},
        why="at 3 x the noise the gate removes PC's weak ramp transients, and PC's refinement then trades its ramp counts "
        "for the 10 Hz sine (noisy-amplifier, SNR 37: PC count error 41.9 % -> 23.1 %); on the strong-signal builds these "
        "settings cost RA's count and PC's VR ratio",
    ),
    Rule(
        name="film-limited",
        when=(Bound("contact_snr", "<", 35.0),),
        sets={"gate_factor": 2.0, "classes.PC.highpass_hz": 5.0, "classes.PC.refine.count_margin": 0.22,
              "classes.PC.refine.sine_count_weight": 1.0},
        why="the PVDF amplifier's slow baseline wander passes the gate and shifts the film's level against PC's threshold from "
        "trial to trial; the high-pass removes it, and within the count margin (counted as the report counts) PC's VR "
        "distance alone decides (corner build, SNR 19: PC 39.4 % / 1.46 -> 21.7 % / 1.49)",
    ),
    Rule(
        name="noisy-singletact",
        when=(Bound("st_noise_n", ">", 0.0065),),
        sets={"classes.SA1.restarts": 1, "classes.SA1.saturated_starts": (-2.0,)},
        why="SA1's optimum depends on the run: its drive grows with the force faster than TouchSim's count, and from the "
        "mild start CMA-ES seldom reaches the saturated SA1 that follows TouchSim (3x-noisy SingleTact: SA1 count error "
        "16.5 % -> 8.3 %); on a quiet SingleTact neither run won, and they cost about 3 min",
    ),
))


# ------------------------------------------------------------------------------------- resolution


@dataclass(frozen=True)
class Resolution:
    """A resolved plan, with what it was resolved from: the profile, the rules that applied, the
    recipe, and per plan field (dotted path) what set it (``origins``; a field absent: the default)."""

    profile: BuildProfile
    plan: FitPlan
    rules: tuple[Rule, ...]
    recipe: Mapping[str, Any] = field(default_factory=dict)
    origins: Mapping[str, str] = field(default_factory=dict)


def resolve(profile: BuildProfile, classes: Sequence[str], recipe: Mapping[str, Any] | None = None,
            rules: Sequence[Rule] = RULES) -> Resolution:
    """The plan of a fit of ``classes`` on a build of ``profile``: the defaults, the ``rules`` the
    profile meets, then ``recipe`` (plan overrides, validated: :meth:`~.plan.FitPlan.overridden`)."""
    plan = default_plan(classes)
    present = leaves(plan.model_dump())
    applied = tuple(r for r in rules if r.applies(profile))
    sets = {p: (v, r.name) for r in applied for p, v in r.sets.items() if p in present}  # a class not fitted: skipped
    plan = plan.overridden(nested({p: v for p, (v, _) in sets.items()}))
    origins = {p: f"rule {name}" for p, (_, name) in sets.items()}
    recipe = dict(recipe or {})
    plan = plan.overridden(recipe)
    origins.update({p: "recipe" for p in leaves(recipe)})
    return Resolution(profile, plan, applied, recipe, origins)


def measured_with(classes: Sequence[str], recipe: Mapping[str, Any] | None = None) -> FitPlan:
    """The plan as far as the profile's measurement needs it (:data:`MEASURED_WITH`: no rule sets
    those fields), resolved without a profile."""
    return resolve(BuildProfile(), classes, recipe).plan
