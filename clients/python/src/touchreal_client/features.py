"""Decoder input features shared by the TouchReal service and its clients (numpy only).

A TouchReal decoder model (ONNX) takes **binned spike counts** of one taxel as its input tensor
``counts`` of shape ``(batch, n_bins, n_classes)`` (float32). Everything a client has to do before
calling the model lives here, written once, so the service and every client compute the same
tensor from the same spike stream:

* **Times** are integer microseconds on the sensor clock.
* **Decoding steps** are the points of the absolute grid ``k * step_us`` (32 ms by default): a
  decoder emits one output per step ``T`` using only spikes with ``t < T``.
* **Binning** (:func:`window_counts`): the window ``[end - window_us, end)`` is cut into
  ``ceil(window_us / bin_us)`` bins counted back from its end, oldest first; when the window is not
  a whole number of bins, the *oldest* bin is the short one (a 128 ms window in 10 ms bins = one
  8 ms bin then twelve 10 ms bins). Windows shorter than a bin are a single bin.
* **Alignment** (texture models, :func:`anchors` and :func:`anchored_end`): the window is anchored
  at the first spike of the alignment class (PC) after at least ``silence_us`` without one (the
  first spike of a trial); bins are laid on ``anchor + j * bin_us`` and the window of step ``T``
  ends at the last such edge at or before ``T``. A model without alignment uses ``end = T``.
* **Feature order**: the model's classes (metadata ``classes``) in the last axis; bins oldest ->
  newest in the middle axis. The features computed from these counts (sums, smoothing, spectra)
  are inside the ONNX graph; the metadata lists their order.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Afferent classes in the order of the wire protocol's class index.
CLASSES: tuple[str, ...] = ("SA1", "RA", "PC")
BIN_US = 10_000  #: default bin width (10 ms)
STEP_US = 32_000  #: default decoding step (32 ms, the service's update interval)


def n_bins(window_us: int, bin_us: int = BIN_US) -> int:
    """Number of bins of a window: ``ceil(window_us / bin_us)``, at least 1."""
    if window_us <= 0 or bin_us <= 0:
        raise ValueError("window and bin widths must be positive")
    return max(1, -(-int(window_us) // int(bin_us)))


def bin_edges(ends_us: np.ndarray, window_us: int, bin_us: int = BIN_US) -> np.ndarray:
    """Bin edges (us) of the windows ending at ``ends_us``: shape ``(len(ends), n_bins + 1)``,
    oldest edge first; the oldest bin is truncated at ``end - window_us``."""
    ends = np.asarray(ends_us, dtype=np.int64).reshape(-1, 1)
    nb = n_bins(window_us, bin_us)
    back = np.minimum(np.arange(nb, -1, -1, dtype=np.int64) * int(bin_us), int(window_us))
    return ends - back


def window_counts(t_us: np.ndarray, ends_us: np.ndarray, window_us: int, bin_us: int = BIN_US) -> np.ndarray:
    """Spike counts of one train (sorted times, us) in the windows ending at ``ends_us``.

    Returns ``(len(ends), n_bins)`` float32, oldest bin first; a bin ``[a, b)`` counts ``a <= t < b``.
    """
    t = np.asarray(t_us, dtype=np.int64)
    edges = bin_edges(ends_us, window_us, bin_us)
    idx = np.searchsorted(t, edges, side="left")
    return np.diff(idx, axis=1).astype(np.float32)


def counts_tensor(
    trains_us: dict[str, np.ndarray], classes: Sequence[str], ends_us: np.ndarray, window_us: int, bin_us: int = BIN_US
) -> np.ndarray:
    """The model input for one taxel: ``(len(ends), n_bins, len(classes))`` float32 counts."""
    return np.stack([window_counts(trains_us[c], ends_us, window_us, bin_us) for c in classes], axis=-1)


def step_times(start_us: int, stop_us: int, step_us: int = STEP_US) -> np.ndarray:
    """Decoding steps ``k * step_us`` with ``start_us <= T <= stop_us`` (int64, us)."""
    k0 = -(-int(start_us) // int(step_us))
    k1 = int(stop_us) // int(step_us)
    return np.arange(k0, k1 + 1, dtype=np.int64) * int(step_us)


def anchors(t_us: np.ndarray, silence_us: int) -> np.ndarray:
    """Alignment anchors of a sorted train: its first spike and every spike that follows at least
    ``silence_us`` without a spike (us, int64)."""
    t = np.asarray(t_us, dtype=np.int64)
    if t.size == 0:
        return t
    keep = np.concatenate(([True], np.diff(t) >= int(silence_us)))
    return t[keep]


def anchored_end(steps_us: np.ndarray, anchor_list_us: np.ndarray, bin_us: int = BIN_US) -> tuple[np.ndarray, np.ndarray]:
    """(window end, anchor) of every step for an anchored model, int64 us.

    The anchor of step ``T`` is the latest anchor ``< T`` (only spikes before ``T`` are known);
    the end is the last anchored bin edge ``anchor + j * bin_us <= T``. Steps with no anchor yet
    get end = anchor = -1.
    """
    steps = np.asarray(steps_us, dtype=np.int64)
    a = np.asarray(anchor_list_us, dtype=np.int64)
    i = np.searchsorted(a, steps, side="left") - 1
    has = i >= 0
    anchor = np.where(has, a[np.maximum(i, 0)] if a.size else 0, -1)
    end = np.where(has, anchor + (steps - anchor) // int(bin_us) * int(bin_us), -1)
    return end, anchor


def ready(ends_us: np.ndarray, anchor_us: np.ndarray, window_us: int) -> np.ndarray:
    """True where an anchored window is filled: ``end - anchor >= window_us``."""
    return (np.asarray(anchor_us) >= 0) & (np.asarray(ends_us) - np.asarray(anchor_us) >= int(window_us))
