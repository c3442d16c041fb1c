"""Stateful causal filter stages: ``process(chunk) -> chunk`` with persistent state.

Chunks are (n, n_taxels) arrays on a regular grid. Feeding a signal in pieces of any size gives the
same output as feeding it whole, so the same code runs offline, online and in tests.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from functools import lru_cache

import numba
import numpy as np
from scipy import signal


@numba.njit(cache=True, nogil=True, inline="always")
def sos_step(sos, i, v, zi, g, m):  # pragma: no cover - compiled
    """One sample of ``m`` columns, ``v[:m]``, through the cascade ``sos[i]`` (sections, 6), a0 = 1,
    in place: transposed direct form II per section (scipy's sosfilt recursion), state
    ``zi[g, s, 0|1, j]`` updated in place. Sections outer, columns inner, so the columns' independent
    recursions run side by side (a caller with a constant ``m`` lets the compiler unroll them).
    Shared by the filter stages and the encoder's fused input kernel (which steps many cascades)."""
    for s in range(sos.shape[1]):
        b0, b1, b2, a1, a2 = sos[i, s, 0], sos[i, s, 1], sos[i, s, 2], sos[i, s, 4], sos[i, s, 5]
        for j in range(m):
            x = v[j]
            y = b0 * x + zi[g, s, 0, j]
            zi[g, s, 0, j] = b1 * x - a1 * y + zi[g, s, 1, j]
            zi[g, s, 1, j] = b2 * x - a2 * y
            v[j] = y


@numba.njit(cache=True, nogil=True)
def _sos_run(sos, x, zi, out):  # pragma: no cover - compiled
    """Every sample of every column through the cascade, state in place."""
    m = x.shape[1]
    v = np.empty(m, x.dtype)
    sos1 = sos.reshape((1,) + sos.shape)
    zi1 = zi.reshape((1,) + zi.shape)
    for i in range(x.shape[0]):
        for j in range(m):  # element loops: a slice copy per sample costs more than the filter
            v[j] = x[i, j]
        sos_step(sos1, 0, v, zi1, 0, m)
        for j in range(m):
            out[i, j] = v[j]


@lru_cache(maxsize=256)
def _unit_state(sos: bytes, n_sections: int, dtype: str) -> np.ndarray:
    """``sosfilt_zi`` of a cascade given as bytes (a filter built often, e.g. per woken taxel, designs it once), read-only."""
    zi = signal.sosfilt_zi(np.frombuffer(sos, np.dtype(dtype)).reshape(n_sections, 6)).astype(dtype)
    zi.flags.writeable = False
    return zi


class SosFilter:
    """A cascade of second-order sections with persistent ``zi`` (one state per taxel).

    Coefficients come from scipy (``butter``, ``iirnotch``, normalised to a0 = 1); the per-chunk
    recursion is scipy's ``sosfilt`` written as a numba kernel, because scipy's per-call overhead
    exceeded the rest of a 32 ms update for one taxel (tests check equality with ``sosfilt``).
    The state starts in steady state for ``initial`` (per taxel) or, by default, for the first
    sample's value, so a constant offset (e.g. a preload force) causes no start-up transient.
    """

    def __init__(self, sos: np.ndarray, n_taxels: int = 1, dtype: type = np.float64, initial: np.ndarray | None = None):
        self.dtype = np.dtype(dtype)
        sos = np.atleast_2d(np.asarray(sos, dtype=np.float64))
        sos = sos / sos[:, 3:4]  # a0 = 1
        self.sos = np.ascontiguousarray(sos.astype(self.dtype))
        self.n_taxels = n_taxels
        self._zi_unit = _unit_state(self.sos.tobytes(), self.sos.shape[0], self.dtype.str)  # (n_sections, 2)
        self.zi: np.ndarray | None = None
        if initial is not None:  # steady state at a known level instead of the first sample
            self.zi = np.ascontiguousarray(self._zi_unit[:, :, None] * np.broadcast_to(initial, (n_taxels,))[None, None, :])

    def process(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=self.dtype)
        if x.shape[0] == 0:
            return x.copy()
        if self.zi is None:
            self.zi = np.ascontiguousarray(self._zi_unit[:, :, None] * x[0][None, None, :])
        y = np.empty(x.shape, self.dtype)
        _sos_run(self.sos, np.ascontiguousarray(x), self.zi, y)
        return y

    def prime(self, history: np.ndarray) -> None:
        """Start from the state left by ``history`` (n, n_taxels), a stand-in for the unseen past
        (e.g. :func:`periodic_history`), itself entered in steady state for its first sample."""
        history = np.asarray(history, dtype=self.dtype)
        if history.shape[0] == 0:
            return
        self.zi = None
        self.process(history)

    @staticmethod
    def gather(parts: Sequence[tuple["SosFilter", np.ndarray]]) -> "SosFilter":
        """One filter over the columns ``idx`` of each part, in order (the same cascade; each
        column's state copied bit for bit). Parts must all have started (state set) or none."""
        first = parts[0][0]
        started = [f.zi is not None for f, _ in parts]
        if any(not np.array_equal(f.sos, first.sos) for f, _ in parts) or len(set(started)) > 1:
            raise ValueError("filters gathered into one must share their cascade and have all started, or none")
        out = copy.copy(first)
        out.n_taxels = sum(len(idx) for _, idx in parts)
        if started[0]:
            out.zi = np.ascontiguousarray(np.concatenate([f.zi[:, :, idx] for f, idx in parts], axis=2))
        return out

    def then(self, other: "SosFilter | None") -> "SosFilter":
        """One cascade: this filter followed by ``other`` (fresh state)."""
        if other is None:
            return SosFilter(self.sos, self.n_taxels, self.dtype)
        return SosFilter(np.vstack((self.sos, other.sos)), self.n_taxels, self.dtype)

    @property
    def state_norm(self) -> float:
        return 0.0 if self.zi is None else float(np.max(np.abs(self.zi)))


@lru_cache(maxsize=64)
def _butter_sos(cutoff_hz: float, fs_hz: float, order: int) -> np.ndarray:
    sos = signal.butter(order, cutoff_hz, btype="low", fs=fs_hz, output="sos")
    sos.flags.writeable = False
    return sos


def butter_lowpass(cutoff_hz: float, fs_hz: float, order: int, n_taxels: int = 1, dtype: type = np.float64) -> SosFilter:
    """Butterworth low-pass as a stateful :class:`SosFilter` (its design computed once per cutoff, rate and order)."""
    return SosFilter(_butter_sos(float(cutoff_hz), float(fs_hz), int(order)), n_taxels, dtype)


def periodic_history(block: np.ndarray, fs_hz: float, freqs_hz: Sequence[float], n_history: int) -> np.ndarray:
    """The ``n_history`` samples before ``block`` (n, n_taxels) predicted by a least-squares fit of a
    constant plus sinusoids at ``freqs_hz`` (e.g. mains hum) to the block.

    Priming a filter with it (:meth:`SosFilter.prime`) starts the filter in the steady state of the
    fitted interference, so notches remove hum from the first sample instead of ringing in over their
    settling time (about Q / (pi f): 0.2 s for a Q = 30 notch at 50 Hz). Frequencies at or above
    Nyquist are ignored; a block too short for every sinusoid is fitted with the constant alone.
    """
    x = np.asarray(block, dtype=np.float64)
    n = x.shape[0]
    if n == 0:
        raise ValueError("periodic_history needs at least one sample")
    f = [float(v) for v in freqs_hz if 0.0 < v < 0.5 * fs_hz]
    if n < 2 * len(f) + 2:
        f = []

    def basis(k: np.ndarray) -> np.ndarray:  # sample index k -> (len(k), 1 + 2 len(f))
        tt = k / fs_hz
        return np.column_stack([np.ones_like(tt)] + [g(2 * np.pi * v * tt) for v in f for g in (np.cos, np.sin)])

    coef, *_ = np.linalg.lstsq(basis(np.arange(n, dtype=np.float64)), x, rcond=None)
    return basis(np.arange(-n_history, 0, dtype=np.float64)) @ coef


HUM_PRIME_S = 0.1  #: stream start used to estimate the mains hum a filter is primed with (s)
HUM_HISTORY_S = 1.0  #: length of the synthetic past it is primed with (s; > 5 settling times of a Q = 30 notch at 50 Hz)


@lru_cache(maxsize=32)
def _hum_priming(sos: bytes, n_sections: int, dtype: str, fs_hz: float, freqs_hz: tuple[float, ...], n: int) -> np.ndarray:
    """(n_sections, 2, n): the filter state that priming with the :func:`periodic_history` of a block
    of ``n`` samples leaves, per unit sample of the block. Both steps are linear in the block (a
    least-squares fit, then the filter from its steady state for the first sample), so the state of
    any block is this operator applied to it: the fit and :data:`HUM_HISTORY_S` of filtering run once
    per cascade and block length, on the ``n`` unit blocks, instead of for every taxel at every start."""
    filt = SosFilter(np.frombuffer(sos, dtype).reshape(n_sections, 6), n, dtype)
    filt.prime(periodic_history(np.eye(n), fs_hz, freqs_hz, int(round(HUM_HISTORY_S * fs_hz))))
    return filt.zi


def prime_with_hum(filt: SosFilter, start: np.ndarray, fs_hz: float, freqs_hz: Sequence[float]) -> None:
    """Prime ``filt`` with the past predicted from ``start`` (the first :data:`HUM_PRIME_S` of a
    stream, (n, n_taxels)) by :func:`periodic_history` at the hum frequencies ``freqs_hz``: its state
    is set to what filtering that past would leave (:func:`_hum_priming`; equal up to rounding)."""
    x = np.asarray(start, dtype=np.float64)
    if x.shape[0] == 0:
        raise ValueError("periodic_history needs at least one sample")
    op = _hum_priming(filt.sos.tobytes(), filt.sos.shape[0], filt.dtype.str, float(fs_hz),
                      tuple(float(f) for f in freqs_hz), x.shape[0])
    filt.zi = np.ascontiguousarray(np.einsum("sck,kn->scn", op, x).astype(filt.dtype))


def mains_frequencies(mains_hz: float, harmonics: Sequence[int], fs_hz: float) -> list[float]:
    """The notched mains harmonics (Hz) below Nyquist, as :func:`mains_notches` builds them."""
    return [h * mains_hz for h in harmonics if 0 < h * mains_hz < 0.5 * fs_hz * 0.98]


def mains_notches(
    mains_hz: float, harmonics: list[int], q: float, fs_hz: float, n_taxels: int = 1, dtype: type = np.float64
) -> SosFilter | None:
    """Comb of IIR notches at the given mains harmonics (below Nyquist), as one SOS cascade."""
    sections = []
    for f in mains_frequencies(mains_hz, harmonics, fs_hz):
        b, a = signal.iirnotch(f, q, fs=fs_hz)
        sections.append(signal.tf2sos(b, a))
    if not sections:
        return None
    return SosFilter(np.vstack(sections), n_taxels, dtype)


@numba.njit(cache=True, nogil=True)
def _alpha_beta(z, x, v, alpha, beta, dt, out_x, out_v):  # pragma: no cover - compiled
    n, m = z.shape
    for i in range(n):
        for j in range(m):
            xp = x[j] + dt * v[j]
            r = z[i, j] - xp
            x[j] = xp + alpha * r
            v[j] = v[j] + beta / dt * r
            out_x[i, j] = x[j]
            out_v[i, j] = v[j]


class AlphaBeta:
    """Causal alpha-beta tracker: position ``x`` (signal unit) and rate ``v`` (unit/s).

    Prediction ``x + dt v``, correction with residual r: ``x += alpha r``, ``v += beta r / dt``.
    Stable for 0 < alpha <= 1 and 0 < beta < 4 - 2 alpha; starts at the first sample, at rest.
    """

    def __init__(self, alpha: float, beta: float, fs_hz: float, n_taxels: int = 1):
        if not (0 < alpha <= 1 and 0 < beta < 4 - 2 * alpha):
            raise ValueError(f"alpha-beta gains ({alpha}, {beta}) are outside the stable region")
        self.alpha, self.beta, self.dt = float(alpha), float(beta), 1.0 / fs_hz
        self.x: np.ndarray | None = None
        self.v = np.zeros(n_taxels)

    @staticmethod
    def gather(parts: Sequence[tuple["AlphaBeta", np.ndarray]]) -> "AlphaBeta":
        """One tracker over the columns ``idx`` of each part, in order (same gains; state copied).
        Parts must all have started or none."""
        first = parts[0][0]
        out = copy.copy(first)
        if len({ab.x is None for ab, _ in parts}) > 1:
            raise ValueError("trackers gathered into one must all have started, or none")
        out.v = np.concatenate([ab.v[idx] for ab, idx in parts])
        if first.x is not None:
            out.x = np.concatenate([ab.x[idx] for ab, idx in parts])
        return out

    def process(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = np.ascontiguousarray(z, dtype=np.float64)
        out_x, out_v = np.empty_like(z), np.empty_like(z)
        if z.shape[0] == 0:
            return out_x, out_v
        if self.x is None:
            self.x = z[0].copy()
        _alpha_beta(z, self.x, self.v, self.alpha, self.beta, self.dt, out_x, out_v)
        return out_x, out_v
