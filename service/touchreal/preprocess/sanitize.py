"""Input sanitation: timestamped raw samples -> a clean sample stream on the channel's regular grid.

Policy (documented in docs/architecture.md, every repair counted in :class:`SanitizeStats`):

* non-finite timestamp: the sample is dropped (``bad_time``);
* timestamp not after the previous accepted one, or landing on an already filled grid slot:
  dropped (``duplicate``);
* non-finite value (NaN, +-Inf): replaced by the last good value of that taxel (``non_finite``);
* value outside the sensor range: clipped to the range (``out_of_range``);
* missing grid slots (a gap in the timestamps): filled by linear interpolation between the
  neighbouring samples (``gap_filled`` counts filled slots, ``gaps`` the gaps).

The grid is anchored at the first accepted timestamp ``t0``: slot n is at ``t0 + n / fs``; a
timestamp maps to the nearest slot. Nothing non-finite ever leaves this stage, so no downstream
filter or neuron state can become NaN or Inf because of the input.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class SanitizeStats:
    """Counts of repaired or rejected input, per channel (all taxels together)."""

    accepted: int = 0  #: samples placed on the grid
    bad_time: int = 0  #: dropped: a non-finite timestamp
    duplicate: int = 0  #: dropped: not after the previous accepted sample, or on a filled slot
    non_finite: int = 0  #: values replaced by the taxel's last good one
    out_of_range: int = 0  #: values clipped to the sensor's range
    gaps: int = 0  #: runs of missing grid slots
    gap_filled: int = 0  #: slots filled by interpolation

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Sanitizer:
    """Sans-I/O stage: ``push(t, x) -> (first_slot, values)`` on the regular grid.

    ``t`` is (n,) seconds, ``x`` is (n,) or (n, n_taxels) in the sensor's unit; the output
    ``values`` is (m, n_taxels) float64 for the consecutive grid slots ``first_slot ...``.
    """

    def __init__(self, fs_hz: float, value_range: tuple[float, float], n_taxels: int = 1, initial: float = 0.0):
        if fs_hz <= 0:
            raise ValueError("fs_hz must be positive")
        self.fs = float(fs_hz)
        self.lo, self.hi = float(value_range[0]), float(value_range[1])
        self.n_taxels = int(n_taxels)
        self.t0: float | None = None
        self.next_slot = 0  # slot the next output sample would take
        self.last = np.full(self.n_taxels, float(np.clip(initial, self.lo, self.hi)))
        self.stats = SanitizeStats()

    def slot_time(self, slot: int | np.ndarray) -> float | np.ndarray:
        """Recording-clock time (s) of a grid slot."""
        assert self.t0 is not None
        return self.t0 + np.asarray(slot) / self.fs

    def push(self, t: np.ndarray, x: np.ndarray) -> tuple[int, np.ndarray]:
        """Place samples ``x`` stamped ``t`` on the grid; (the first slot out, the (m, n_taxels) float64
        values of the consecutive slots from it, a new array). Each repair is counted in :attr:`stats`;
        a block that needs none (finite, in range, no gap) costs one conversion and two reductions."""
        t = np.asarray(t, dtype=np.float64).ravel()
        x = np.asarray(x)
        if x.dtype not in (np.float32, np.float64):
            x = x.astype(np.float64)
        if x.ndim == 1:
            x = x[:, None]
        if x.shape != (t.size, self.n_taxels):
            raise ValueError(f"expected values of shape ({t.size}, {self.n_taxels}), got {x.shape}")
        first = self.next_slot
        if t.size == 0:
            return first, np.zeros((0, self.n_taxels))

        finite_t = np.isfinite(t)
        if not finite_t.all():
            self.stats.bad_time += int(np.count_nonzero(~finite_t))
            t, x = t[finite_t], x[finite_t]
        if t.size and self.t0 is None:
            self.t0 = float(t[0])
        if t.size == 0:
            return first, np.zeros((0, self.n_taxels))

        slots = np.rint((t - self.t0) * self.fs).astype(np.int64)
        # keep strictly increasing slots, each above the last emitted one
        running_max = np.maximum.accumulate(np.concatenate(([self.next_slot - 1], slots)))[:-1]
        keep = slots > running_max
        if not keep.all():
            self.stats.duplicate += int(slots.size - np.count_nonzero(keep))
            slots, x = slots[keep], x[keep]
        if slots.size == 0:
            return first, np.zeros((0, self.n_taxels))

        x = self._repair_values(x)
        n_out = int(slots[-1] - self.next_slot + 1)
        if n_out == slots.size:  # every slot from next_slot on: the samples are the output
            out = x
        else:  # gaps: interpolate linearly between known neighbours
            out = np.empty((n_out, self.n_taxels))
            rel = slots - self.next_slot
            out[rel] = x
            known = np.concatenate(([-1], rel))
            known_vals = np.vstack((self.last[None, :], x))
            missing = np.setdiff1d(np.arange(n_out), rel, assume_unique=True)
            for j in range(self.n_taxels):
                out[missing, j] = np.interp(missing, known, known_vals[:, j])
            self.stats.gap_filled += int(missing.size) * self.n_taxels
            self.stats.gaps += int(np.count_nonzero(np.diff(known) > 1))
        self.stats.accepted += int(slots.size) * self.n_taxels
        self.last = out[-1].copy()
        self.next_slot = int(slots[-1]) + 1
        return first, out

    def _repair_values(self, x: np.ndarray) -> np.ndarray:
        """``x`` as a new float64 array, non-finite values held and out-of-range ones clipped (counted)."""
        lo, hi = (float(x.min()), float(x.max())) if x.size else (self.lo, self.hi)  # NaN propagates: not finite
        x = x.astype(np.float64)
        if self.lo <= lo and hi <= self.hi:  # (False for NaN and infinities beyond the range)
            return x
        bad = ~np.isfinite(x)
        if bad.any():
            self.stats.non_finite += int(np.count_nonzero(bad))
            # hold the last good value: index of the latest finite sample at or before each row
            rows = np.arange(x.shape[0])[:, None]
            src = np.maximum.accumulate(np.where(bad, -1, rows), axis=0)
            held = np.take_along_axis(x, np.maximum(src, 0), axis=0)
            x = np.where(src >= 0, held, self.last[None, :])
        out_of_range = (x < self.lo) | (x > self.hi)
        if out_of_range.any():
            self.stats.out_of_range += int(np.count_nonzero(out_of_range))
            np.clip(x, self.lo, self.hi, out=x)
        return x
