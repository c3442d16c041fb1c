"""Causal PCHIP resampling of a knot stream onto the absolute 5 kHz output grid.

Output sample k is at ``k / fs_out`` on the recording clock. A point between knots i and i+1 needs
the PCHIP slopes at both, which depend on knots i-1 ... i+2, so output lags the newest knot by one
knot interval (buffering). Points are evaluated only inside intervals whose four knots are known,
so the result does not depend on how the knots were chunked.

The interpolant is scipy's ``PchipInterpolator`` (Fritsch-Carlson slopes with the weighted harmonic
mean at interior knots), evaluated here by a small numba kernel because constructing scipy's object
for every 32 ms update cost more than the rest of the pipeline; tests check equality with scipy to
1e-12. Values (knots, slopes, coefficients, output) are in the resampler's ``dtype`` (float64 or
float32); times stay float64 (seconds on the recording clock need it) and enter the arithmetic only
as knot intervals and offsets within an interval, rounded to ``dtype``.
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
    """Stateful PCHIP resampler for (m, n_cols) knots with increasing times (s), values in ``dtype``."""

    def __init__(self, fs_out_hz: float, n_cols: int = 1, dtype: type = np.float64):
        self.fs_out = float(fs_out_hz)
        self.n_cols = n_cols
        self.dtype = np.dtype(dtype)
        self._t = np.zeros(0)
        self._y = np.zeros((0, n_cols), self.dtype)
        self.next_k: int | None = None  # next output grid index to emit

    @staticmethod
    def gather(parts: "list[tuple[CausalPchip, np.ndarray]]", groups: int = 1) -> "CausalPchip":
        """One resampler over the columns ``idx`` of each part, in order, where a part's columns
        are ``groups`` consecutive groups of its taxels (e.g. value and rate) and ``idx`` picks taxels:
        the result keeps the group layout. Parts must hold the same knot times (fed the same samples)."""
        first = parts[0][0]
        if any(p.next_k != first.next_k or not np.array_equal(p._t, first._t) for p, _ in parts):
            raise ValueError("resamplers gathered into one must hold the same knots")
        n = sum(len(idx) for _, idx in parts)
        out = CausalPchip(first.fs_out, groups * n, first.dtype)
        out._t, out.next_k = first._t.copy(), first.next_k
        cols = [p._y[:, g * (p.n_cols // groups) + idx] for g in range(groups) for p, idx in parts]
        out._y = np.concatenate(cols, axis=1) if cols else out._y
        return out

    def process(self, t: np.ndarray, y: np.ndarray) -> tuple[int, np.ndarray]:
        """Add knots; return (first grid index, (T, n_cols) values) of the newly final points."""
        t_all = np.concatenate((self._t, np.asarray(t, dtype=np.float64)))
        y_all = np.concatenate((self._y, np.asarray(y, dtype=self.dtype).reshape(-1, self.n_cols)))
        if self.next_k is None and t_all.size >= 2:
            self.next_k = first_grid_index(float(t_all[1]), self.fs_out)
        out = self._emit(t_all, y_all, end_s=t_all[-2] if t_all.size >= 4 else None)
        self._t, self._y = t_all[-3:], y_all[-3:]
        return out

    def finish(self, until_s: float) -> tuple[int, np.ndarray]:
        """End of stream: hold the last value for two more knots and emit points before ``until_s``."""
        if self._t.size < 2 or self.next_k is None:
            return (self.next_k or 0), np.zeros((0, self.n_cols), self.dtype)
        dt = self._t[-1] - self._t[-2]
        t_all = np.concatenate((self._t, self._t[-1] + dt * np.array([1.0, 2.0])))
        y_all = np.concatenate((self._y, np.repeat(self._y[-1:], 2, axis=0)))
        return self._emit(t_all, y_all, end_s=min(until_s, t_all[-2]))

    def _emit(self, t_all: np.ndarray, y_all: np.ndarray, end_s: float | None) -> tuple[int, np.ndarray]:
        k0 = self.next_k if self.next_k is not None else 0
        if end_s is None or self.next_k is None:
            return k0, np.zeros((0, self.n_cols), self.dtype)
        tk = np.arange(k0, max(k0, math.ceil(end_s * self.fs_out) + 1)) / self.fs_out
        tk = tk[tk < end_s]  # emit exactly the grid points before end_s
        if tk.size == 0:
            return k0, np.zeros((0, self.n_cols), self.dtype)
        k_end = k0 + tk.size
        values = pchip_eval(t_all, y_all, tk)
        self.next_k = k_end
        return k0, values



@numba.njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf (discarded), no exception
def _pchip_eval(h, y, idx, s, one, out, a, b):  # pragma: no cover - compiled
    """Columns a ... b - 1: slopes at the interior knots (weighted harmonic mean, 0 at extrema),
    then per interval the cubic's coefficients once (secants computed once) and Horner at the interval's points. ``h``:
    knot intervals, ``s``: each point's offset from its interval's knot ``idx``; all arithmetic is
    in the dtype of ``y``, the dtype of ``one`` (constants are built from it, so float32 never widens)."""
    m = y.shape[0]
    w = b - a
    two = one + one
    three = two + one
    zero = one - one
    delta = np.empty((m - 1, w), y.dtype)  # secant slope of every interval
    for j in range(m - 1):
        hj = h[j]
        for c in range(w):
            delta[j, c] = (y[j + 1, a + c] - y[j, a + c]) / hj
    d = np.zeros((m, w), y.dtype)
    for j in range(1, m - 1):
        h0, h1 = h[j - 1], h[j]
        w1, w2 = two * h1 + h0, h1 + two * h0
        for c in range(w):  # branch-free, so that it vectorises: the mean is discarded where it is not used
            m0, m1 = delta[j - 1, c], delta[j, c]
            mean = one / ((w1 / m0 + w2 / m1) / (w1 + w2))
            d[j, c] = mean if (m0 > zero and m1 > zero) or (m0 < zero and m1 < zero) else zero
    c2 = np.empty(w, y.dtype)
    c3 = np.empty(w, y.dtype)
    n_t = s.shape[0]
    k = 0
    while k < n_t:
        i = idx[k]
        hi = h[i]
        for c in range(w):
            slope = delta[i, c]
            c2[c] = (three * slope - two * d[i, c] - d[i + 1, c]) / hi
            c3[c] = (d[i, c] + d[i + 1, c] - two * slope) / (hi * hi)
        while k < n_t and idx[k] == i:
            sk = s[k]
            for c in range(w):
                out[k, a + c] = y[i, a + c] + sk * (d[i, c] + sk * (c2[c] + sk * c3[c]))
            k += 1


def pchip_eval(x: np.ndarray, y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Evaluate the PCHIP interpolant of knots (x [s, float64], y) at increasing ``t`` (s), all within
    [x[1], x[-2]), in the dtype of ``y`` (float64 or float32); the columns of a large call run on
    both cores (:func:`~touchreal.preprocess.parallel.split_run`)."""
    y = np.ascontiguousarray(y)
    if y.dtype not in (np.float64, np.float32):
        y = y.astype(np.float64)
    x, t = np.asarray(x, np.float64), np.asarray(t, np.float64)
    idx = np.searchsorted(x, t, side="right") - 1  # the interval [x[i], x[i + 1]) of each point
    h = np.diff(x).astype(y.dtype)
    s = (t - x[idx]).astype(y.dtype)
    out = np.empty((t.shape[0], y.shape[1]), y.dtype)
    one = y.dtype.type(1)
    split_run(lambda a, b: _pchip_eval(h, y, idx, s, one, out, a, b), y.shape[1], y.shape[1] * (t.shape[0] + y.shape[0]))
    return out
