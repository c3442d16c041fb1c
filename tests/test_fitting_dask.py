"""Fitting on Dask: candidates evaluated on a real 2-process LocalCluster give bit-identical
parameters to the local fit with the same seed; a worker killed mid-generation is survived; the
CLI fits several datasets side by side on one cluster."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")
pytestmark = pytest.mark.slow  # a 2-process LocalCluster and three small fits: about 45 s (pytest -m slow; .ci/run runs it)

from touchreal.fitting import fit as F  # noqa: E402
from touchreal.params import EncoderParams  # noqa: E402
from touchreal.simulator.simulate import simulate_dataset  # noqa: E402

#: SA1 from its saturated start too: two runs side by side
RECIPE = {"popsize": 6, "generations": 3, "classes": {"SA1": {"saturated_starts": [-2.0]}}}
CFG = dict(classes=("SA1", "RA"), progress=False, seed=1, holdout=False, recipe=RECIPE)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> list[Path]:
    """Two small simulated datasets (one per 'sensor') with TouchSim references."""
    root = tmp_path_factory.mktemp("dask-ds")
    return [simulate_dataset(["ramp", "sine"], root / f"sensor{s}", {"ramp": 8, "sine": 4}, seed=s).root for s in (1, 2)]


@pytest.fixture(scope="module")
def local_fits(datasets) -> list[F.FitResult]:
    return [F.fit_dataset(d, F.FitConfig(workers=1, **CFG)) for d in datasets]


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with distributed.Client(cluster) as c:
            yield c


def _dask_fit(client, dataset: Path) -> F.FitResult:
    from touchreal.fitting.dask_executor import DaskExecutor

    return F.fit_dataset(dataset, F.FitConfig(**CFG), executor=DaskExecutor.factory(client))


def _fit_plugins(client) -> list[str]:
    """The fit plugins still installed on any worker."""
    return [p for names in client.run(lambda dask_worker: list(dask_worker.plugins)).values() for p in names if p.startswith("touchreal-fit-")]


def _assert_same_fit(a: F.FitResult, b: F.FitResult) -> None:
    assert list(a.classes) == list(b.classes)
    for c in a.classes:
        np.testing.assert_array_equal(a.classes[c].x, b.classes[c].x)  # bit-identical, not close
        assert [r.history for r in a.classes[c].runs] == [r.history for r in b.classes[c].runs]
        assert a.classes[c].evaluations == b.classes[c].evaluations
        assert a.params.classes[c] == b.params.classes[c]
        assert a.classes[c].train.as_dict() == b.classes[c].train.as_dict()


def test_dask_fit_is_bit_identical_to_the_local_fit(client, datasets, local_fits):
    res = _dask_fit(client, datasets[0])
    _assert_same_fit(res, local_fits[0])
    assert local_fits[0].classes["SA1"].generations == 2 * 3  # CMA-ES really ran (SA1: from its own and its saturated start)
    # the fit's worker plugin is gone afterwards; the workers carry no state of it
    assert not _fit_plugins(client)


def test_a_dataset_the_workers_cannot_read_is_a_clear_error(client, tmp_path):
    from touchreal.fitting.dask_executor import DaskExecutor

    with pytest.raises(ValueError, match="every worker must read the dataset"):
        DaskExecutor(client, F.FitSource(str(tmp_path / "not-there"), F.FitConfig(**CFG)))
    assert not _fit_plugins(client)


class KillOnce(distributed.WorkerPlugin):
    """Kills its worker process the first time a fit chunk starts executing (the nanny restarts it)."""

    def __init__(self, marker: str):
        self.marker = marker

    def transition(self, key, start, finish, **kwargs) -> None:
        if finish == "executing" and "_chunk_losses" in str(key):
            try:
                os.close(os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                return
            os._exit(1)


def test_a_worker_killed_mid_generation_is_survived(client, datasets, local_fits, tmp_path):
    from touchreal.fitting.dask_executor import DaskExecutor, _setup_error

    class Probe(DaskExecutor):
        """Before the fit's plugin goes: which workers hold the fit's state."""

        def close(self) -> None:
            client.wait_for_workers(2, timeout=60)
            self.workers = client.run(_setup_error, self.name)
            self.pids = client.run(os.getpid)
            super().close()

    probes: list[Probe] = []

    def probe(source, state) -> Probe:
        probes.append(Probe(client, source))
        return probes[-1]

    marker = tmp_path / "killed"
    pids = set(client.run(os.getpid).values())
    client.register_plugin(KillOnce(str(marker)), name="kill-once")
    try:
        res = F.fit_dataset(datasets[0], F.FitConfig(**CFG), executor=probe)
    finally:
        client.unregister_worker_plugin("kill-once")
    assert marker.exists()  # a worker process died while evaluating a chunk
    _assert_same_fit(res, local_fits[0])
    # the nanny restarted it during the fit, and the new worker got the fit's plugin and built the state
    assert len(probes[0].pids) == 2 and set(probes[0].pids.values()) != pids
    assert list(probes[0].workers.values()) == [None, None]


def test_cli_fits_several_datasets_on_one_cluster(client, datasets, local_fits, tmp_path):
    from touchreal.cli import main

    # SA1 alone: a class's fit does not depend on the other classes fitted with it
    recipe = tmp_path / "recipe.json"
    recipe.write_text(json.dumps(RECIPE))
    args = ["--classes", "SA1", "--recipe", str(recipe), "--seed", "1", "--no-holdout", "--quiet", "--scheduler", client.scheduler.address]
    assert main(["fit", *map(str, datasets), "--out", str(tmp_path), *args]) == 0
    for d, local in zip(datasets, local_fits):
        p = EncoderParams.load(tmp_path / f"{d.name}.json")
        mine, ref = p.classes["SA1"], local.params.classes["SA1"]
        assert set(p.classes) == {"SA1"} and mine.model_copy(update={"delay_ms": 0.0}) == ref.model_copy(update={"delay_ms": 0.0})
        # the file's alignment is set by the class with the largest lead: compare the reference-clock delay
        assert mine.delay_ms - p.alignment.lag_ms == pytest.approx(ref.delay_ms - local.params.alignment.lag_ms, abs=1e-9)
        assert p.provenance["dataset_dir"] == str(d.resolve())
    # several datasets need an existing output folder; the error is clear
    assert main(["fit", *map(str, datasets), "--out", str(tmp_path / "missing"), *args]) == 2
