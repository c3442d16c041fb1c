"""A fit's plan: every setting of a fit as data, per class (:class:`FitPlan`).

The policy (:mod:`.policy`) resolves a plan from a build's profile; a recipe overrides any field of
it (:meth:`FitPlan.overridden`, validated: an unknown field or class is refused); the fit runs it and
records it in the parameter file's provenance. Nothing in a plan means "choose later": every value
is the one the fit uses. Its JSON form (:meth:`FitPlan.model_dump`) is what a recipe file overrides.

State keys: the fit evaluates a class's search under the class's name and its refinement under
``"<class>:refine"`` (:func:`stage_key`); :meth:`FitPlan.objective_of` and the search read a stage's
settings by that key.
"""

from __future__ import annotations

import typing
from typing import Annotated, Any, Mapping

from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError, field_validator

from ..params import HIGHPASS_RANGE_HZ, WINDOW_RANGE_MS, GateCalibration
from ..settings import CLASSES
from .objective import ObjectiveConfig
from .space import LOG_ISAT_RANGE

MAX_RESTARTS = 8  #: IPOP restarts a class may have (each doubles the population)
REFINE_SUFFIX = ":refine"  #: a refinement's key beside its class's in a fit's state (``"PC:refine"``)


class PlanError(ValueError):
    """A plan or its overrides do not validate; the message names every bad field."""


def stage_key(cls: str, refinement: bool) -> str:
    """The state key of class ``cls``'s search (the class) or of its refinement (``"PC:refine"``)."""
    return cls + REFINE_SUFFIX if refinement else cls


def parse_stage_key(key: str) -> tuple[str, bool]:
    """(class, whether the key is its refinement's) of a state key."""
    return (key[: -len(REFINE_SUFFIX)], True) if key.endswith(REFINE_SUFFIX) else (key, False)


class _Plan(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class RefinePlan(_Plan):
    """A class's refinement: a second CMA-ES run of the same budget from its search's best point, on
    an objective of its own (whole-trial counts)."""

    count_weight: float = Field(ge=0.0, description="K: multiplier of the relative count loss L_rel in the refinement's objective")
    sine_count_weight: float | None = Field(
        None, ge=0.0, description="a sine condition's weight, in ramp conditions, in the count terms alone (1: the plain mean "
        "over conditions the held-out report takes); null: the plan's sine_weight, as in the distance")
    count_margin: float = Field(0.0, ge=0.0, lt=1.0, description="a relative count error up to this costs nothing: "
                                "K max(L_rel - margin, 0), so the distance alone decides within it")
    vr_distance: StrictBool = Field(False, description="score the distance by the VR-normalised distance (the held-out "
                                    "report's inter/intra ratio per condition, at the objective's kernel) instead of the paper's")


class ClassPlan(_Plan):
    """How one afferent class is fitted: its window, its search space, its search and its refinement."""

    window_ms: float = Field(ge=WINDOW_RANGE_MS[0], le=WINDOW_RANGE_MS[1], description="causal PVDF window (ms) the class is fitted at, and runs at")
    input_stage: StrictBool = Field(False, description="fit the class input stage: low-pass cutoff (Hz) and negative-part lead (ms)")
    pvdf: StrictBool = Field(True, description="read the PVDF channels; false: the PVDF and dPVDF weights (w5..w8) are held at 0")
    excitatory: StrictBool = Field(False, description="hold the film's weights (w5, w6: both polarities of PVDF) >= 0, so "
                                   "pressing and releasing both excite the class")
    segmented_count: StrictBool = Field(False, description="the search's ramp count loss is summed over the ramp's "
                                        "turning-point windows instead of taken over the whole trial")
    highpass_hz: float | None = Field(None, ge=HIGHPASS_RANGE_HZ[0], le=HIGHPASS_RANGE_HZ[1],
                                      description="cutoff (Hz) of the class input's 1st-order high-pass, held fixed (not searched); null: none")
    restarts: int = Field(0, ge=0, le=MAX_RESTARTS, description="IPOP restarts (same start, own seed, population x2, "
                          "generations /2) beside the first run, in the search and in the refinement")
    saturated_starts: tuple[Annotated[float, Field(ge=LOG_ISAT_RANGE[0], le=LOG_ISAT_RANGE[1])], ...] = Field(
        (), description="input saturations (log i_sat) the search also starts from, each with a CMA-ES run of its own")
    refine: RefinePlan | None = Field(None, description="the refinement after the search; null: the paper's single search")


class FitPlan(_Plan):
    """Every setting of a fit: the settings shared by its classes, and one :class:`ClassPlan` per
    fitted class (in ``classes``)."""

    window_ms: float = Field(128.0, ge=WINDOW_RANGE_MS[0], le=WINDOW_RANGE_MS[1],
                             description="the parameter file's preprocessing window (ms); a class at another window gets its own")
    max_ramp_conditions: int | None = Field(None, ge=1, description="train on a seeded subsample of this many ramp conditions; null: all")
    gate_factor: float = Field(GateCalibration.model_fields["factor"].default, gt=0.0, le=100.0,
                               description="the PVDF spectral gate keeps bins above this multiple of the noise calibrated on the baselines")
    kernel_ms: float = Field(10.0, gt=0.0, description="time constant (ms) of the objective's exponential kernel (eqs. 2-3)")
    sine_weight: float = Field(30.0, gt=0.0, description="weight of one sine condition relative to one ramp condition (paper: 1)")
    count_weight: float = Field(1.0, ge=0.0, description="multiplier of L_rel in the search's objective (paper: 1)")
    max_refs_per_condition: int = Field(80, ge=1, description="reference trains kept per condition (whole repeats)")
    popsize: int = Field(12, ge=4, description="CMA-ES population of a first run")
    generations: int = Field(250, ge=1, description="CMA-ES generations of a first run")
    classes: dict[str, ClassPlan] = Field(description="the fitted classes' plans")

    @field_validator("classes")
    @classmethod
    def _known_classes(cls, v: dict[str, ClassPlan]) -> dict[str, ClassPlan]:
        unknown = [c for c in v if c not in CLASSES]
        if unknown or not v:
            raise ValueError(f"expected a non-empty subset of {', '.join(CLASSES)}, got {', '.join(v) or 'none'}")
        return {c: v[c] for c in CLASSES if c in v}

    def window_of(self, cls: str) -> float:
        """Causal PVDF window (ms) class ``cls`` is fitted at."""
        return self.classes[cls].window_ms

    def refined(self) -> tuple[str, ...]:
        """The classes refined after their search."""
        return tuple(c for c, p in self.classes.items() if p.refine is not None)

    def objective_of(self, key: str) -> ObjectiveConfig:
        """The objective of a class's search (``key`` = the class) or of its refinement (its
        :func:`stage_key`): the paper's constants, the plan's kernel, the stage's count weight and margin."""
        cls, refinement = parse_stage_key(key)
        weight, margin = self.count_weight, 0.0
        if refinement:
            refine = self.classes[cls].refine
            if refine is None:
                raise KeyError(f"{cls} is not refined in this plan")
            weight, margin = refine.count_weight, refine.count_margin
        return ObjectiveConfig(kernel_tau_s=self.kernel_ms / 1000.0, count_weight=float(weight), count_margin=float(margin))

    def overridden(self, overrides: Mapping[str, Any]) -> FitPlan:
        """This plan with ``overrides`` (nested like :meth:`model_dump`: ``{"gate_factor": 2.5,
        "classes": {"PC": {"refine": {"count_margin": 0.1}}}}``) merged in, validated. Raises
        :class:`PlanError` naming every bad field: unknown fields, classes this plan does not fit,
        values out of range."""
        if not isinstance(overrides, Mapping):
            raise PlanError(f"expected an object of plan fields, got {type(overrides).__name__}")
        given = overrides.get("classes", {})
        if not isinstance(given, Mapping):
            raise PlanError("classes: expected an object with one entry per class")
        absent = [c for c in given if c not in self.classes]
        if absent:
            raise PlanError("; ".join(f"classes.{c}: " + (f"{c} is not fitted (fitted: {', '.join(self.classes)})" if c in CLASSES
                                                          else f"unknown class (expected one of {', '.join(CLASSES)})") for c in absent))
        try:
            return FitPlan.model_validate(merged(self.model_dump(), overrides))
        except ValidationError as exc:
            raise PlanError("; ".join(_error_text(e) for e in exc.errors())) from None


def merged(base: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``overrides`` merged in, object by object (a value that is not an object replaces)."""
    out = dict(base)
    for k, v in overrides.items():
        out[k] = merged(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def leaves(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Every value of a nested mapping that is not itself a mapping, by dotted path (``"classes.PC.highpass_hz"``)."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        path = f"{prefix}{k}"
        out.update(leaves(v, path + ".") if isinstance(v, Mapping) and v else {path: v})
    return out


def nested(paths: Mapping[str, Any]) -> dict[str, Any]:
    """The nested mapping of values given by dotted path (the inverse of :func:`leaves`)."""
    out: dict[str, Any] = {}
    for path, v in paths.items():
        *parents, last = path.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = v
    return out


def _error_text(e: Mapping[str, Any]) -> str:
    loc = ".".join(str(p) for p in e["loc"])
    if e["type"] == "extra_forbidden":
        return f"{loc}: unknown field (fields there: {', '.join(_fields_at(e['loc'][:-1]))})"
    return f"{loc}: {e['msg']}"


def _fields_at(loc: tuple) -> list[str]:
    """The field names of the plan model at ``loc`` (a path of field names and class keys)."""
    model: Any = FitPlan
    for part in loc:
        ann = model.model_fields[part].annotation if isinstance(part, str) and part in model.model_fields else None
        if ann is None:  # a class key of ``classes``
            continue
        if typing.get_origin(ann) is dict:
            ann = typing.get_args(ann)[1]
        model = next((a for a in (ann, *typing.get_args(ann)) if isinstance(a, type) and issubclass(a, BaseModel)), model)
    return list(model.model_fields)
