"""Streaming decoder: spike events in, one decoded output per 32 ms step out (sans I/O).

The service calls :meth:`StreamingDecoder.push` once per update from its acquisition thread. The
decoder bins on the sensor clock with the rules of :mod:`touchreal_client.features` (the module the
clients use too), so its outputs equal the offline windows of a recorded trial exactly
(tests/test_decoding_streaming.py).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from touchreal_client import features as F

from .model import DecoderModel


class StreamingDecoder:
    """Sliding-window decoding of one model for a set of taxels, one onnxruntime session.

    Steps are the absolute grid ``T = k * step_us`` of the sensor clock (32 ms). Step ``T`` is
    decoded once every class the model reads is complete up to ``T`` (``final_us[c] >= T``), from
    the spikes with ``t < T``; all taxels go through one inference call (batch = taxels).

    * Force models: the window is ``[T - window, T)`` in 10 ms bins counted back from ``T``.
    * Texture models (alignment ``first spike after silence``): per taxel, a PC spike that follows
      at least ``silence_ms`` (500 ms) without one - or the first PC spike seen - is an anchor.
      The window of step ``T`` is anchored at the latest anchor before ``T``: its bins lie on
      ``anchor + j * 10 ms`` and it ends at the last such edge ``<= T``. A taxel whose anchored
      window is not yet filled (``end - anchor < window``), or that has no anchor, outputs NaN.
      A pause of 500 ms re-anchors, as a new touch does; a continuous slide keeps its anchor and
      the window slides along it.

    ``start_us``: the first step is the first grid point at or after it; None = at or after the
    completeness time of the first :meth:`push` (earlier steps would lack their history).
    Spikes of taxels not in ``taxels`` and of classes the model does not read are ignored.
    """

    def __init__(self, model: DecoderModel, taxels: Sequence[int], threads: int = 1, start_us: int | None = None):
        self.model = model
        self.taxels = np.asarray(list(taxels), dtype=np.int64)
        if self.taxels.size == 0 or np.unique(self.taxels).size != self.taxels.size:
            raise ValueError("taxels must be a non-empty list of distinct taxel indices")
        self._order = np.argsort(self.taxels)
        self._sorted = self.taxels[self._order]
        meta = model.meta
        self.classes: list[str] = list(meta["classes"])
        self._class_col = np.full(len(F.CLASSES), -1, dtype=np.int64)
        for j, c in enumerate(self.classes):
            self._class_col[F.CLASSES.index(c)] = j
        self.window_us, self.bin_us, self.step_us = model.window_us, model.bin_us, model.step_us
        self.n_bins = F.n_bins(self.window_us, self.bin_us)
        align = meta.get("alignment")
        self._anchored = align is not None
        if self._anchored:
            if align.get("rule") != "first spike after silence":
                raise ValueError(f"{model.name}: unknown alignment rule {align.get('rule')!r}")
            self._silence_us = round(float(align["silence_ms"]) * 1000)
            self._anchor_col = self.classes.index(align["class"])
            n = self.taxels.size
            self._last_spike = np.full(n, np.iinfo(np.int64).min // 2, dtype=np.int64)
            self._anchor = np.full(n, -1, dtype=np.int64)
            self._pend_row = np.zeros(0, np.int64)
            self._pend_t = np.zeros(0, np.int64)
        self._session = model.session(threads)
        self._input = meta["input"]["name"]
        self._output = meta["outputs"][0]
        self._t = np.zeros(0, np.int64)
        self._row = np.zeros(0, np.int64)
        self._col = np.zeros(0, np.int64)
        self._next: int | None = None if start_us is None else self._ceil_step(start_us)
        self._complete = np.iinfo(np.int64).min

    @property
    def output_names(self) -> list[str]:
        """Names of the output columns: ``["force_N"]`` or the texture labels (probabilities)."""
        return list(self.model.meta["output_names"])

    def _ceil_step(self, t_us: int) -> int:
        return -(-int(t_us) // self.step_us) * self.step_us

    def push(
        self, t_us: np.ndarray, taxel: np.ndarray, cls: np.ndarray, final_us: dict[str, int]
    ) -> list[tuple[int, np.ndarray]]:
        """Add the spike events of one update; return ``(T, values (n_taxels, n_outputs) float32)``
        for every step completed by it, in time order (rows in the order of ``taxels``)."""
        t = np.asarray(t_us, dtype=np.int64)
        tax = np.asarray(taxel, dtype=np.int64)
        c = np.asarray(cls, dtype=np.int64)
        if not (t.shape == tax.shape == c.shape):
            raise ValueError("t_us, taxel and cls must have one length")
        if c.size and (c.min() < 0 or c.max() >= len(F.CLASSES)):
            raise ValueError(f"cls indexes {F.CLASSES}")
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
        missing = [k for k in self.classes if k not in final_us]
        if missing:
            raise ValueError(f"final_us lacks classes {missing}")
        self._complete = max(self._complete, min(int(final_us[k]) for k in self.classes))
        if self._next is None:
            self._next = self._ceil_step(self._complete)
        out = []
        while self._next <= self._complete:
            out.append((self._next, self._decode(self._next)))
            self._next += self.step_us
        self._prune()
        return out

    def _add_anchors(self, t: np.ndarray, row: np.ndarray) -> None:
        if t.size == 0:
            return
        order = np.lexsort((t, row))
        t, row = t[order], row[order]
        prev = np.concatenate(([-1], row[:-1]))
        prev_t = np.where(prev == row, np.concatenate(([0], t[:-1])), self._last_spike[row])
        is_anchor = t - prev_t >= self._silence_us
        self._pend_row = np.concatenate((self._pend_row, row[is_anchor]))
        self._pend_t = np.concatenate((self._pend_t, t[is_anchor]))
        np.maximum.at(self._last_spike, row, t)

    def _ends(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(window end per taxel, filled mask) of ``step``."""
        n = self.taxels.size
        if not self._anchored:
            return np.full(n, step, dtype=np.int64), np.ones(n, bool)
        due = self._pend_t < step
        if due.any():
            np.maximum.at(self._anchor, self._pend_row[due], self._pend_t[due])
            self._pend_row, self._pend_t = self._pend_row[~due], self._pend_t[~due]
        end = np.where(self._anchor >= 0, self._anchor + (step - self._anchor) // self.bin_us * self.bin_us, -1)
        return end, F.ready(end, self._anchor, self.window_us)

    def _decode(self, step: int) -> np.ndarray:
        end, filled = self._ends(step)
        off = end[self._row] - self._t  # (0, window] inside the window
        inside = (off > 0) & (off <= self.window_us) & filled[self._row]
        b = self.n_bins - 1 - (off[inside] - 1) // self.bin_us
        n, nc = self.taxels.size, len(self.classes)
        flat = (self._row[inside] * self.n_bins + b) * nc + self._col[inside]
        counts = np.bincount(flat, minlength=n * self.n_bins * nc).astype(np.float32).reshape(n, self.n_bins, nc)
        (values,) = self._session.run([self._output], {self._input: counts})
        values = np.asarray(values, dtype=np.float32).reshape(n, -1)
        values[~filled] = np.nan
        return values

    def _prune(self) -> None:
        """Drop events no future window can contain."""
        horizon = self._next - self.window_us - self.bin_us
        keep = self._t >= horizon
        if not keep.all():
            self._t, self._row, self._col = self._t[keep], self._row[keep], self._col[keep]
