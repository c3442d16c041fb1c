"""Exponential-kernel sums of spike trains, the compiled core that the fit's objective
(:mod:`touchreal.fitting.objective`) and the evaluation's measures (:mod:`touchreal.analysis.spiketrains`)
share.

Spike times are in seconds; ``inv_tau`` is 1 / the kernel's time constant (1/s). The kernel is the
two-sided exponential ``k(d) = exp(-|d| / tau)``; a sum over all pairs of two sorted trains is exact
in O(n + m) with running sums over the merged trains (Houghton & Kreuz 2012). A set of trains is
held flat: ``flat`` (every train's times, each train sorted) and ``off`` (train k is
``flat[off[k]:off[k + 1]]``), as :func:`pack` makes it.
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np

#: epsilon of the paper's eq. (4) (the normalised kernel similarity's denominator)
SIM_EPS = 1e-12


@numba.njit(cache=True, nogil=True)
def kernel_sum_sorted(x, y, inv_tau):  # pragma: no cover - compiled
    """sum_i sum_j exp(-|x_i - y_j| * inv_tau) for sorted x, y (s), exactly, in O(n + m)."""
    n = x.shape[0]
    m = y.shape[0]
    if n == 0 or m == 0:
        return 0.0
    total = 0.0
    # forward: y_j <= x_i
    acc = 0.0
    last = 0.0
    j = 0
    for i in range(n):
        xi = x[i]
        while j < m and y[j] <= xi:
            if acc != 0.0:
                acc *= np.exp(-(y[j] - last) * inv_tau)
            acc += 1.0
            last = y[j]
            j += 1
        if acc != 0.0:
            total += acc * np.exp(-(xi - last) * inv_tau)
    # backward: y_j > x_i
    acc = 0.0
    last = 0.0
    j = m - 1
    for i in range(n - 1, -1, -1):
        xi = x[i]
        while j >= 0 and y[j] > xi:
            if acc != 0.0:
                acc *= np.exp(-(last - y[j]) * inv_tau)
            acc += 1.0
            last = y[j]
            j -= 1
        if acc != 0.0:
            total += acc * np.exp(-(last - xi) * inv_tau)
    return total


@numba.njit(cache=True, nogil=True)
def cross_sums_flat(x, flat, off, inv_tau, out):  # pragma: no cover - compiled
    """out[k] = kernel sum of the sorted train x with train k of a flat train set."""
    for k in range(off.shape[0] - 1):
        out[k] = kernel_sum_sorted(x, flat[off[k] : off[k + 1]], inv_tau)


@numba.njit(cache=True, nogil=True)
def auto_sums_flat(flat, off, inv_tau, out):  # pragma: no cover - compiled
    """out[k] = kernel sum of train k of a flat train set with itself (its A of eq. 3)."""
    for k in range(off.shape[0] - 1):
        t = flat[off[k] : off[k + 1]]
        out[k] = kernel_sum_sorted(t, t, inv_tau)


@numba.njit(cache=True, nogil=True)
def pair_matrix_flat(flat, off, inv_tau, out):  # pragma: no cover - compiled
    """out[a, b] = kernel sum of trains a and b of a flat train set (symmetric, diagonal included)."""
    n = off.shape[0] - 1
    for a in range(n):
        ta = flat[off[a] : off[a + 1]]
        for b in range(a, n):
            v = kernel_sum_sorted(ta, flat[off[b] : off[b + 1]], inv_tau)
            out[a, b] = v
            out[b, a] = v


def sorted_train(t: np.ndarray, presorted: bool = False) -> np.ndarray:
    """A train (s) as a contiguous 1-D float64 array, sorted unless ``presorted``."""
    t = np.asarray(t, dtype=np.float64).ravel()
    if not presorted:
        t = np.sort(t)
    return np.ascontiguousarray(t)


def pack(trains: Sequence[np.ndarray], presorted: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Flatten trains (s) into (times, offsets) with every train sorted; offsets has len(trains)+1."""
    arrs = [sorted_train(t, presorted) for t in trains]
    off = np.zeros(len(arrs) + 1, dtype=np.int64)
    if arrs:
        off[1:] = np.cumsum([a.size for a in arrs])
    flat = np.concatenate(arrs) if arrs and off[-1] > 0 else np.zeros(0)
    return np.ascontiguousarray(flat, dtype=np.float64), off
