"""The PVDF stage's calibration for a fit, with the build's mains frequency found from the data.

:func:`touchreal.preprocess.gate.calibrate` notches the harmonics of the mains frequency it is given
and measures the gate's noise floor after the notches. A build on 60 Hz mains calibrated at 50 Hz
keeps its 60/120/180 Hz lines: they enter the gate's floor 10-60x above its median (weak-film-60hz),
so the gate removes real PVDF signal at those bins, in RA's and PC's band. :func:`calibrate_pvdf`
calibrates at each of the parameters' ``mains_candidates_hz`` (50 and 60 Hz) and keeps the one whose
gate floor is flattest at the mains lines; a stream resolves its own among the same candidates
(:mod:`touchreal.preprocess.mains`).

:func:`contact_snr` measures how far the contact signal stands out of that floor, and
:func:`singletact_noise` the SingleTact's own noise on the same baselines: the two measures of a
build's profile (:mod:`.profile`) that the fit's policy reads (:mod:`.policy`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..params import PreprocessParams
from ..preprocess.gate import calibrate, filter_segments

RESIDUAL_HARMONICS = 9  #: harmonics (of every candidate) at which the residual floor is read


def mains_residual(pre: PreprocessParams, max_hz: float = 1000.0) -> float:
    """Mean log ratio of the calibrated gate's noise floor at every candidate's mains lines (below
    ``max_hz``) to its median: near 0 when the notches removed the lines, large when they were missed."""
    f = np.asarray(pre.gate.freqs_hz)
    asd = np.asarray(pre.gate.noise_asd)
    candidates = pre.mains_candidates_hz or [pre.mains_hz]
    lines = sorted({k * m for m in candidates for k in range(1, RESIDUAL_HARMONICS + 1) if k * m < max_hz})
    at = asd[np.abs(f[:, None] - np.asarray(lines)[None, :]).argmin(axis=0)]
    return float(np.mean(np.log(at / np.median(asd))))


def calibrate_pvdf(baselines: Sequence[np.ndarray], base: PreprocessParams) -> PreprocessParams:
    """``base`` calibrated on the contact-free PVDF ``baselines`` (V) at the mains frequency of
    ``base.mains_candidates_hz`` that leaves the flattest gate floor (``base.mains_hz`` on a tie)."""
    order = sorted(dict.fromkeys([base.mains_hz, *base.mains_candidates_hz]), key=lambda m: m != base.mains_hz)  # the given frequency first: it wins ties
    cals = [calibrate(baselines, base.model_copy(update={"mains_hz": m})) for m in order]
    return min(cals, key=mains_residual)


def noise_rms(pre: PreprocessParams) -> float:
    """RMS (V) of the calibrated PVDF noise after the low-pass and notches: the gate's noise floor
    summed over its evenly spaced bins."""
    f = np.asarray(pre.gate.freqs_hz)
    return float(np.sqrt(np.sum(np.asarray(pre.gate.noise_asd) ** 2) * (f[1] - f[0])))


def contact_snr(pvdf: Sequence[np.ndarray], onsets: Sequence[int], pre: PreprocessParams, fs_hz: float = 2000.0) -> float | None:
    """The PVDF contact signal over the calibrated noise: the 99th percentile of |PVDF| (after the
    calibrated low-pass and notches) from each recording's contact onset (sample index) on, over the
    noise RMS (:func:`noise_rms`). ``pvdf``: whole ramp recordings (V), filtered from their start as
    the pipeline filters a stream. None without contact samples."""
    contact = [y[i:] for y, i in zip(filter_segments(pvdf, pre, fs_hz), onsets)]
    contact = [c for c in contact if c.size]
    if not contact:
        return None
    return float(np.percentile(np.abs(np.concatenate(contact)), 99.0)) / noise_rms(pre)


def singletact_noise(baselines: Sequence[np.ndarray]) -> float | None:
    """The SingleTact's sample noise (N RMS) on contact-free baselines (N): per baseline the RMS of
    successive differences over sqrt(2) (blind to a slow drift), the median over baselines. None
    without a baseline of at least three samples."""
    rms = [np.sqrt(np.mean(np.diff(b) ** 2) / 2.0) for b in baselines if b.size >= 3]
    return float(np.median(rms)) if rms else None
