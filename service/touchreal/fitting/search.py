"""CMA-ES search of one class's parameters (``cma``) in the normalised space of :mod:`.space`.

:meth:`Searcher.stage` evaluates a deterministic start grid, then runs the first CMA-ES run and its IPOP
restarts side by side from the grid's best point (each from the same point with its own seed, so
they are independent of each other), and one more run from the best point of the same grid at each
saturated start the plan gives the class (SA1 on a noisy SingleTact: ``i_sat`` = e^-2); the best
point any of them evaluated wins (:class:`Budget`: the runs of one stage). Every run draws its
samples from a random stream of its own, so runs (and the classes of a fit) may interleave in any
order and the result is still the same for a seed. A run ends at its generation budget or at
``cma``'s own stopping rules. There is no stop on stagnation: on rig-v1 a run's best loss stays flat
for 20-30 generations and then falls by 0.1-0.4 (docs/fitting.md). :meth:`Searcher.search_and_refine` follows a
class's search with its refinement (a second stage on another objective) where the plan has one.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..params import ClassParams
from ..settings import CLASSES
from .executor import Executor
from .objective import LossTerms
from .plan import FitPlan, parse_stage_key, stage_key
from .space import DELAY_UNIT_MS, Coord, ParamSpace

GRID_GAINS = 2.0 ** np.arange(-4, 5)  #: overall weight gains of the start grid
GRID_LOG_TAU = (-1.4, 0.0, 1.4)  #: tau multipliers exp(.) of the start grid (x0.25, x1, x4)
GRID_DELAYS_MS = (-20.0, 0.0, 20.0)  #: delay offsets of the start grid (clipped to delays >= 0)


@dataclass
class RunFit:
    """One CMA-ES run of a class: its population, generations done, why it stopped, its best point."""

    popsize: int
    budget: int  #: generations allowed
    generations: int
    stop: str  #: "budget" or cma's stopping rules
    best_loss: float
    best_x: np.ndarray
    history: list[float] = field(default_factory=list)  #: the run's best-so-far loss per generation

    def as_dict(self) -> dict[str, object]:
        return {"popsize": self.popsize, "generations": self.generations, "stop": self.stop, "best_loss": round(self.best_loss, 5)}


@dataclass
class ClassFit:
    cls: str
    params: ClassParams
    x: np.ndarray
    generations: int  #: over all runs
    evaluations: int  #: start grid + all runs
    seconds: float
    runs: list[RunFit]
    start_loss: float
    train: LossTerms | None = None
    validation: LossTerms | None = None
    search: "ClassFit | None" = None  #: for a refinement: the class's search it started from

    @property
    def best_loss(self) -> float:
        """The best loss evaluated: the start grid's or a run's."""
        return min([self.start_loss] + [r.best_loss for r in self.runs])


@dataclass(frozen=True)
class Budget:
    """The CMA-ES runs of one stage of a class: a first run of ``popsize`` candidates for at most
    ``generations`` generations, its ``restarts`` (population x2, generations /2 each) and one run
    from each of ``saturated_starts`` (log i_sat), all side by side."""

    popsize: int
    generations: int
    restarts: int = 0
    saturated_starts: tuple[float, ...] = ()

    @classmethod
    def of(cls, plan: FitPlan, key: str) -> Budget:
        """The budget of a class's search (``key`` = the class) or of its refinement (its
        :func:`~.plan.stage_key`): the plan's population and generations, the class's restarts; the
        saturated starts are the search's only (a refinement starts from the saturation the search chose)."""
        name, refinement = parse_stage_key(key)
        cp = plan.classes[name]
        return cls(plan.popsize, plan.generations, cp.restarts, () if refinement else cp.saturated_starts)


def cma_seed(seed: int, key: str, run: int = 0) -> int:
    """The seed of run ``run`` of a class's search (``key`` = the class) or of its refinement (the
    class's :func:`~.plan.stage_key`) in a fit seeded with ``seed``."""
    cls, refinement = parse_stage_key(key)
    entropy = [int(seed), CLASSES.index(cls), run] + ([1] if refinement else [])
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] % (2**31 - 2)) + 1


def make_cma(space: ParamSpace, x0: np.ndarray, popsize: int, generations: int, seed: int):
    """A ``cma`` strategy on ``space`` from ``x0`` whose samples come from its own ``RandomState(seed)``
    (the same numbers ``cma`` draws from NumPy's global generator seeded with ``seed``, without sharing it)."""
    import cma

    lo, hi = space.bounds()
    opts = {
        "seed": np.nan,  # the stream is ``randn``'s own
        "randn": np.random.RandomState(seed).randn,
        "popsize": popsize,
        "bounds": [list(lo), list(hi)],
        "CMA_stds": list(space.stds()),
        "maxiter": generations,
        "verbose": -9,
        "tolfun": 1e-6,
        "tolflatfitness": 10,
    }
    if space.fixed():
        opts["fixed_variables"] = space.fixed()
    return cma.CMAEvolutionStrategy(list(x0), 1.0, opts)


def start_grid(space: ParamSpace, starts: Sequence[np.ndarray], delay0_ms: float, log_isat: float | None = None) -> np.ndarray:
    """Every start x gain x tau multiplier x delay offset (deterministic), at each start's own input
    saturation or at ``log_isat``."""
    out = []
    for x0 in starts:
        x = np.array(x0, np.float64)
        if log_isat is not None:
            x[Coord.LOG_ISAT] = log_isat
        for g in GRID_GAINS:
            for lt in GRID_LOG_TAU:
                for dd in GRID_DELAYS_MS:
                    y = space.with_gain(x, g)
                    y[Coord.LOG_TAU] = x[Coord.LOG_TAU] + lt
                    y[Coord.DELAY] = (delay0_ms + dd) / DELAY_UNIT_MS
                    out.append(space.clip(y))
    return np.array(out)


def run_cma(cls: str, space: ParamSpace, evaluate: Executor, x0: np.ndarray, popsize: int, budget: int, seed: int,
            progress: Callable[[int], None] = lambda n: None) -> RunFit:
    """One CMA-ES run from ``x0``: ``budget`` generations of ``popsize`` candidates at most."""
    es = make_cma(space, x0, popsize, budget, seed)
    best_x, best_f = np.asarray(x0, np.float64).copy(), np.inf
    history: list[float] = []
    while not es.stop():
        xs = np.asarray(es.ask())
        f = [r[0] for r in evaluate(cls, xs)]
        es.tell(list(xs), f)
        i = int(np.argmin(f))
        if f[i] < best_f:
            best_f, best_x = float(f[i]), xs[i].copy()
        history.append(best_f)
        progress(1)
    stop = ",".join(k for k in es.stop() if k != "maxiter") or "budget"
    progress(budget - len(history))
    return RunFit(popsize, budget, len(history), stop, best_f, best_x, history)


@dataclass(frozen=True)
class Searcher:
    """What every stage of one class's search shares: the class's space, the executor that scores its
    points, the fit's seed, and its progress bar (``progress``: shown, on line ``position``)."""

    space: ParamSpace
    evaluate: Executor
    seed: int
    progress: bool = False
    position: int = 0

    def stage(self, key: str, budget: Budget, starts: Sequence[np.ndarray], delay0_ms: float) -> ClassFit:
        """CMA-ES for one stage of a class from the best point of :func:`start_grid` around ``starts``,
        with the budget's IPOP restarts (population doubled, generations halved each time, so every run
        costs about the same) run side by side with the first run, each with its own seed, and one more
        run from the best grid point at each of the budget's saturated starts.
        The best point ever evaluated wins (the grid's best if no run beats it; the earlier run on a tie).
        Independent restarts matter: on rig-v1, runs that differ only in their seed end in optima that
        differ by up to 0.2 in loss, while restarting from a converged point does not move it.
        ``key`` is the state key the executor evaluates (a class, or a class's refinement)."""
        from tqdm import tqdm

        t_start = time.perf_counter()
        grids = [start_grid(self.space, starts, delay0_ms, li) for li in (None, *budget.saturated_starts)]
        grid = np.concatenate(grids)
        losses = np.array([r[0] for r in self.evaluate(key, grid)])
        edges = np.cumsum([0] + [len(g) for g in grids])
        x0s = [grid[a + int(np.argmin(losses[a:b]))] for a, b in zip(edges[:-1], edges[1:])]  # each saturation's best
        best = int(np.argmin(losses))
        start_loss = float(losses[best])
        # (start, population, generations): the first run and its restarts from the best point at the
        # starts' own saturation, then one run from the best point at each saturated start's
        runs_plan = [(x0s[0], budget.popsize * 2**k, max(1, budget.generations // 2**k)) for k in range(budget.restarts + 1)]
        runs_plan += [(x, budget.popsize, budget.generations) for x in x0s[1:]]
        bar = tqdm(total=sum(g for _, _, g in runs_plan), desc=f"fit {key}", unit="gen", disable=not self.progress,
                   dynamic_ncols=True, position=self.position, leave=True)
        lock = threading.Lock()

        def advance(n: int) -> None:
            with lock:
                bar.update(n)

        try:
            with ThreadPoolExecutor(len(runs_plan), thread_name_prefix=f"fit-{key}") as pool:
                futures = [pool.submit(run_cma, key, self.space, self.evaluate, x, p, g, cma_seed(self.seed, key, k), advance)
                           for k, (x, p, g) in enumerate(runs_plan)]
                runs = [f.result() for f in futures]
        finally:
            bar.close()
        best_x, best_f = grid[best].copy(), start_loss
        for r in runs:  # in run order: the earlier run wins a tie
            if r.best_loss < best_f:
                best_x, best_f = r.best_x, r.best_loss
        return ClassFit(
            cls=key,
            params=self.space.decode(best_x),
            x=self.space.clip(best_x),
            generations=sum(r.generations for r in runs),
            evaluations=len(grid) + sum(r.generations * r.popsize for r in runs),
            seconds=time.perf_counter() - t_start,
            runs=runs,
            start_loss=start_loss,
        )

    def search_and_refine(self, cls: str, plan: FitPlan, starts: Sequence[np.ndarray], delay0_ms: float) -> ClassFit:
        """:meth:`stage` on the class's objective with the plan's budget for its search; for a class
        the plan refines, then its refinement: :meth:`stage` on the refinement's objective (its
        :func:`~.plan.stage_key`) from the search's best point. That point is on the refinement's start
        grid (gain 1, tau and delay unchanged), so the refinement never ends worse on its own objective.
        Returns the refinement, with the search in ``.search``."""
        first = self.stage(cls, Budget.of(plan, cls), starts, delay0_ms)
        if plan.classes[cls].refine is None:
            return first
        key = stage_key(cls, True)
        refined = self.stage(key, Budget.of(plan, key), [first.x], float(first.x[Coord.DELAY]) * DELAY_UNIT_MS)
        refined.cls, refined.search = cls, first
        return refined
