"""The fit's CMA-ES driver: every run has its own random stream, so runs and classes may interleave
without changing a seeded fit."""

from __future__ import annotations

import numpy as np
import pytest

from touchreal.fitting import search as S
from touchreal.fitting.policy import default_plan
from touchreal.fitting.space import Coord, ParamSpace

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


def test_restarts_run_side_by_side_independently_and_the_best_point_wins():
    x0 = SPACE.initial(100.0)
    fit = S.Searcher(SPACE, _sphere, 4).stage("RA", S.Budget(6, 12, restarts=1), [x0], 100.0)
    assert [(r.popsize, r.budget, r.generations) for r in fit.runs] == [(6, 12, 12), (12, 6, 6)]
    grid = S.start_grid(SPACE, [x0], 100.0)
    start = grid[int(np.argmin([f for f, _ in _sphere("RA", grid)]))]
    for k, run in enumerate(fit.runs):  # each run is the run it would be alone: it shares nothing with the other
        alone = S.run_cma("RA", SPACE, _sphere, start, run.popsize, run.budget, S.cma_seed(4, "RA", k))
        assert alone.history == run.history
        np.testing.assert_array_equal(alone.best_x, run.best_x)
    best = min(fit.runs, key=lambda r: r.best_loss)
    np.testing.assert_array_equal(fit.x, SPACE.clip(best.best_x))
    assert fit.evaluations == len(grid) + 6 * 12 + 12 * 6  # start grid + both runs
    seen: list[int] = []
    S.run_cma("RA", SPACE, _sphere, x0, 6, 5, 3, seen.append)
    assert sum(seen) == 5  # the progress bar reaches the budget


def test_a_refinement_starts_from_the_search_best_point_and_optimises_its_own_objective():
    lo, hi = SPACE.bounds()
    a, b = lo + 0.4 * (hi - lo), lo + 0.45 * (hi - lo)  # the search's optimum, and the refinement's nearby

    def two_objectives(key: str, xs: np.ndarray) -> list[tuple[float, dict[str, float]]]:
        centre = b if key == "RA:refine" else a
        return [(float(np.sum((x - centre) ** 2)), {}) for x in np.asarray(xs)]

    x0 = SPACE.initial(100.0)
    plan = default_plan(("RA",)).overridden({"popsize": 6, "generations": 30})  # RA is refined
    searcher = S.Searcher(SPACE, two_objectives, 4)
    fit = searcher.search_and_refine("RA", plan, [x0], 100.0)
    assert fit.cls == "RA" and fit.search is not None and fit.search.search is None
    on_refinement = lambda x: two_objectives("RA:refine", np.array([x]))[0][0]  # noqa: E731
    # the search's best point is on the refinement's start grid: the refinement starts no worse than it
    assert fit.start_loss <= on_refinement(fit.search.x) + 1e-12
    assert on_refinement(fit.x) < on_refinement(fit.search.x)
    assert fit.runs[0].history[-1] <= fit.start_loss
    # a class not refined is searched once
    plain = searcher.search_and_refine("RA", plan.overridden({"generations": 3, "classes": {"RA": {"refine": None}}}), [x0], 100.0)
    assert plain.search is None
    # the refinement draws from streams of its own
    assert S.cma_seed(4, "RA:refine") != S.cma_seed(4, "RA") == S.cma_seed(4, "RA", 0)


def test_sa1_also_searches_from_a_saturated_start_in_a_run_of_its_own():
    sa1 = ParamSpace.for_class("SA1", [8.0, 60.0, 0.2, 200.0])
    starts = [sa1.initial(100.0, v) for v in range(2)]
    own, saturated = S.start_grid(sa1, starts, 100.0), S.start_grid(sa1, starts, 100.0, -2.0)
    assert np.all(own[:, Coord.LOG_ISAT] == 3.0) and np.all(saturated[:, Coord.LOG_ISAT] == -2.0)  # each start's own i_sat (e^3), and e^-2
    np.testing.assert_array_equal(np.delete(own, Coord.LOG_ISAT, axis=1), np.delete(saturated, Coord.LOG_ISAT, axis=1))  # the same points otherwise
    plan = default_plan(("SA1",)).overridden({"popsize": 6, "generations": 10, "classes": {"SA1": {"restarts": 1, "saturated_starts": [-2.0]}}})
    fit = S.Searcher(sa1, _sphere, 4).stage("SA1", S.Budget.of(plan, "SA1"), starts, 100.0)
    assert [(r.popsize, r.budget) for r in fit.runs] == [(6, 10), (12, 5), (6, 10)]  # the search, its restart, the saturated run
    x_sat = saturated[int(np.argmin([f for f, _ in _sphere("SA1", saturated)]))]
    alone = S.run_cma("SA1", sa1, _sphere, x_sat, 6, 10, S.cma_seed(4, "SA1", 2))
    assert alone.history == fit.runs[2].history  # from the best saturated grid point, on a stream of its own
    assert fit.evaluations == len(own) + len(saturated) + 6 * 10 + 12 * 5 + 6 * 10
    assert min(r.best_loss for r in fit.runs) == pytest.approx(float(np.sum((fit.x - 0.3) ** 2)))  # the best run wins
    assert S.Budget.of(plan, "SA1:refine") == S.Budget(6, 10, restarts=1)  # a refinement keeps the search's saturation
    refined = S.Searcher(sa1, _sphere, 4).stage("SA1:refine", S.Budget.of(plan, "SA1:refine"), [fit.x], 100.0)
    assert [(r.popsize, r.budget) for r in refined.runs] == [(6, 10), (12, 5)]
    quiet = S.Searcher(sa1, _sphere, 4).stage("SA1", S.Budget(6, 4), starts, 100.0)
    assert len(quiet.runs) == 1 and quiet.evaluations == len(own) + 6 * 4  # not asked for (a quiet SingleTact): one run from its own grid
