"""TouchSim constants as arrays: the 17 single-unit models, receptor depths, skin and post-spike basis.

Read from the packaged ``touchreal/data/touchsim_constants.json`` (no ``../shared`` needed). The
17 models are kept in TouchSim's population order (SA1 0-3, RA 0-8, PC 0-3); every per-model array
below is indexed that way.

Parameter columns (``PARAMS[:, j]``), see also docs/reference-model.md:

====  ==========================================================================================
 j    meaning
====  ==========================================================================================
 0    input low-pass: 3rd-order Butterworth with normalised cutoff p0 * 4 / 1000 (10 * p0 Hz)
 1-2  weights of max(s, 0) and max(-s, 0) of the static (stress) input
 3-4  weights of max(d, 0) and max(-d, 0) of the dynamic input
 5-6  weights of the positive/negative part of the per-sample forward difference of d
 7    input saturation I_sat (I -> I_sat I / (I_sat + |I|) when > 0)
 8    noise standard deviation per 5 kHz sample (noisy runs)
 9    membrane time constant (samples of the 5 kHz update)
 10-11 weights of the two post-spike current basis functions
 12   conduction delay (ms), used only when delays are enabled
====  ==========================================================================================
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..settings import CLASSES, PACKAGE_DATA

CONSTANTS_PATH = PACKAGE_DATA / "touchsim_constants.json"

#: Number of parameter columns of one single-unit model.
N_COLUMNS = 13


@dataclass(frozen=True)
class TouchSimConstants:
    """Numeric constants of TouchSim's single-probe model (units in field comments)."""

    params: np.ndarray  # (17, 13) float64, columns as in the module docstring
    model_class: np.ndarray  # (17,) str, 'SA1' | 'RA' | 'PC'
    model_index: np.ndarray  # (17,) int, index of the model within its class
    class_of_model: np.ndarray  # (17,) int, index into CLASSES
    depth_mm: np.ndarray  # (3,) float64, receptor depth per class (mm), CLASSES order
    ihbasis: np.ndarray  # (2, L) float64, post-spike current basis, one value per 5 kHz sample
    youngs_modulus_mpa: float  # skin Young's modulus E (MPa)
    poisson_ratio: float  # skin Poisson ratio nu
    wave_velocity_mm_s: float  # surface wave velocity (mm/s)
    fs_hz: float  # LIF update rate (Hz)

    @property
    def n_models(self) -> int:
        return self.params.shape[0]

    def class_slice(self, cls: str) -> slice:
        """Models of class ``cls`` as a slice of the 17 (they are contiguous)."""
        idx = np.flatnonzero(self.model_class == cls)
        if idx.size == 0:
            raise KeyError(cls)
        return slice(int(idx[0]), int(idx[-1]) + 1)

    @property
    def model_depth_mm(self) -> np.ndarray:
        """(17,) receptor depth (mm) of every model."""
        return self.depth_mm[self.class_of_model]


def parse_constants(data: dict) -> TouchSimConstants:
    """Build :class:`TouchSimConstants` from the packaged JSON layout (``models``, ``ihbasis``, ...).

    The ``../shared/touchsim/constants.json`` layout (``parameters`` instead of ``models``,
    ``ihbasis`` as ``{'values': ...}``) is accepted too.
    """
    table = data["models"] if "models" in data else data["parameters"]
    rows, cls_names, index = [], [], []
    for cls in CLASSES:
        models = table[cls]
        for i, row in enumerate(models):
            if len(row) != N_COLUMNS:
                raise ValueError(f"{cls} model {i} has {len(row)} parameters, expected {N_COLUMNS}")
            rows.append(row)
            cls_names.append(cls)
            index.append(i)
    ihbasis = data["ihbasis"]
    if isinstance(ihbasis, dict):  # the ../shared layout stores {'values': ..., 'shape': ...}
        ihbasis = ihbasis["values"]
    skin = data["skin"]
    params = np.asarray(rows, dtype=np.float64)
    if not np.all(np.isfinite(params)):
        raise ValueError("non-finite model parameter")
    model_class = np.asarray(cls_names)
    return TouchSimConstants(
        params=params,
        model_class=model_class,
        model_index=np.asarray(index, dtype=np.int64),
        class_of_model=np.asarray([CLASSES.index(c) for c in cls_names], dtype=np.int64),
        depth_mm=np.asarray([data["afferent_depth_mm"][c] for c in CLASSES], dtype=np.float64),
        ihbasis=np.atleast_2d(np.asarray(ihbasis, dtype=np.float64)),
        youngs_modulus_mpa=float(skin["youngs_modulus"]),
        poisson_ratio=float(skin["poisson_ratio"]),
        wave_velocity_mm_s=float(skin["wave_velocity_mm_per_s"]),
        fs_hz=float(data.get("fs_hz", skin.get("sampling_rate_hz", 5000.0))),
    )


@lru_cache(maxsize=4)
def load_constants(path: str | Path | None = None) -> TouchSimConstants:
    """Load (and cache) the TouchSim constants; default: the packaged JSON file."""
    path = Path(path) if path is not None else CONSTANTS_PATH
    return parse_constants(json.loads(path.read_text()))
