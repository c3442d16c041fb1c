"""Evaluate a fit's CMA-ES candidates on Dask distributed workers (``touchreal fit --scheduler``).

The same seam as the local processes (:class:`~touchreal.fitting.executor.Executor`): the driver runs
CMA-ES and sends each generation's candidates, split into one chunk per worker thread; every worker
holds the fit's training state, built once by :class:`FitDataPlugin` from the :class:`FitSource`
(the dataset folder, the configuration, the ``--init`` file) with the driver's own deterministic
:func:`~touchreal.fitting.fit.prepare`. Candidates travel (a few hundred bytes each), the dataset
does not. A candidate's loss depends on that candidate alone, so the fit is bit-identical to the
local one with the same seed, however the batch is split and wherever a chunk runs.

The dataset must be readable by every worker at the path the driver passes (an absolute path;
mount the same volume on every worker, as deploy/dask does). A worker that joins or restarts
gets the plugin from the scheduler and builds the state before its first chunk; a chunk whose
worker dies is recomputed elsewhere by the scheduler, and a chunk that fails is retried.

Requires ``dask[distributed]`` (the ``fit-dask`` extra); imported only when a Dask fit is asked for.
"""

from __future__ import annotations

import asyncio
import threading
import uuid
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import dask
import numpy as np
from distributed import Client, LocalCluster, WorkerPlugin, get_worker

from .executor import ExecutorFactory, FitSource, FitState, Losses, losses, warm_up
from .fit import prepare

#: worker settings for fits: the statistical profiler samples every thread's stack every 10 ms; with
#: it a generation took 1.75x the local one instead of 1.3-1.5x (docs/scale-out-dask.md); deploy/dask sets the same
#: through DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
RETRIES = 3  #: retries of a chunk that raised (a chunk lost with its worker is rescheduled anyway)


class FitDataPlugin(WorkerPlugin):
    """Holds one fit's training state on a worker: loads and preprocesses the dataset once
    (:func:`prepare`) and compiles the numba kernels, when the worker starts or joins."""

    def __init__(self, source: FitSource):
        self.source = source
        self._state: FitState | None = None
        self._lock = threading.Lock()
        self.error: str | None = None  #: why setup failed on this worker

    def __getstate__(self) -> dict:
        return {"source": self.source}

    def __setstate__(self, d: dict) -> None:
        self.__init__(d["source"])

    async def setup(self, worker) -> None:
        """Build the state off the worker's event loop. A failure (say, the dataset is not at that
        path on this worker) is kept, not raised, so the worker still starts; the driver asks for it
        (:func:`_setup_error`), and a chunk sent here tries again and fails the same way (retried)."""
        try:
            await asyncio.get_running_loop().run_in_executor(None, self.state)
        except Exception as exc:  # noqa: BLE001 - reported to the driver by _setup_error
            self.error = f"{type(exc).__name__}: {exc}"

    def teardown(self, worker) -> None:
        self._state = None

    def state(self) -> FitState:
        """The fit's state, built on first use (setup, or the first chunk if that comes first)."""
        with self._lock:
            if self._state is None:
                state = prepare(self.source).state
                warm_up()
                self._state = state
            return self._state


def _chunk_losses(plugin_name: str, cls: str, xs: np.ndarray) -> Losses:
    """Task: losses of a chunk of candidates on this worker's copy of the fit's state."""
    plugin = get_worker().plugins.get(plugin_name)
    if not isinstance(plugin, FitDataPlugin):
        raise RuntimeError(f"worker has no fit plugin {plugin_name!r} yet")  # retried
    return losses(plugin.state(), cls, xs)


def _setup_error(plugin_name: str, dask_worker) -> str | None:
    """Run on each worker: why its fit plugin could not build the state (None: it did)."""
    plugin = dask_worker.plugins.get(plugin_name)
    return plugin.error if isinstance(plugin, FitDataPlugin) else f"no fit plugin {plugin_name!r}"


class DaskExecutor:
    """Evaluates candidate batches on the workers of ``client``'s cluster (one chunk per worker thread)."""

    def __init__(self, client: Client, source: FitSource):
        self.client = client
        self.name = f"touchreal-fit-{uuid.uuid4().hex[:12]}"
        source = replace(source, dataset_dir=str(Path(source.dataset_dir).resolve()))
        client.register_plugin(FitDataPlugin(source), name=self.name)
        errors = {w: e for w, e in client.run(_setup_error, self.name).items() if e}
        if errors:
            self.close()
            raise ValueError(f"Dask workers could not load {source.dataset_dir} (every worker must read the dataset at the "
                             f"driver's path): " + "; ".join(f"{w}: {e}" for w, e in sorted(errors.items())))

    @classmethod
    def factory(cls, client: Client) -> ExecutorFactory:
        """Executor factory for :func:`~touchreal.fitting.fit.fit_dataset` (the local state is not needed)."""
        return lambda source, state: cls(client, source)

    def __call__(self, cls: str, xs: np.ndarray) -> Losses:
        xs = np.asarray(xs, np.float64)
        threads = max(1, sum(self.client.nthreads().values()))
        chunks = [c for c in np.array_split(xs, min(threads, len(xs))) if len(c)]
        futures = [self.client.submit(_chunk_losses, self.name, cls, c, pure=False, retries=RETRIES) for c in chunks]
        res: Losses = []
        for part in self.client.gather(futures):
            res += part
        return res

    def close(self) -> None:
        self.client.unregister_worker_plugin(self.name)


@contextmanager
def dask_client(scheduler: str | None = None, n_workers: int | None = None) -> Iterator[Client]:
    """A client of the scheduler at ``scheduler`` (``tcp://HOST:PORT``), or of a local cluster of
    ``n_workers`` single-threaded worker processes started for the fit and closed after it."""
    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    if not n_workers or n_workers < 1:
        raise ValueError("give a scheduler address or a number of local Dask workers >= 1")
    with dask.config.set(WORKER_CONFIG):
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None)
    with cluster, Client(cluster) as client:
        yield client
