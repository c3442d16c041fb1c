"""The reading clock both simulated sources share: samples in PVDF ticks (2 kHz) or up to a time."""

from __future__ import annotations

import math

from ..raw import RawChunk
from .eskin import FS_HZ


class TickReads:
    """``advance(n)`` and ``read(duration_s)`` over a source's ``_advance(n)`` (the next n PVDF ticks and
    the SingleTact samples among them). A subclass sets ``_requested_s`` to its clock's start and has
    ``tick`` (the next tick's index) and ``clock_t0_s`` (the time of tick 0, s)."""

    _requested_s: float
    tick: int
    clock_t0_s: float

    def _advance(self, n: int) -> RawChunk:
        raise NotImplementedError

    @property
    def fs_hz(self) -> float:
        return FS_HZ

    @property
    def time_s(self) -> float:
        """Recording time (s) up to which samples have been produced (the time of the next tick)."""
        return self.clock_t0_s + self.tick / FS_HZ

    @property
    def requested_s(self) -> float:
        """Recording time (s) up to which samples were asked for (:meth:`read`): every sample before
        it has been delivered, none after it."""
        return self._requested_s

    def advance(self, n_ticks: int) -> RawChunk:
        """The next ``n_ticks`` PVDF ticks and the SingleTact samples among them; afterwards the clock
        of :meth:`read` stands at the time of the next tick."""
        n = int(n_ticks)
        if n < 0:
            raise ValueError("n_ticks must be >= 0")
        chunk = self._advance(n)
        self._requested_s = max(self._requested_s, self.time_s)
        return chunk

    def read(self, duration_s: float) -> RawChunk:
        """All samples with times before (previous end + ``duration_s``); the clock keeps the remainder."""
        if duration_s < 0:
            raise ValueError("duration_s must be >= 0")
        self._requested_s += float(duration_s)
        end_tick = math.ceil((self._requested_s - self.clock_t0_s) * FS_HZ - 1e-6)
        return self._advance(max(end_tick - self.tick, 0))
