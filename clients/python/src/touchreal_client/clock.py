"""The stream's clock model: sensor stamps -> the server's wall clock -> this client's clock (sans-I/O).

The service states how its wire clock (the sensor clock plus a replay's segment offset, integer us)
maps to its wall clock, from the acquisition of samples and independently of class delays, windows
and subscriptions: a ``clock`` message (and the ``clock`` field of ``hello``)

    {"type": "clock", "sensor_us": S, "wall_us": W, "rate": R, "error_us": E, "epoch": N}

says that the sample stamped ``S`` was acquired at server wall time ``W`` (Unix epoch, us) and that,
around it, ``wall(t) = W + (t - S) * R`` (``R``: wall us per sensor us, 1 for the simulated e-skin,
1 / speed for a replay, estimated for a serial device). ``E`` is the stated uncertainty of ``W`` and
``epoch`` counts the jumps of the mapping (source reopened, replay resumed or on a new trial, serial
reconnect). The ``time`` exchange gives the offset between the server's wall clock and this
client's (:meth:`ClockMap.set_offset`); together they place any stamp on the client's clock.

A spike stamped ``t_us`` of class ``c`` happened (in the afferent model) at ``t_us``; the sample
that caused it was acquired at ``wall(t_us - delay_us[c])`` (``hello.delay_us``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

_FIELDS = ("sensor_us", "wall_us", "rate", "error_us", "epoch")


def _uint(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**63


@dataclass(frozen=True)
class ClockPoint:
    """One point of the mapping: the sample stamped ``sensor_us`` (wire clock, us) was acquired at
    server wall time ``wall_us`` (us); ``rate`` wall us per sensor us around it; ``error_us`` the
    stated uncertainty (us); ``epoch`` increments whenever the mapping jumps."""

    sensor_us: int
    wall_us: int
    rate: float = 1.0
    error_us: int = 0
    epoch: int = 0

    def wall_of(self, t_us: Any) -> Any:
        """Server wall time (us, float or float array) at which the sample stamped ``t_us`` was acquired."""
        return self.wall_us + (np.asarray(t_us, np.float64) - self.sensor_us) * self.rate

    def to_json(self) -> dict[str, Any]:
        return {"type": "clock", "sensor_us": self.sensor_us, "wall_us": self.wall_us, "rate": self.rate,
                "error_us": self.error_us, "epoch": self.epoch}

    @classmethod
    def from_json(cls, msg: dict[str, Any]) -> ClockPoint:
        """Validate a ``clock`` message (or hello's ``clock`` object); ValueError if malformed."""
        if not isinstance(msg, dict) or any(k not in msg for k in _FIELDS):
            raise ValueError(f"a clock needs the fields {list(_FIELDS)}, got {msg!r:.200}")
        rate = msg["rate"]
        if not all(_uint(msg[k]) for k in ("sensor_us", "wall_us", "error_us", "epoch")):
            raise ValueError(f"clock fields sensor_us, wall_us, error_us, epoch must be non-negative integers: {msg!r:.200}")
        if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not math.isfinite(rate) or not 0.0 < rate < 1e6:
            raise ValueError(f"clock rate must be a positive finite number, got {rate!r}")
        return cls(int(msg["sensor_us"]), int(msg["wall_us"]), float(rate), int(msg["error_us"]), int(msg["epoch"]))


class ClockMap:
    """Maps wire-clock stamps onto the server's wall clock and this client's clock.

    Keeps the last ``history`` points, so stamps of an earlier segment (a replayed trial that just
    ended) still map with a point of their own segment: a stamp maps with the newest point at or
    before it, or with the oldest point if it precedes them all.
    """

    def __init__(self, history: int = 64):
        self._points: deque[ClockPoint] = deque(maxlen=history)
        self.offset_us = 0.0  #: server wall clock minus client wall clock (``time`` exchange; 0 until then)
        self.offset_error_us: float | None = None  #: half the round trip of the exchange in use

    @property
    def last(self) -> ClockPoint | None:
        return self._points[-1] if self._points else None

    @property
    def points(self) -> list[ClockPoint]:
        return list(self._points)

    def update(self, msg: dict[str, Any] | ClockPoint | None) -> ClockPoint | None:
        """Take a ``clock`` message (or hello's ``clock``; None is ignored). A point whose epoch is
        older than the newest one, or whose stamp runs backwards within an epoch, is ignored."""
        if msg is None:
            return None
        p = msg if isinstance(msg, ClockPoint) else ClockPoint.from_json(msg)
        last = self.last
        if last is not None and (p.epoch < last.epoch or (p.epoch == last.epoch and p.sensor_us < last.sensor_us)):
            return None
        if last is not None and p.sensor_us < last.sensor_us:  # a new epoch that starts the wire clock lower
            self._points.clear()
        if last is not None and p.sensor_us == last.sensor_us:
            self._points.pop()
        self._points.append(p)
        return p

    def set_offset(self, offset_us: float, error_us: float | None = None) -> None:
        """The server-minus-client wall-clock offset (us) from a ``time`` exchange."""
        self.offset_us, self.offset_error_us = float(offset_us), error_us

    def _point_index(self, t: np.ndarray) -> np.ndarray:
        starts = np.array([p.sensor_us for p in self._points], np.float64)
        return np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)

    def to_server_wall_us(self, t_us: Any) -> Any:
        """Server wall time (us, float) of the acquisition of the sample stamped ``t_us`` (scalar or
        array). Raises LookupError before the first clock point."""
        if not self._points:
            raise LookupError("no clock point yet (the hello's clock is null until the first sample is acquired)")
        t = np.asarray(t_us, np.float64)
        idx = self._point_index(np.atleast_1d(t))
        pts = self._points
        sensor = np.array([p.sensor_us for p in pts], np.float64)[idx]
        wall = np.array([p.wall_us for p in pts], np.float64)[idx]
        rate = np.array([p.rate for p in pts], np.float64)[idx]
        out = wall + (np.atleast_1d(t) - sensor) * rate
        return float(out[0]) if t.ndim == 0 else out

    def to_local_us(self, t_us: Any) -> Any:
        """This client's wall time (us, float) of the acquisition of the sample stamped ``t_us``."""
        return self.to_server_wall_us(t_us) - self.offset_us

    def error_us(self) -> float:
        """Stated uncertainty of :meth:`to_local_us` (us): the clock point's plus the offset's."""
        last = self.last
        return (last.error_us if last else math.inf) + (self.offset_error_us or 0.0)
