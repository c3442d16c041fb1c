"""A population resolved for a skin and a parameter set, and its stateful encoder.

:class:`Population` holds the layout (:mod:`.layout`), each afferent's model variant (its
class's fitted parameters with the variant's input gain, :mod:`touchreal.fitting.variants`) and the spatial
rule resolved for its afferents (:mod:`.spatial`). :class:`PopulationEncoder` is the
:class:`~touchreal.encoding.encoder.Encoder` whose units are afferents: each block of taxel
channels is mixed into the active afferents' inputs, then runs the same fused input stage and
LIF kernel, one column per afferent. Only the active afferents are mixed and run; the taxels' loads
are localised for all of them at once (every 5 ms on the absolute sample grid, held in between).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from ..encoding.encoder import Encoder
from ..params import ClassParams, EncoderParams
from ..reference.constants import load_constants
from ..settings import CLASSES
from .layout import Layout, PopulationPlan, place
from .spatial import RuleState, SpatialRule


def variant_params(params: ClassParams, gain: float) -> ClassParams:
    """A class's parameters with every input weight scaled by ``gain``."""
    return params.model_copy(update={"weights": [w * gain for w in params.weights]})


@dataclass(frozen=True)
class Population:
    """A resolved population: plan (``cell_mm`` set), taxel positions, layout and weights."""

    plan: PopulationPlan
    taxels_xy_mm: np.ndarray  # (X, 2)
    layout: Layout
    rule: SpatialRule

    @classmethod
    def build(cls, taxels_xy_mm: np.ndarray, plan: PopulationPlan) -> Population:
        """Place the afferents and compute their weights. A class without variants in the plan runs
        its fitted parameters alone (one model)."""
        taxels = np.asarray(taxels_xy_mm, np.float64).reshape(-1, 2)
        plan = plan.resolved(taxels)
        return cls.with_layout(taxels, plan, place(taxels, plan, {c: len(plan.variants.get(c, [1.0])) for c in CLASSES}))

    @classmethod
    def with_layout(cls, taxels_xy_mm: np.ndarray, plan: PopulationPlan, layout: Layout) -> Population:
        """A population of given afferents (e.g. one per taxel centre and class: today's layout)."""
        taxels = np.asarray(taxels_xy_mm, np.float64).reshape(-1, 2)
        plan = plan.resolved(taxels)
        depth = load_constants().depth_mm[layout.cls]
        wave = np.isin(layout.cls, [CLASSES.index(c) for c in plan.surface_wave])
        rule = SpatialRule.build(layout.xy_mm, depth, wave, taxels, cell_mm=plan.cell_mm, probe_radius_mm=plan.probe_radius_mm,
                                 min_weight=plan.min_weight)
        return cls(plan, taxels, layout, rule)

    def __len__(self) -> int:
        return len(self.layout)

    def gain(self, afferent: int) -> float:
        c = CLASSES[int(self.layout.cls[afferent])]
        return float(self.plan.variants.get(c, [1.0])[int(self.layout.model[afferent])])

    def describe(self) -> dict:
        """The population as the stream's hello and recordings carry it."""
        return {"plan": asdict(self.plan), "afferents": self.layout.describe()}


class PopulationEncoder(Encoder):
    """Stateful encoder of a population's afferents (units = afferent ids) for the selected classes.

    ``process`` takes the taxels' (T, X, 4) channels; spikes address afferents (``taxel`` of the
    returned events is the afferent id). Columns are (afferent, its class); ``set_columns`` takes
    class -> afferent ids (ids of another class are ignored). A continuing afferent keeps its state
    bit-exactly; its input does not depend on which other afferents run.
    """

    def __init__(self, params: EncoderParams, population: Population, classes: Sequence[str] | None = None):
        self.population = population
        self._cls = population.layout.cls
        self._variants: dict[tuple[str, int], ClassParams] = {}
        self._rule_state = RuleState(len(population.taxels_xy_mm))  # the held localisation, whichever afferents run
        self._next_k = 0  # absolute grid index of the next sample
        super().__init__(params, len(population.taxels_xy_mm), classes)

    @property
    def n_units(self) -> int:
        return len(self.population)

    def _has(self, unit: int, cls: str) -> bool:
        return CLASSES[int(self._cls[unit])] == cls

    def _column_params(self, unit: int, cls: str) -> ClassParams:
        key = (cls, int(self.population.layout.model[unit]))
        if key not in self._variants:
            self._variants[key] = variant_params(self.params.classes[cls], self.population.gain(unit))
        return self._variants[key]

    def _build(self, columns: list[tuple[int, str]]) -> None:
        super()._build(columns)
        self._rule_rows = self.population.rule.rows(self._taxel_n)  # the afferent of each column

    def _input_rows(self) -> np.ndarray:
        return np.arange(len(self.columns), dtype=np.int64)

    def process(self, channels, k0: int | None = None):
        k = channels.k0 if k0 is None else k0
        if k != self._next_k:  # not where the last block ended: nothing held applies
            self._rule_state.valid = False
        self._next_k = k
        return super().process(channels, k0)

    def _inputs(self, data: np.ndarray) -> np.ndarray:
        out = self.population.rule.mix(data, self._rule_rows, self._next_k, self._rule_state)
        self._next_k += data.shape[0]
        return out
