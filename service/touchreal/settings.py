"""One settings module: rates and class names, and :class:`ProcessSettings`, what every command reads
from its environment.

Rates are in Hz, times in seconds unless a name says otherwise.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

#: Afferent classes, in the order used for every (..., 3) array in the package.
CLASSES: tuple[str, ...] = ("SA1", "RA", "PC")

#: The four encoder input channels, in the order of every (..., 4) array.
CHANNELS: tuple[str, ...] = ("ST", "dST", "PVDF", "dPVDF")

ST_FS_HZ = 100.0  #: SingleTact sample rate
PVDF_FS_HZ = 2000.0  #: PVDF sample rate
OUT_FS_HZ = 5000.0  #: encoder (TouchSim) rate

ST_RANGE_N = (0.0, 10.0)  #: SingleTact force range
ST_RESOLUTION_N = 0.01  #: SingleTact quantisation step
PVDF_RANGE_V = (-1.65, 1.65)  #: PVDF ADC range around the bias point

DEFAULT_WINDOW_MS = 128.0  #: causal PVDF analysis window
DEFAULT_UPDATE_MS = 32.0  #: online update interval

PACKAGE_DATA = Path(__file__).resolve().parent / "data"


class ProcessSettings(BaseSettings):
    """Settings of every ``touchreal`` command, read from the environment (``TOUCHREAL_<NAME>``)."""

    model_config = SettingsConfigDict(env_prefix="TOUCHREAL_", extra="ignore")

    threads: int | None = Field(default=None, ge=0, le=256, description="threads of the large kernels (1 or 0: no "
                                "thread pool); unset: the CPUs this process may run on, at most 4")
    shared: Path = Field(default=Path("../shared"), description="the shared data folder (the paper's rig "
                         "recordings, TouchSim conformance data) that tests and benchmarks read when present")


def shared_dir() -> Path:
    """The shared data folder (:attr:`ProcessSettings.shared`), absolute."""
    return ProcessSettings().shared.resolve()
