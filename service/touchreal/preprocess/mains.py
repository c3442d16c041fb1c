"""The mains frequency of a source, resolved once from its first PVDF samples (sans-I/O).

A parameter set notches the harmonics ``notch_harmonics`` of one mains frequency (``mains_hz``,
found by the fit's calibration on the dataset it was fitted on). A source on the other mains keeps
its hum: at 60 Hz the 50 Hz notches leave 60, 180, 300 ... Hz in the PVDF, where the spectral gate
passes them to RA and PC. :class:`MainsResolver` looks at the stream's first :data:`HUM_PRIME_S`
(the samples the PVDF filter is primed on) and keeps ``mains_hz`` unless another of
``mains_candidates_hz`` clearly carries the hum:

* per candidate, the least-squares fit of a constant plus sinusoids at its notched harmonics (the
  same harmonic numbers) to every taxel's samples; the *line energy* is what the sinusoids explain
  beyond the constant (V^2, summed over taxels). 0.1 s at 2 kHz holds whole periods of every
  multiple of 10 Hz, so the 50 and 60 Hz sets are orthogonal;
* another candidate wins when its line energy exceeds the configured one's by :data:`LINE_RATIO` and
  at least :data:`MIN_LINES` of its lines stand :data:`LINE_RATIO` above the residual noise per
  degree of freedom (the same 10 dB the calibration asks of a harmonic before it notches it): hum
  is a comb of harmonics, a contact's vibration at one of them is one line. Noise alone, or a
  contact, does not move the choice; a hum of either frequency does, from its first tenth of a
  second.

The choice is made once per stream (every taxel block and every branch restart uses it), so the
output does not depend on how the samples are chunked.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..params import PreprocessParams
from .filters import HUM_PRIME_S, mains_frequencies

LINE_RATIO = 10.0  #: how far (energy ratio) a candidate's lines must stand out to move the choice
MIN_LINES = 2  #: hum is a comb: one line alone (a vibration at one harmonic of the other frequency) is not hum
MAX_TAXELS = 256  #: taxels the fit reads at most (a 65,536-taxel skin's start: ~0.4 GB and 0.3 s at once otherwise)


def line_energies(x: np.ndarray, fs_hz: float, freqs_hz: Sequence[float]) -> tuple[np.ndarray, float]:
    """(energy of each line (len(freqs_hz),), residual energy per degree of freedom) of samples ``x``
    (n, N) fitted with a constant plus sinusoids at ``freqs_hz`` per column (V^2, summed over columns).
    A line's energy is its fitted sinusoids' (cos and sin), exact when the lines are orthogonal over
    the window (whole periods)."""
    n, m = x.shape
    tt = np.arange(n) / fs_hz
    basis = np.column_stack([np.ones(n)] + [g(2 * np.pi * f * tt) for f in freqs_hz for g in (np.cos, np.sin)])
    coef, *_ = np.linalg.lstsq(basis, x, rcond=None)
    resid = x - basis @ coef
    lines = np.array([np.sum((basis[:, 1 + 2 * i : 3 + 2 * i] @ coef[1 + 2 * i : 3 + 2 * i]) ** 2)
                      for i in range(len(freqs_hz))])
    return lines, float(np.sum(resid**2)) / max(1, (n - basis.shape[1]) * m)


def _stride(n_taxels: int) -> int:
    """Every how many taxels one is read, so that at most :data:`MAX_TAXELS` are."""
    return max(1, -(-n_taxels // MAX_TAXELS))


def resolve_mains(start: np.ndarray, params: PreprocessParams, fs_hz: float) -> float:
    """The mains frequency (Hz) of a stream whose first PVDF samples are ``start`` (n, N; V): the
    configured ``params.mains_hz`` unless another of ``params.mains_candidates_hz`` carries the hum
    (module docstring)."""
    x = np.asarray(start, dtype=np.float64)
    chosen = float(params.mains_hz)
    if x.ndim != 2 or x.shape[0] < 2 or not params.notch_harmonics:
        return chosen
    x = x[:, :: _stride(x.shape[1])]  # one mains for the whole source: evenly spaced taxels suffice
    fits = {}
    for f in dict.fromkeys([chosen, *map(float, params.mains_candidates_hz)]):
        lines = mains_frequencies(f, params.notch_harmonics, fs_hz)
        if lines and x.shape[0] > 2 * len(lines) + 1:
            fits[f] = line_energies(x, fs_hz, lines)
    if chosen not in fits:
        return chosen
    best = max(fits, key=lambda f: fits[f][0].sum())
    energies, floor = fits[best]
    standing = int(np.sum(energies / (2 * x.shape[1]) > LINE_RATIO * floor))  # lines 10x above the noise per dof
    if best != chosen and energies.sum() > LINE_RATIO * fits[chosen][0].sum() and standing >= MIN_LINES:
        return best
    return chosen


class MainsResolver:
    """Collects a stream's first :data:`HUM_PRIME_S` of sanitized PVDF and resolves its mains once
    (:func:`resolve_mains`); :attr:`hz` is None until then. ``hz``: the mains already resolved on
    this source (a pipeline that restarts after shedding load: the source's hum did not change)."""

    def __init__(self, params: PreprocessParams, fs_hz: float, hz: float | None = None):
        self.params = params
        self.fs_hz = fs_hz
        self.n_start = int(round(HUM_PRIME_S * fs_hz))
        self._start: list[np.ndarray] = []
        self._held = 0
        self.hz: float | None = hz

    def push(self, x: np.ndarray) -> None:
        """The stream's next sanitized PVDF samples (n, N); resolves once :data:`HUM_PRIME_S` arrived."""
        if self.hz is not None or x.shape[0] == 0:
            return
        self._start.append(x[: self.n_start - self._held, :: _stride(x.shape[1])])
        self._held += self._start[-1].shape[0]
        if self._held >= self.n_start:
            self.resolve()

    def resolve(self) -> float:
        """The resolved frequency (Hz), resolving now on the samples held if not yet done (a stream
        that ends before :data:`HUM_PRIME_S`)."""
        if self.hz is None:
            start = np.concatenate(self._start) if self._start else np.zeros((0, 1))
            self.hz = resolve_mains(start, self.params, self.fs_hz)
            self._start = []
        return self.hz
