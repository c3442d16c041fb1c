"""Shared pytest fixtures: the ``../shared`` data folder and the rig-v1 dataset, and a module's real server.

Tests needing them are marked ``@pytest.mark.shared`` and skip with a clear reason when the folder
is missing.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_path() -> Path:
    """The shared data folder: :class:`touchreal.settings.ProcessSettings`' ``shared`` (TOUCHREAL_SHARED,
    default ``../shared``), relative to the repo root."""
    from touchreal.settings import ProcessSettings

    path = ProcessSettings().shared
    if not path.is_absolute():
        path = (REPO_ROOT / path).resolve()
    return path


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared data folder (:func:`shared_path`), or skip."""
    path = shared_path()
    if not path.is_dir():
        pytest.skip(f"shared data folder not found at {path}: set TOUCHREAL_SHARED to the ../shared folder")
    return path


@pytest.fixture(scope="session")
def rig(shared: Path):
    """The rig-v1 development dataset (:class:`touchreal.recording.Dataset`)."""
    from touchreal.recording import Dataset

    root = shared / "datasets" / "rig-v1"
    if not (root / "manifest.json").is_file():
        pytest.skip(f"rig-v1 dataset not found at {root}")
    return Dataset.open(root)


@pytest.fixture(scope="session")
def conformance(shared: Path):
    """(folder, stimulus entries) of TouchSim's conformance data; skips when it is missing."""
    import json

    root = shared / "touchsim" / "conformance"
    if not (root / "manifest.json").is_file():
        pytest.skip(f"TouchSim conformance data not found at {root}")
    return root, json.loads((root / "manifest.json").read_text())["stimuli"]


#: the corner of the documented build ranges (docs/fitting.md, "The limit"): half the film's coupling
#: on a 3x-noisy amplifier and SingleTact, the longest rig lag
CORNER_BUILD = {"name": "weak-noisy-film", "pvdf_coupling": 0.5, "pvdf_noise": 3.0, "st_noise": 3.0, "rig_lag_ms": 120.0}


@pytest.fixture
def corner_build(tmp_path: Path) -> Path:
    """A build file (``touchreal simulate --build FILE``) of :data:`CORNER_BUILD`."""
    import json

    path = tmp_path / f"{CORNER_BUILD['name']}.json"
    path.write_text(json.dumps(CORNER_BUILD))
    return path


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """(``host:port``, the service) of one real server (:func:`server_harness.running_server`) that the
    tests of a module share."""
    from server_harness import running_server

    with running_server(tmp_path_factory.mktemp("state")) as (addr, svc):
        yield addr, svc


@pytest.fixture
def nats_url():
    """The URL of a real nats-server on a free loopback port (skips where none is installed)."""
    yield from _nats_server()


@pytest.fixture
def nats_js_url():
    """A nats-server with JetStream (-js, a temporary store directory)."""
    yield from _nats_server(jetstream=True)


def _nats_server(**options):
    from server_harness import needs_nats_server

    from touchreal.bridge import natsd

    needs_nats_server()
    with natsd.local_nats_server(**options) as url:
        yield url


# -- leaving the test process ------------------------------------------------------------------------
# Servers under test run on daemon threads with native libraries loaded (onnxruntime, liblsl through
# pylsl, numba/LLVM). Now and then one of their C++ threads is still alive when the interpreter
# finalises, and the C++ runtime aborts the process ("terminate called without an active exception",
# exit 134) after every test has passed and been reported. Once pytest has reported everything, the
# process leaves with pytest's own exit status, without interpreter finalisation.
_EXIT_STATUS: list[int] = []


def pytest_sessionfinish(session, exitstatus) -> None:
    _EXIT_STATUS.append(int(exitstatus))


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config) -> None:
    if _EXIT_STATUS:
        import sys

        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])
