"""Replay of a recorded trial as a stream of raw chunks (no hardware, no sleeping).

``ReplaySource(trial).read(duration_s)`` returns the samples of the next ``duration_s`` seconds of
the recording clock, so tests, benchmarks and the service can drive the online pipeline exactly as
a live sensor would.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..recording import Trial
from ..raw import RawChunk


class ReplaySource:
    """Sans-I/O player of one :class:`~touchreal.recording.Trial` (one taxel)."""

    def __init__(self, trial: Trial):
        self.trial = trial
        self.now_s = 0.0  # recording-clock time up to which samples were delivered
        self._i_st = 0
        self._i_pv = 0

    @property
    def done(self) -> bool:
        return self._i_st >= self.trial.st_t.size and self._i_pv >= self.trial.pvdf_t.size

    def read(self, duration_s: float) -> RawChunk:
        """Samples with times in [now, now + duration_s)."""
        end = self.now_s + duration_s
        tr = self.trial
        j_st = int(np.searchsorted(tr.st_t, end, side="left"))
        j_pv = int(np.searchsorted(tr.pvdf_t, end, side="left"))
        chunk = RawChunk(
            tr.st_t[self._i_st : j_st],
            np.asarray(tr.st[self._i_st : j_st], np.float64)[:, None],
            tr.pvdf_t[self._i_pv : j_pv],
            np.asarray(tr.pvdf[self._i_pv : j_pv], np.float64)[:, None],
        )
        self._i_st, self._i_pv, self.now_s = j_st, j_pv, end
        return chunk

    def chunks(self, update_s: float) -> Iterator[RawChunk]:
        """Every update interval's samples until the recording ends."""
        while not self.done:
            yield self.read(update_s)
