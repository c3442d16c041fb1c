"""Calibration of the PVDF stage from contact-free baseline recordings.

Two things are measured on baseline PVDF (V, 2 kHz) and stored in the parameter file:

* which mains harmonics stand out of the noise floor (only those get a notch, so a stimulus at an
  even multiple of 50 Hz is not notched away when the hum has only odd harmonics);
* the noise amplitude spectral density after the low-pass and notches, from which the spectral
  gate's per-bin thresholds follow for any window length (:func:`gate_thresholds`).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
from scipy import signal

from ..params import GateCalibration, PreprocessParams
from .filters import HUM_PRIME_S, SosFilter, butter_lowpass, mains_frequencies, mains_notches, prime_with_hum

_PVDF_LP_ORDER = 4
_WELCH_SEG = 256
_LINE_RATIO = 10.0  # a harmonic is notched when its PSD is 10x (10 dB) the local floor


def _welch(segments: Sequence[np.ndarray], fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean one-sided PSD (V^2/Hz) over segments, weighted by their number of Welch frames."""
    total, weight, freqs = None, 0.0, None
    for seg in segments:
        seg = np.asarray(seg, dtype=np.float64)
        if seg.size < _WELCH_SEG:
            continue
        freqs, psd = signal.welch(seg, fs=fs_hz, nperseg=_WELCH_SEG)
        w = (seg.size - _WELCH_SEG) // (_WELCH_SEG // 2) + 1
        total = psd * w if total is None else total + psd * w
        weight += w
    if total is None:
        raise ValueError(f"calibration needs at least one baseline segment of {_WELCH_SEG} samples")
    return freqs, total / weight


@lru_cache(maxsize=64)
def _pvdf_sos(lowpass_hz: float, fs_hz: float, mains_hz: float | None, harmonics: tuple[int, ...], q: float) -> np.ndarray:
    """The PVDF cascade's sections (a stream that wakes taxels builds it often); ``mains_hz`` None: no notches."""
    filt = butter_lowpass(lowpass_hz, fs_hz, _PVDF_LP_ORDER)
    if mains_hz is not None:
        filt = filt.then(mains_notches(mains_hz, list(harmonics), q, fs_hz))
    filt.sos.flags.writeable = False
    return filt.sos


def pvdf_filter(params: PreprocessParams, fs_hz: float, n_taxels: int = 1, dtype: type = np.float64, notch: bool = True) -> SosFilter:
    """The PVDF cascade: Butterworth low-pass, then (with ``notch``) the mains notch comb."""
    sos = _pvdf_sos(params.pvdf_lowpass_hz, fs_hz, params.mains_hz if notch else None, tuple(params.notch_harmonics), params.notch_q)
    return SosFilter(sos, n_taxels, dtype)


def filter_segments(segments: Sequence[np.ndarray], params: PreprocessParams, fs_hz: float, notch: bool = True) -> list[np.ndarray]:
    """Each PVDF segment (V) through the pipeline's PVDF filters (with the notches or not), primed
    as the pipeline primes them at stream start."""
    out = []
    n_prime = int(round(HUM_PRIME_S * fs_hz))
    hum = mains_frequencies(params.mains_hz, params.notch_harmonics, fs_hz) if notch else []
    for seg in segments:
        x = np.asarray(seg, dtype=np.float64)[:, None]
        filt = pvdf_filter(params, fs_hz, notch=notch)
        if x.shape[0]:
            prime_with_hum(filt, x[:n_prime], fs_hz, hum)
        out.append(filt.process(x)[:, 0])
    return out


def detect_harmonics(freqs: np.ndarray, psd: np.ndarray, mains_hz: float, fs_hz: float) -> list[int]:
    """Mains harmonics whose PSD peak exceeds the surrounding floor by :data:`_LINE_RATIO`."""
    found = []
    df = freqs[1] - freqs[0]
    for h in range(1, int(0.5 * fs_hz / mains_hz)):
        f = h * mains_hz
        near = np.abs(freqs - f) <= 1.5 * df
        ring = (np.abs(freqs - f) > 3 * df) & (np.abs(freqs - f) <= 8 * df)
        if near.any() and ring.any() and psd[near].max() > _LINE_RATIO * np.median(psd[ring]):
            found.append(h)
    return found


def calibrate(pvdf_baselines: Sequence[np.ndarray], params: PreprocessParams, fs_hz: float = 2000.0) -> PreprocessParams:
    """Return ``params`` with ``notch_harmonics`` and ``gate`` measured on baseline PVDF segments (V)."""
    lp_only = filter_segments(pvdf_baselines, params, fs_hz, notch=False)
    freqs, psd = _welch(lp_only, fs_hz)
    harmonics = detect_harmonics(freqs, psd, params.mains_hz, fs_hz)
    notched_params = params.model_copy(update={"notch_harmonics": harmonics})
    freqs, psd = _welch(filter_segments(pvdf_baselines, notched_params, fs_hz, notch=True), fs_hz)
    factor = params.gate.factor if params.gate else GateCalibration.model_fields["factor"].default
    attenuation = params.gate.attenuation if params.gate else GateCalibration.model_fields["attenuation"].default
    gate = GateCalibration(
        freqs_hz=[float(f) for f in freqs],
        noise_asd=[float(a) for a in np.sqrt(psd)],
        factor=factor,
        attenuation=attenuation,
    )
    return params.model_copy(update={"notch_harmonics": harmonics, "gate": gate})


def gate_thresholds(gate: GateCalibration, window: np.ndarray, fs_hz: float) -> np.ndarray:
    """Per-bin magnitude thresholds (V) for frames windowed by ``window``.

    For noise of one-sided PSD S(f), a windowed frame's rfft has E|X(f)|^2 = S(f) fs sum(w^2) / 2;
    the threshold is ``factor`` times its square root, S interpolated at the frame's bins.
    """
    n = window.size
    bins = np.fft.rfftfreq(n, 1.0 / fs_hz)
    asd = np.interp(bins, gate.freqs_hz, gate.noise_asd)
    return gate.factor * asd * np.sqrt(fs_hz * np.sum(window**2) / 2.0)
