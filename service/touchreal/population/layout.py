"""Where the afferents of a population sit and which model each one runs.

A population covers the skin the taxels cover: the union of the taxels' cells, squares of side
``cell_mm`` centred on the taxel centres (the tiling of a grid of that pitch). Afferents of each
class are placed uniformly at random over that area (a binomial point process: the count is
``density x area``, the positions independent), reproducibly from the plan's seed. Each afferent
runs one of its class's model variants, drawn uniformly, as TouchSim draws one of its fitted
single-unit models per afferent.

Default densities are those of the human fingertip, after Johansson & Vallbo (1979): 70 SA1,
140 RA and 25 PC afferents per cm^2 (TouchSim's own per-region figures differ in detail).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from pydantic import TypeAdapter

from ..settings import CLASSES

FINGERTIP_DENSITY_PER_CM2 = {"SA1": 70.0, "RA": 140.0, "PC": 25.0}
MAX_AFFERENTS = 65_536  #: afferents a population may hold (the stream's id space)


def taxel_pitch_mm(taxels_xy_mm: np.ndarray) -> float:
    """Median nearest-neighbour distance of the taxel centres (mm); 8 mm (one SingleTact) for one taxel."""
    xy = np.asarray(taxels_xy_mm, np.float64).reshape(-1, 2)
    if len(xy) < 2:
        return 8.0
    d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


@dataclass(frozen=True)
class PopulationPlan:
    """Everything a population is built from; printed, overridden and recorded as one JSON object.

    ``cell_mm`` None is resolved once, from the taxel positions, to their pitch
    (:meth:`resolved`); every other field is explicit.
    """

    density_per_cm2: dict[str, float] = field(default_factory=lambda: dict(FINGERTIP_DENSITY_PER_CM2))
    seed: int = 0
    cell_mm: float | None = None  #: side of a taxel's cell (mm): the skin a taxel reports on
    probe_radius_mm: float = 0.5  #: radius of the probe the class parameters were fitted for (mm)
    min_weight: float = 1e-3  #: taxel weights below this (relative to 1) are dropped
    variants: dict[str, list[float]] = field(default_factory=dict)  #: per class, each model variant's input gain
    #: classes whose film channels come from the localised contacts with TouchSim's surface-wave decay
    #: (population/spatial.py); the others' films are interpolated at the afferent
    surface_wave: list[str] = field(default_factory=lambda: ["RA"])

    def __post_init__(self) -> None:
        bad = [c for c in self.density_per_cm2 if c not in CLASSES]
        if bad:
            raise ValueError(f"unknown classes {bad} in density_per_cm2 (have {list(CLASSES)})")
        if any(not (0.0 <= d <= 10_000.0) for d in self.density_per_cm2.values()):
            raise ValueError("densities must be within 0-10000 per cm^2")
        if self.cell_mm is not None and not 0.1 <= self.cell_mm <= 100.0:
            raise ValueError("cell_mm must be within 0.1-100 mm")
        if not 0.05 <= self.probe_radius_mm <= 10.0:
            raise ValueError("probe_radius_mm must be within 0.05-10 mm")
        if not 0.0 <= self.min_weight < 1.0:
            raise ValueError("min_weight must be within [0, 1)")
        if any(c not in CLASSES for c in self.surface_wave):
            raise ValueError(f"surface_wave: unknown classes {[c for c in self.surface_wave if c not in CLASSES]}")
        for c, gains in self.variants.items():
            if c not in CLASSES or not gains or any(not (0.0 < g < 1e3) for g in gains):
                raise ValueError(f"variants[{c!r}] must be a non-empty list of gains in (0, 1000) of a known class")

    def resolved(self, taxels_xy_mm: np.ndarray) -> PopulationPlan:
        """This plan with ``cell_mm`` set from the taxel positions when it was None."""
        return self if self.cell_mm is not None else replace(self, cell_mm=taxel_pitch_mm(taxels_xy_mm))

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    @classmethod
    def from_dict(cls, d: object) -> PopulationPlan:
        """A plan from JSON data; a wrong field, type or value raises ValueError naming it."""
        if not isinstance(d, dict):
            raise ValueError("a population plan is a JSON object")
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown population plan fields {sorted(unknown)}")
        return TypeAdapter(cls).validate_python(d, strict=False)


@dataclass(frozen=True)
class Layout:
    """The afferents: id = row index; ``cls`` index into CLASSES, position (mm), model variant index."""

    cls: np.ndarray  # (A,) int64
    xy_mm: np.ndarray  # (A, 2) float64
    model: np.ndarray  # (A,) int64

    def __len__(self) -> int:
        return int(self.cls.size)

    def ids(self, cls: str) -> np.ndarray:
        return np.flatnonzero(self.cls == CLASSES.index(cls))

    def describe(self) -> list[dict]:
        """One entry per afferent (id, class, x_mm, y_mm, model) as the stream's hello lists them."""
        return [{"id": i, "class": CLASSES[c], "x_mm": round(float(x), 3), "y_mm": round(float(y), 3), "model": int(m)}
                for i, (c, (x, y), m) in enumerate(zip(self.cls.tolist(), self.xy_mm.tolist(), self.model.tolist()))]


def covered(xy_mm: np.ndarray, taxels_xy_mm: np.ndarray, cell_mm: float) -> np.ndarray:
    """(N,) bool: the points lie on some taxel's cell."""
    d = np.abs(np.asarray(xy_mm, np.float64)[:, None, :] - np.asarray(taxels_xy_mm, np.float64)[None, :, :])
    return np.any(np.all(d <= cell_mm / 2.0, axis=2), axis=1)


def place(taxels_xy_mm: np.ndarray, plan: PopulationPlan, n_models: dict[str, int]) -> Layout:
    """Afferents over the taxels' cells at the plan's densities; reproducible from ``plan.seed``.

    ``n_models``: per class, the number of model variants to draw from. Classes are placed in
    CLASSES order, so the ids of a class are contiguous.
    """
    taxels = np.asarray(taxels_xy_mm, np.float64).reshape(-1, 2)
    cell = plan.resolved(taxels).cell_mm
    rng = np.random.default_rng(plan.seed)
    lo, hi = taxels.min(axis=0) - cell / 2.0, taxels.max(axis=0) + cell / 2.0
    # rejection sampling from the bounding box keeps every class's count exact on any union of cells
    uniq = np.unique(np.round(taxels / (cell * 1e-3)) * (cell * 1e-3), axis=0)
    area_cm2 = len(uniq) * cell * cell / 100.0 if _disjoint(uniq, cell) else _area_cm2(taxels, cell, lo, hi)
    cls, xy, model = [], [], []
    for c, name in enumerate(CLASSES):
        n = int(round(plan.density_per_cm2.get(name, 0.0) * area_cm2))
        if n == 0:
            continue
        pts = np.zeros((0, 2))
        while len(pts) < n:
            cand = rng.uniform(lo, hi, size=(2 * n + 16, 2))
            pts = np.vstack([pts, cand[covered(cand, taxels, cell)]])
        cls.append(np.full(n, c))
        xy.append(pts[:n])
        model.append(rng.integers(0, n_models[name], n))
    if not cls:
        raise ValueError("the plan places no afferent (every density is 0)")
    total = sum(len(c) for c in cls)
    if total > MAX_AFFERENTS:
        raise ValueError(f"{total} afferents exceed the limit of {MAX_AFFERENTS}: lower the densities or the skin area")
    return Layout(np.concatenate(cls).astype(np.int64), np.vstack(xy), np.concatenate(model).astype(np.int64))


def _disjoint(cells: np.ndarray, cell: float) -> bool:
    """The cells do not overlap (taxel centres at least a cell apart on x or y)."""
    d = np.abs(cells[:, None, :] - cells[None, :, :])
    overlap = np.all(d < cell * (1.0 - 1e-9), axis=2)
    np.fill_diagonal(overlap, False)
    return not overlap.any()


def _area_cm2(taxels: np.ndarray, cell: float, lo: np.ndarray, hi: np.ndarray, n: int = 400) -> float:
    """Area of a union of overlapping cells on an n x n raster of the bounding box (cm^2)."""
    gx, gy = (np.linspace(a, b, n) for a, b in zip(lo, hi))
    pts = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    frac = covered(pts, taxels, cell).mean()
    return float(frac * np.prod(hi - lo) / 100.0)
