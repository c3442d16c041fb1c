"""How to run a fit (:class:`FitConfig`): which classes, the split, the seed, the workers, and the
recipe that overrides the plan the policy resolves for the build (:mod:`.policy`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from ..settings import CLASSES
from .policy import measured_with


@dataclass(frozen=True)
class FitConfig:
    """A fit's run options; everything else the fit does is its plan. Validated on construction
    (the recipe against the plan's fields: :class:`~.plan.PlanError`)."""

    classes: tuple[str, ...] = CLASSES  #: the classes to fit (the others are kept from ``init``)
    seed: int = 0  #: seed of the train/held-out split, of the ramp-condition subsample and of CMA-ES
    holdout: bool = True  #: False: every trial trains (no held-out half)
    #: overrides of the resolved plan, nested as its JSON (``{"classes": {"PC": {"highpass_hz": null}}}``)
    recipe: Mapping[str, Any] = field(default_factory=dict)
    workers: int | None = None  #: local worker processes (None: all cores, at most the population)
    progress: bool = True  #: progress bars on stderr

    def __post_init__(self) -> None:
        bad = [c for c in self.classes if c not in CLASSES]
        if bad or not self.classes:
            raise ValueError(f"classes must be a non-empty subset of {list(CLASSES)}, got {list(self.classes)}")
        object.__setattr__(self, "classes", tuple(c for c in CLASSES if c in self.classes))  # in the classes' order
        if self.workers is not None and self.workers < 1:
            raise ValueError("workers must be >= 1")
        measured_with(self.classes, self.recipe)  # a recipe that does not validate fails here, before any data is read
