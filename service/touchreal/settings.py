"""One settings module: rates, class names and environment-derived paths.

Rates are in Hz, times in seconds unless a name says otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path

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


def shared_dir() -> Path:
    """Location of the shared data folder (``TOUCHREAL_SHARED``, default ``../shared``)."""
    return Path(os.environ.get("TOUCHREAL_SHARED", "../shared")).resolve()
