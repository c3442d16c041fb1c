"""Causal PCHIP resampling of a knot stream onto the absolute 5 kHz output grid.

Output sample k is at ``k / fs_out`` on the recording clock. A point between knots i and i+1 needs
the PCHIP slopes at both, which depend on knots i-1 ... i+2, so output lags the newest knot by one
knot interval (buffering). Points are evaluated only inside intervals whose four knots are known,
so the result does not depend on how the knots were chunked.

The interpolant is scipy's ``PchipInterpolator`` (Fritsch-Carlson slopes with the weighted harmonic
mean at interior knots), evaluated here by a small numba kernel because constructing scipy's object
for every 32 ms update cost more than the rest of the pipeline; tests check equality with scipy to
1e-12.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .parallel import split_run


def first_grid_index(t_s: float, fs_hz: float) -> int:
    """The first index k of the grid ``k / fs_hz`` with ``k / fs_hz >= t_s``."""
    k = math.ceil(t_s * fs_hz)
    return k if k / fs_hz >= t_s else k + 1


class CausalPchip:
    """Stateful PCHIP resampler for (m, n_cols) knots with increasing times (s)."""

    def __init__(self, fs_out_hz: float, n_cols: int = 1):
        self.fs_out = float(fs_out_hz)
        self.n_cols = n_cols
        self._t = np.zeros(0)
        self._y = np.zeros((0, n_cols))
        self.next_k: int | None = None  # next output grid index to emit

    def process(self, t: np.ndarray, y: np.ndarray) -> tuple[int, np.ndarray]:
        """Add knots; return (first grid index, (T, n_cols) values) of the newly final points."""
        t_all = np.concatenate((self._t, np.asarray(t, dtype=np.float64)))
        y_all = np.concatenate((self._y, np.asarray(y, dtype=np.float64).reshape(-1, self.n_cols)))
        if self.next_k is None and t_all.size >= 2:
            self.next_k = first_grid_index(float(t_all[1]), self.fs_out)
        out = self._emit(t_all, y_all, end_s=t_all[-2] if t_all.size >= 4 else None)
        self._t, self._y = t_all[-3:], y_all[-3:]
        return out

    def finish(self, until_s: float) -> tuple[int, np.ndarray]:
        """End of stream: hold the last value for two more knots and emit points before ``until_s``."""
        if self._t.size < 2 or self.next_k is None:
            return (self.next_k or 0), np.zeros((0, self.n_cols))
        dt = self._t[-1] - self._t[-2]
        t_all = np.concatenate((self._t, self._t[-1] + dt * np.array([1.0, 2.0])))
        y_all = np.concatenate((self._y, np.repeat(self._y[-1:], 2, axis=0)))
        return self._emit(t_all, y_all, end_s=min(until_s, t_all[-2]))

    def _emit(self, t_all: np.ndarray, y_all: np.ndarray, end_s: float | None) -> tuple[int, np.ndarray]:
        k0 = self.next_k if self.next_k is not None else 0
        if end_s is None or self.next_k is None:
            return k0, np.zeros((0, self.n_cols))
        tk = np.arange(k0, max(k0, math.ceil(end_s * self.fs_out) + 1)) / self.fs_out
        tk = tk[tk < end_s]  # emit exactly the grid points before end_s
        if tk.size == 0:
            return k0, np.zeros((0, self.n_cols))
        k_end = k0 + tk.size
        values = pchip_eval(t_all, y_all, tk)
        self.next_k = k_end
        return k0, values



@numba.njit(cache=True, nogil=True)
def _pchip_eval(x, y, t, out, a, b):  # pragma: no cover - compiled
    """Columns a ... b - 1: slopes at the interior knots (weighted harmonic mean, 0 at extrema),
    then per interval the cubic's coefficients once and Horner at the interval's points."""
    m = y.shape[0]
    w = b - a
    d = np.zeros((m, w))
    for j in range(1, m - 1):
        h0, h1 = x[j] - x[j - 1], x[j + 1] - x[j]
        w1, w2 = 2 * h1 + h0, h1 + 2 * h0
        for c in range(w):
            m0 = (y[j, a + c] - y[j - 1, a + c]) / h0
            m1 = (y[j + 1, a + c] - y[j, a + c]) / h1
            if m0 == 0.0 or m1 == 0.0 or (m0 > 0.0) != (m1 > 0.0):
                d[j, c] = 0.0
            else:
                d[j, c] = 1.0 / ((w1 / m0 + w2 / m1) / (w1 + w2))
    c2 = np.empty(w)
    c3 = np.empty(w)
    n_t = t.shape[0]
    k = 0
    i = 1
    while k < n_t:
        while x[i + 1] <= t[k]:
            i += 1
        h = x[i + 1] - x[i]
        for c in range(w):
            slope = (y[i + 1, a + c] - y[i, a + c]) / h
            c2[c] = (3 * slope - 2 * d[i, c] - d[i + 1, c]) / h
            c3[c] = (d[i, c] + d[i + 1, c] - 2 * slope) / (h * h)
        while k < n_t and t[k] < x[i + 1]:
            s = t[k] - x[i]
            for c in range(w):
                out[k, a + c] = y[i, a + c] + s * (d[i, c] + s * (c2[c] + s * c3[c]))
            k += 1


def pchip_eval(x: np.ndarray, y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Evaluate the PCHIP interpolant of knots (x, y) at increasing ``t``, all within [x[1], x[-2]);
    the columns of a large call run on both cores (:func:`~touchreal.preprocess.parallel.split_run`)."""
    out = np.empty((t.shape[0], y.shape[1]))
    x, y, t = np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64), np.ascontiguousarray(t)
    split_run(lambda a, b: _pchip_eval(x, y, t, out, a, b), y.shape[1], y.shape[1] * (t.shape[0] + y.shape[0]))
    return out
