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
from typing import Any

import numpy as np

#: Afferent classes in the order of the wire protocol's class index.
CLASSES: tuple[str, ...] = ("SA1", "RA", "PC")
BIN_US = 10_000  #: default bin width (10 ms)
STEP_US = 32_000  #: default decoding step (32 ms, the service's update interval)
#: ONNX ``metadata_props`` key of a decoder's metadata (JSON); with onnxruntime:
#: ``json.loads(session.get_modelmeta().custom_metadata_map[META_KEY])``
META_KEY = "touchreal.decoder"
ALIGN_RULE = "first spike after silence"  #: the one alignment rule (texture models)


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


class StreamBinner:
    """The streaming half of a decoder, numpy only: spike events in, one counts tensor per step out.

    Steps are the absolute grid ``T = k * step_us`` of the sensor clock. Step ``T`` is ready once
    every class the model reads is complete up to ``T`` (``final_us[c] >= T``); its counts use the
    spikes with ``t < T`` only, so they equal :func:`window_counts` of the whole train.

    * No alignment (force): the window is ``[T - window, T)``.
    * Alignment ``first spike after silence`` (texture): per taxel, a spike of the alignment class
      that follows at least ``silence_us`` without one - or the first one seen - is an anchor. The
      window of step ``T`` is anchored at the latest anchor before ``T``: bins on
      ``anchor + j * bin_us``, ending at the last such edge ``<= T``. A taxel without an anchor or
      whose anchored window is not filled yet (``end - anchor < window``) is flagged not filled.
      A pause of ``silence_us`` re-anchors (a new touch); a continuous slide keeps its anchor.

    ``start_us``: the first step is the first grid point at or after it; None = at or after the
    completeness time of the first :meth:`push`. Spikes of other taxels or classes are ignored.
    """

    def __init__(
        self,
        classes: Sequence[str],
        taxels: Sequence[int],
        window_us: int,
        bin_us: int = BIN_US,
        step_us: int = STEP_US,
        alignment: dict[str, Any] | None = None,
        start_us: int | None = None,
    ):
        self.classes = list(classes)
        self.taxels = np.asarray(list(taxels), dtype=np.int64)
        if self.taxels.size == 0 or np.unique(self.taxels).size != self.taxels.size:
            raise ValueError("taxels must be a non-empty list of distinct taxel indices")
        self._order = np.argsort(self.taxels)
        self._sorted = self.taxels[self._order]
        self._class_col = np.full(len(CLASSES), -1, dtype=np.int64)
        for j, c in enumerate(self.classes):
            self._class_col[CLASSES.index(c)] = j
        self.window_us, self.bin_us, self.step_us = int(window_us), int(bin_us), int(step_us)
        self.n_bins = n_bins(self.window_us, self.bin_us)
        self._anchored = alignment is not None
        if self._anchored:
            if alignment.get("rule") != ALIGN_RULE:
                raise ValueError(f"unknown alignment rule {alignment.get('rule')!r}")
            self._silence_us = round(float(alignment["silence_ms"]) * 1000)
            self._anchor_col = self.classes.index(alignment["class"])
            n = self.taxels.size
            self._last_spike = np.full(n, np.iinfo(np.int64).min // 2, dtype=np.int64)
            self._anchor = np.full(n, -1, dtype=np.int64)
            self._pend_row = np.zeros(0, np.int64)
            self._pend_t = np.zeros(0, np.int64)
        self._t = np.zeros(0, np.int64)
        self._row = np.zeros(0, np.int64)
        self._col = np.zeros(0, np.int64)
        self._next: int | None = None if start_us is None else self._ceil_step(start_us)
        self._complete = np.iinfo(np.int64).min

    @classmethod
    def from_metadata(cls, meta: dict[str, Any], taxels: Sequence[int], start_us: int | None = None) -> "StreamBinner":
        """The binner a decoder's metadata describes."""
        return cls(meta["classes"], taxels, round(meta["window_ms"] * 1000), round(meta["bin_ms"] * 1000),
                   round(meta["step_ms"] * 1000), meta.get("alignment"), start_us)

    def _ceil_step(self, t_us: int) -> int:
        return -(-int(t_us) // self.step_us) * self.step_us

    def push(
        self, t_us: np.ndarray, taxel: np.ndarray, cls: np.ndarray, final_us: dict[str, int]
    ) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """Add one update's spike events (``cls`` indexes :data:`CLASSES`); return
        ``(T, counts (n_taxels, n_bins, n_classes) float32, filled (n_taxels,) bool)`` for every
        step it completes, in time order, rows in the order of ``taxels``."""
        t = np.asarray(t_us).astype(np.int64)
        tax = np.asarray(taxel, dtype=np.int64)
        c = np.asarray(cls, dtype=np.int64)
        if not (t.shape == tax.shape == c.shape):
            raise ValueError("t_us, taxel and cls must have one length")
        if c.size and (c.min() < 0 or c.max() >= len(CLASSES)):
            raise ValueError(f"cls indexes {CLASSES}")
        missing = [k for k in self.classes if k not in final_us]
        if missing:
            raise ValueError(f"final_us lacks classes {missing}")
        col = self._class_col[c]
        pos = np.searchsorted(self._sorted, tax)
        known = (pos < self._sorted.size) & (self._sorted[np.minimum(pos, self._sorted.size - 1)] == tax)
        keep = (col >= 0) & known
        t, row, col = t[keep], self._order[pos[keep]], col[keep]
        if self._anchored:
            self._add_anchors(t[col == self._anchor_col], row[col == self._anchor_col])
        self._t = np.concatenate((self._t, t))
        self._row = np.concatenate((self._row, row))
        self._col = np.concatenate((self._col, col))
        self._complete = max(self._complete, min(int(final_us[k]) for k in self.classes))
        if self._next is None:
            self._next = self._ceil_step(self._complete)
        out = []
        while self._next <= self._complete:
            out.append((self._next, *self._counts(self._next)))
            self._next += self.step_us
        self._prune()
        return out

    def _add_anchors(self, t: np.ndarray, row: np.ndarray) -> None:
        if t.size == 0:
            return
        order = np.lexsort((t, row))
        t, row = t[order], row[order]
        same = np.concatenate(([False], row[1:] == row[:-1]))
        prev_t = np.where(same, np.concatenate(([0], t[:-1])), self._last_spike[row])
        is_anchor = t - prev_t >= self._silence_us
        self._pend_row = np.concatenate((self._pend_row, row[is_anchor]))
        self._pend_t = np.concatenate((self._pend_t, t[is_anchor]))
        np.maximum.at(self._last_spike, row, t)

    def _ends(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        n = self.taxels.size
        if not self._anchored:
            return np.full(n, step, dtype=np.int64), np.ones(n, bool)
        due = self._pend_t < step
        if due.any():
            np.maximum.at(self._anchor, self._pend_row[due], self._pend_t[due])
            self._pend_row, self._pend_t = self._pend_row[~due], self._pend_t[~due]
        end = np.where(self._anchor >= 0, self._anchor + (step - self._anchor) // self.bin_us * self.bin_us, -1)
        return end, ready(end, self._anchor, self.window_us)

    def _counts(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        end, filled = self._ends(step)
        off = end[self._row] - self._t  # in (0, window] inside the window
        inside = (off > 0) & (off <= self.window_us) & filled[self._row]
        b = self.n_bins - 1 - (off[inside] - 1) // self.bin_us
        n, nc = self.taxels.size, len(self.classes)
        flat = (self._row[inside] * self.n_bins + b) * nc + self._col[inside]
        counts = np.bincount(flat, minlength=n * self.n_bins * nc).astype(np.float32).reshape(n, self.n_bins, nc)
        return counts, filled

    def _prune(self) -> None:
        """Drop events no future window can contain."""
        keep = self._t >= self._next - self.window_us - self.bin_us
        if not keep.all():
            self._t, self._row, self._col = self._t[keep], self._row[keep], self._col[keep]
