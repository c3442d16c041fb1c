"""Where a fit's candidates are evaluated. An :class:`Executor` maps (class, candidate batch) to
losses from a :class:`FitState`: :class:`LocalExecutor` uses forked processes on this machine;
``touchreal.fitting.dask_executor`` uses Dask workers, each of which rebuilds the same state once
from the :class:`FitSource` (see :func:`touchreal.fitting.fit.prepare`). Executors are called from
several threads at once (the classes and restarts of a fit search side by side)."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from ..encoding.encoder import encode_population
from ..params import ClassParams, EncoderParams
from .config import FitConfig
from .objective import ObjectiveConfig, ReferenceSet, evaluate_loss
from .plan import FitPlan
from .space import ParamSpace
from .trials import TrialSet, simulate


@dataclass(frozen=True)
class FitSource:
    """Everything a fit's training state is built from (a worker rebuilds it from this alone):
    the dataset folder (as seen by the worker), the run's configuration and the ``--init`` file."""

    dataset_dir: str
    cfg: FitConfig
    init: EncoderParams | None = None


@dataclass
class FitState:
    """What evaluating a candidate needs: the plan (each stage's objective), and per state key (a
    class for its search, the class + ``:refine`` for its refinement) the search space, references
    and preprocessed training trials; the search's alignment ``lag_s`` (s; spikes compared at stamp
    minus it)."""

    plan: FitPlan
    spaces: dict[str, ParamSpace]
    refs: dict[str, ReferenceSet]
    train: dict[str, TrialSet]
    lag_s: float


Losses = list[tuple[float, dict[str, float]]]  #: per candidate: (total loss, loss terms)


def losses(state: FitState, cls: str, xs: np.ndarray) -> Losses:
    """Objective of every candidate ``xs`` (n, dim) of class ``cls`` (a non-finite loss counts as 1e6).
    Each candidate's loss depends on that candidate alone, so any split of a batch gives the same numbers."""
    space, tset, objective = state.spaces[cls], state.train[cls], state.plan.objective_of(cls)
    trains = simulate(tset.trials, [space.decode(x) for x in xs], state.lag_s)
    out = []
    for tr in trains:
        terms = evaluate_loss(tr, tset.cond_index, state.refs[cls], objective)
        total = terms.total if np.isfinite(terms.total) else 1e6
        out.append((float(total), terms.as_dict()))
    return out


class Executor(Protocol):
    """Evaluates a batch of candidates of one class: ``executor(cls, xs) -> losses``, in order."""

    def __call__(self, cls: str, xs: np.ndarray) -> Losses: ...

    def close(self) -> None: ...


ExecutorFactory = Callable[[FitSource, FitState], Executor]

_STATE: dict[str, FitState] = {}  # the local worker processes' state (inherited by fork)


def _local_losses(cls: str, xs: np.ndarray) -> Losses:
    return losses(_STATE["state"], cls, xs)


def _init_worker(state: FitState | None) -> None:
    if state is not None:
        _STATE["state"] = state


class LocalExecutor:
    """Evaluates candidate batches in-process or on ``workers`` forked processes (the state is
    inherited, not copied; numba kernels are compiled before forking). A batch is split across the
    workers while fewer batches than workers are in flight; otherwise it is one task, so that its
    per-trial set-up (input stage, LIF, spike sorting: about 0.1 ms a trial) is paid once."""

    def __init__(self, state: FitState, workers: int):
        _STATE["state"] = state
        warm_up()
        self.state = state
        self.workers = workers
        self.pool: ProcessPoolExecutor | None = None
        self._in_flight = 0
        self._lock = threading.Lock()
        if workers > 1:
            methods = mp.get_all_start_methods()
            if "fork" in methods:
                self.pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("fork"), initializer=_init_worker, initargs=(None,))
            else:  # pragma: no cover - platforms without fork: ship the cache once per worker
                self.pool = ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(state,))

    @classmethod
    def factory(cls, workers: int | None) -> ExecutorFactory:
        """Executor factory for :func:`fit_dataset`: ``workers`` processes (None = all cores, at most the population)."""
        return lambda source, state: cls(state, max(1, min(workers or os.cpu_count() or 1, state.plan.popsize)))

    def __call__(self, cls: str, xs: np.ndarray) -> Losses:
        xs = np.asarray(xs, np.float64)
        if self.pool is None or len(xs) < 2:
            return losses(self.state, cls, xs)
        with self._lock:
            n_chunks = 1 if self._in_flight >= self.workers else self.workers
            self._in_flight += 1
        try:
            chunks = [c for c in np.array_split(xs, n_chunks) if len(c)]
            res = []
            for part in self.pool.map(_local_losses, [cls] * len(chunks), chunks):
                res += part
            return res
        finally:
            with self._lock:
                self._in_flight -= 1

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None
        _STATE.pop("state", None)


def warm_up() -> None:
    """Compile the numba kernels (before forking, so workers inherit them; once per Dask worker)."""
    encode_population(np.zeros((16, 4)), 0.0, [ClassParams(weights=[0.0] * 8, i_sat=0, tau_ms=1, ih=[0, 0], delay_ms=0)])
    refs = ReferenceSet.build([[np.array([0.1])]], 0.01)
    evaluate_loss([np.array([0.1])], [0], refs, ObjectiveConfig())
