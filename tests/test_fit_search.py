"""The fit's CMA-ES driver: every run has its own random stream (runs and classes may interleave
without changing a seeded fit), and a run stops when it stagnates."""

from __future__ import annotations

import numpy as np
import pytest

from touchreal.fitting import search as S
from touchreal.fitting.config import FitConfig
from touchreal.fitting.space import ParamSpace

SPACE = ParamSpace.for_class("RA", [8.0, 60.0, 0.2, 200.0], input_stage=True)


def _sphere(cls: str, xs: np.ndarray) -> list[tuple[float, dict[str, float]]]:
    """Loss of candidates on a shifted sphere (an objective with a known optimum)."""
    return [(float(np.sum((x - 0.3) ** 2)), {}) for x in np.asarray(xs)]


def _asks(strategies, generations: int) -> list[list[np.ndarray]]:
    """Ask/tell the strategies in turn, one generation each, on the sphere; every strategy's asks."""
    out: list[list[np.ndarray]] = [[] for _ in strategies]
    for _ in range(generations):
        for k, es in enumerate(strategies):
            xs = np.asarray(es.ask())
            es.tell(list(xs), [f for f, _ in _sphere("RA", xs)])
            out[k].append(xs)
    return out


def test_interleaved_runs_draw_the_same_candidates_as_runs_alone_and_as_a_globally_seeded_cma():
    import cma

    x0 = SPACE.initial(100.0)
    together = _asks([S.make_cma(SPACE, x0, 6, 20, 11), S.make_cma(SPACE, x0, 12, 20, 12)], 8)
    alone = [_asks([S.make_cma(SPACE, x0, 6, 20, 11)], 8)[0], _asks([S.make_cma(SPACE, x0, 12, 20, 12)], 8)[0]]
    for a, b in zip(together, alone):
        for xa, xb in zip(a, b):
            np.testing.assert_array_equal(xa, xb)
    # the numbers are those of cma seeding NumPy's global generator (how a fit drew them when it ran one run at a time)
    lo, hi = SPACE.bounds()
    es = cma.CMAEvolutionStrategy(list(x0), 1.0, {"seed": 11, "popsize": 6, "bounds": [list(lo), list(hi)],
                                                  "CMA_stds": list(SPACE.stds()), "maxiter": 20, "verbose": -9,
                                                  "tolfun": 1e-6, "tolflatfitness": 10})
    for xa, xb in zip(together[0], _asks([es], 8)[0]):
        np.testing.assert_array_equal(xa, xb)
    assert not np.array_equal(together[0][0], _asks([S.make_cma(SPACE, x0, 6, 20, 13)], 1)[0][0])  # the seed matters


@pytest.mark.parametrize(
    "history, generations, tol, expected",
    [
        ([5.0, 4.0, 3.0, 3.0], 2, 0.5, False),  # improved by 1.0 over the last 2 generations
        ([5.0, 4.0, 3.0, 2.9, 2.9], 2, 0.5, True),  # by 0.1 only
        ([5.0, 5.0, 5.0], 3, 0.5, False),  # not yet 3 generations of history to compare with
        ([5.0, 5.0, 5.0, 5.0], 3, 0.5, True),
        ([5.0] * 50, 0, 0.5, False),  # 0: never
    ],
)
def test_stall_rule(history, generations, tol, expected):
    assert S.stalled(history, generations, tol) is expected


def test_a_run_stops_when_it_stagnates_and_runs_its_budget_otherwise():
    x0 = SPACE.initial(100.0)
    seen: list[int] = []
    cfg = FitConfig(classes=("RA",), stall_generations=4, stall_tol=1e9, progress=False)  # no step is progress
    run = S.run_cma("RA", SPACE, _sphere, x0, 6, 40, 3, cfg, seen.append)
    assert (run.generations, run.stop) == (5, "stalled")
    assert sum(seen) == 40  # the progress bar is completed to the budget
    full = S.run_cma("RA", SPACE, _sphere, x0, 6, 40, 3, FitConfig(classes=("RA",), progress=False))
    assert (full.generations, full.stop) == (40, "budget")
    assert full.history[:5] == run.history  # the same run, cut short
    assert full.best_loss < run.best_loss
    sensible = S.run_cma("RA", SPACE, _sphere, x0, 6, 400, 3, FitConfig(classes=("RA",), stall_generations=10, stall_tol=1e-3, progress=False))
    assert sensible.stop == "stalled" and sensible.generations < 400
    assert sensible.history[-1] - sensible.history[-11] > -1e-3


def test_stall_settings_are_validated():
    with pytest.raises(ValueError):
        FitConfig(stall_generations=-1)
    with pytest.raises(ValueError):
        FitConfig(stall_tol=float("nan"))
