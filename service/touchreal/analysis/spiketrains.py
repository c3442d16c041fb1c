"""Spike-train measures: exponential-kernel sums, the van Rossum distance, the paper's normalised
kernel distance (eqs. 2-5), and firing rates / PSTHs.

All spike times are in seconds and every train is a 1-D float array. Functions sort their inputs
unless told the trains are already sorted.

Kernel sums use the two-sided exponential ``k(d) = exp(-|d| / tau)`` and are computed exactly in
O(n + m) by :mod:`touchreal.spike_kernels` (shared with the fit's objective); they are checked
against brute force and against ``elephant`` in tests/test_analysis_spiketrains.py.

Van Rossum normalisation: ``vr_distance`` follows ``elephant.spike_train_dissimilarity``:
``D = sqrt(A(x) + A(y) - 2 C(x, y))``, which is 1 between an empty train and a one-spike train
(van Rossum's 2001 paper divides this by sqrt(2)).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..spike_kernels import SIM_EPS, auto_sums_flat, cross_sums_flat, kernel_sum_sorted, pack, pair_matrix_flat, sorted_train


def kernel_sum(x: np.ndarray, y: np.ndarray, tau: float, presorted: bool = False) -> float:
    """``sum_i sum_j exp(-|x_i - y_j| / tau)`` (eqs. 2-3); ``A(x) = kernel_sum(x, x)``."""
    if tau <= 0:
        raise ValueError("tau must be > 0")
    return float(kernel_sum_sorted(sorted_train(x, presorted), sorted_train(y, presorted), 1.0 / tau))


def kernel_sum_bruteforce(x: np.ndarray, y: np.ndarray, tau: float) -> float:
    """Reference O(n m) implementation (tests only)."""
    x = np.asarray(x, np.float64).ravel()
    y = np.asarray(y, np.float64).ravel()
    if x.size == 0 or y.size == 0:
        return 0.0
    return float(np.exp(-np.abs(x[:, None] - y[None, :]) / tau).sum())


def similarity_from_sums(c: np.ndarray | float, a_x: np.ndarray | float, a_y: np.ndarray | float) -> np.ndarray:
    """Eq. (4): ``C / (sqrt(A_x A_y) + eps)``."""
    return np.asarray(c, np.float64) / (np.sqrt(np.asarray(a_x, np.float64) * np.asarray(a_y, np.float64)) + SIM_EPS)


def kernel_similarity(x: np.ndarray, y: np.ndarray, tau: float, presorted: bool = False) -> float:
    """Normalised kernel similarity of eq. (4), in [0, 1]."""
    x, y = sorted_train(x, presorted), sorted_train(y, presorted)
    inv = 1.0 / tau
    return float(similarity_from_sums(kernel_sum_sorted(x, y, inv), kernel_sum_sorted(x, x, inv), kernel_sum_sorted(y, y, inv)))


def kernel_distance(x: np.ndarray, y: np.ndarray, tau: float, presorted: bool = False, empty_pair: float = 0.0) -> float:
    """Eq. (5): ``1 - sim``. Two empty trains are identical and get ``empty_pair`` (default 0;
    the literal formula would give 1, see docs/fitting.md)."""
    x, y = sorted_train(x, presorted), sorted_train(y, presorted)
    if x.size == 0 and y.size == 0:
        return float(empty_pair)
    return 1.0 - kernel_similarity(x, y, tau, presorted=True)


def vr_distance(x: np.ndarray, y: np.ndarray, tau: float, presorted: bool = False) -> float:
    """Van Rossum distance with elephant's normalisation: ``sqrt(A(x) + A(y) - 2 C(x, y))``."""
    x, y = sorted_train(x, presorted), sorted_train(y, presorted)
    inv = 1.0 / tau
    d2 = kernel_sum_sorted(x, x, inv) + kernel_sum_sorted(y, y, inv) - 2.0 * kernel_sum_sorted(x, y, inv)
    return float(np.sqrt(max(d2, 0.0)))


def auto_sums(trains: Sequence[np.ndarray], tau: float, presorted: bool = False) -> np.ndarray:
    flat, off = pack(trains, presorted)
    out = np.zeros(len(trains))
    auto_sums_flat(flat, off, 1.0 / tau, out)
    return out


def cross_sums(x: np.ndarray, trains: Sequence[np.ndarray], tau: float, presorted: bool = False) -> np.ndarray:
    flat, off = pack(trains, presorted)
    out = np.zeros(len(trains))
    cross_sums_flat(sorted_train(x, presorted), flat, off, 1.0 / tau, out)
    return out


def vr_distance_matrix(trains: Sequence[np.ndarray], tau: float, presorted: bool = False) -> np.ndarray:
    """Pairwise van Rossum distances (elephant normalisation), shape (N, N)."""
    flat, off = pack(trains, presorted)
    n = len(trains)
    k = np.zeros((n, n))
    if n:
        pair_matrix_flat(flat, off, 1.0 / tau, k)
    d = np.diag(k)
    d2 = d[:, None] + d[None, :] - 2.0 * k
    return np.sqrt(np.maximum(d2, 0.0))


def vr_distances_between(a: Sequence[np.ndarray], b: Sequence[np.ndarray], tau: float, presorted: bool = False) -> np.ndarray:
    """VR distance of every train in ``a`` to every train in ``b``: shape (len(a), len(b))."""
    fb, ob = pack(b, presorted)
    inv = 1.0 / tau
    ab = auto_sums(b, tau, presorted=True) if presorted else auto_sums([sorted_train(t, False) for t in b], tau, True)
    out = np.zeros((len(a), len(b)))
    row = np.zeros(len(b))
    for i, x in enumerate(a):
        x = sorted_train(x, presorted)
        cross_sums_flat(x, fb, ob, inv, row)
        ax = kernel_sum_sorted(x, x, inv)
        out[i] = np.sqrt(np.maximum(ax + ab - 2.0 * row, 0.0))
    return out


def pairwise_upper(d: np.ndarray) -> np.ndarray:
    """Values above the diagonal of a square distance matrix (every unordered pair once)."""
    iu = np.triu_indices(d.shape[0], k=1)
    return d[iu]


# ----------------------------------------------------------------------------------------- rates


def spike_count(train: np.ndarray, t0: float | None = None, t1: float | None = None) -> int:
    """Number of spikes in [t0, t1) (whole train when a bound is None)."""
    t = np.asarray(train)
    m = np.ones(t.shape, bool)
    if t0 is not None:
        m &= t >= t0
    if t1 is not None:
        m &= t < t1
    return int(m.sum())


def firing_rate(train: np.ndarray, t0: float, t1: float) -> float:
    """Mean rate (Hz) in [t0, t1)."""
    if t1 <= t0:
        raise ValueError("t1 must be > t0")
    return spike_count(train, t0, t1) / (t1 - t0)


def psth(trains: Sequence[np.ndarray], t0: float, t1: float, bin_s: float = 0.01, smooth_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Rate (Hz) per train: returns bin centres (T,) and rates (len(trains), T).

    ``smooth_s`` > 0 applies a Gaussian of that standard deviation (s) along time.
    """
    edges = np.arange(t0, t1 + bin_s * 0.5, bin_s)
    if edges.size < 2:
        raise ValueError("interval shorter than one bin")
    rates = np.stack([np.histogram(np.asarray(t), bins=edges)[0] / bin_s for t in trains]) if len(trains) else np.zeros((0, edges.size - 1))
    if smooth_s > 0 and rates.size:
        from scipy.ndimage import gaussian_filter1d

        rates = gaussian_filter1d(rates.astype(np.float64), smooth_s / bin_s, axis=-1, mode="constant")
    return 0.5 * (edges[:-1] + edges[1:]), rates
