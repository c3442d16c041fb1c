"""The PVDF stage's calibration for a fit, with the build's mains frequency found from the data.

:func:`touchreal.preprocess.gate.calibrate` notches the harmonics of the mains frequency it is given
and measures the gate's noise floor after the notches. A build on 60 Hz mains calibrated at 50 Hz
keeps its 60/120/180 Hz lines: they enter the gate's floor 10-60x above its median (weak-film-60hz),
so the gate removes real PVDF signal at those bins, in RA's and PC's band. :func:`calibrate_pvdf`
calibrates at 50 and at 60 Hz and keeps the one whose gate floor is flattest at the mains lines.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..params import PreprocessParams
from ..preprocess.gate import calibrate

MAINS_CANDIDATES_HZ = (50.0, 60.0)  #: mains frequencies a build may run on
RESIDUAL_HARMONICS = 9  #: harmonics (of every candidate) at which the residual floor is read


def mains_residual(pre: PreprocessParams, max_hz: float = 1000.0) -> float:
    """Mean log ratio of the calibrated gate's noise floor at every candidate's mains lines (below
    ``max_hz``) to its median: near 0 when the notches removed the lines, large when they were missed."""
    f = np.asarray(pre.gate.freqs_hz)
    asd = np.asarray(pre.gate.noise_asd)
    lines = sorted({k * m for m in MAINS_CANDIDATES_HZ for k in range(1, RESIDUAL_HARMONICS + 1) if k * m < max_hz})
    at = asd[np.abs(f[:, None] - np.asarray(lines)[None, :]).argmin(axis=0)]
    return float(np.mean(np.log(at / np.median(asd))))


def calibrate_pvdf(baselines: Sequence[np.ndarray], base: PreprocessParams, gate_factor: float | None = None) -> PreprocessParams:
    """``base`` calibrated on the contact-free PVDF ``baselines`` (V) at the mains frequency of
    :data:`MAINS_CANDIDATES_HZ` that leaves the flattest gate floor (``base.mains_hz`` on a tie),
    its gate keeping bins above ``gate_factor`` x the noise (default: ``base``'s factor)."""
    order = sorted(MAINS_CANDIDATES_HZ, key=lambda m: m != base.mains_hz)  # the given frequency first: it wins ties
    cals = [calibrate(baselines, base.model_copy(update={"mains_hz": m}), factor=gate_factor) for m in order]
    return min(cals, key=mains_residual)
