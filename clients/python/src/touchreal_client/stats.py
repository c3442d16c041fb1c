"""Stream statistics and latency from the frame clocks (sans-I/O: the stream feeds it, tests too).

Counters (:class:`StreamStats`): frames and spike events received, sequence gaps (frames the server
dropped for this client: a jump in the per-connection ``seq``), the server's own ``dropped`` counter,
frames flagged ``source_gap`` / ``restarted`` / ``params_changed``, reconnects and session changes.

Latency (:class:`LatencyEstimator`): every frame carries two server wall-clock stamps (``emit_us``,
the update left the encoder; ``sent_us``, the frame was handed to this client's socket). With the
client's receive time mapped onto the server clock by the NTP-style ``time`` exchange
(:meth:`LatencyEstimator.add_time_sample`; offset 0 until then, right when both clocks are
synchronised, e.g. on one machine) they give

* ``queue_us = sent_us - emit_us`` (waiting in the server's per-client queue),
* ``network_us = receive - sent_us`` (socket, network, client read),
* ``delivery_us = receive - emit_us`` (their sum),
* per class ``total_us[c] = latency_us[c] + delivery_us``: the algorithmic latency the server
  states in ``hello`` / ``subscribed`` (stamp to emission, an upper bound) plus the measured delivery.

Per spike, with the stream's clock model (:class:`~.clock.ClockMap`), the latency a robot
experiences: receipt minus the moment the spike's causing sample was acquired, both on this
client's clock (:meth:`LatencyEstimator.on_spikes`).

All times are integer microseconds; receive times are the client's wall clock (Unix epoch).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .clock import ClockMap
from .protocol import CLASSES, FLAG_PARAMS_CHANGED, FLAG_RESTARTED, FLAG_SOURCE_GAP, Header, SpikesFrame, clock_offset


@dataclass
class StreamStats:
    """Counters of one stream (all connections of one client, across reconnects)."""

    frames: int = 0  #: frames received
    spike_events: int = 0  #: spike events received
    decoded_steps: int = 0  #: decoded-output steps received
    gaps: int = 0  #: jumps in ``seq`` (each one = a run of frames dropped for this client)
    missed_frames: int = 0  #: frames missing by ``seq`` (dropped by the server's flow control)
    server_dropped: int = 0  #: the server's ``dropped`` counter of the current connection
    source_gaps: int = 0  #: frames flagged ``source_gap`` (samples missing or repaired)
    restarts: int = 0  #: frames flagged ``restarted`` (pipeline started again from rest)
    params_changes: int = 0  #: frames flagged ``params_changed``
    connections: int = 0  #: connections opened (1 + reconnects)
    session_changes: int = 0  #: reconnects that found a new server session (seq and clock restart)
    _next_seq: int | None = field(default=None, repr=False)

    def on_connect(self, new_session: bool) -> None:
        """A connection delivered its hello: ``seq`` restarts at 0 per connection."""
        self.connections += 1
        self.session_changes += int(new_session and self.connections > 1)
        self._next_seq = None
        self.server_dropped = 0

    def on_frame(self, header: Header, n_events: int = 0, n_steps: int = 0) -> int:
        """Count one frame; returns how many frames were missed just before it (0 normally)."""
        missed = 0
        if self._next_seq is not None and header.seq != self._next_seq:
            missed = (header.seq - self._next_seq) & 0xFFFFFFFF  # seq is a u32 on the wire
            self.gaps += 1
            self.missed_frames += missed
        self._next_seq = (header.seq + 1) & 0xFFFFFFFF
        self.frames += 1
        self.spike_events += n_events
        self.decoded_steps += n_steps
        self.server_dropped = header.dropped
        self.source_gaps += bool(header.flags & FLAG_SOURCE_GAP)
        self.restarts += bool(header.flags & FLAG_RESTARTED)
        self.params_changes += bool(header.flags & FLAG_PARAMS_CHANGED)
        return missed

    @property
    def reconnects(self) -> int:
        return max(self.connections - 1, 0)


def spike_latency_us(frame: SpikesFrame, recv_us: int, clock: ClockMap, delay_us: dict[str, int]) -> np.ndarray:
    """Per spike: ``recv_us`` (client wall clock) minus the acquisition of its causing sample (its stamp
    minus its class's delay, mapped by ``clock``), us. Empty without spikes or before the first clock point."""
    if not frame.t_us.size or clock.last is None:
        return np.zeros(0)
    delays = np.array([delay_us.get(c, 0) for c in CLASSES], np.float64)[frame.cls]
    return recv_us - clock.to_local_us(frame.t_us.astype(np.float64) - delays)


@dataclass(frozen=True)
class Latency:
    """One frame's delivery figures (us); ``total_us[c]`` adds the server's algorithmic latency."""

    queue_us: int  #: in the server's queue: sent_us - emit_us
    network_us: int  #: from the server's socket to this client: receipt - sent_us, by the clock mapping
    delivery_us: int  #: queue and network: receipt - emit_us
    total_us: dict[str, int]  #: per class: delivery plus the class's algorithmic latency


@dataclass(frozen=True)
class LatencySummary:
    """Median and 99th percentile of the recent frames' delivery, and the clock offset in use."""

    frames: int
    delivery_median_us: float
    delivery_p99_us: float
    total_median_us: dict[str, float]
    offset_us: float
    offset_uncertainty_us: float | None  #: half the best round trip; None = no time exchange yet
    #: per class, over the recent spikes: (median, p95, max) of receipt minus acquisition of the causing sample (us)
    spike_us: dict[str, tuple[float, float, float]] = field(default_factory=dict)


class LatencyEstimator:
    """Latency of the frames of one stream from their clocks (see the module docstring)."""

    def __init__(self, window: int = 512):
        self.offset_us = 0.0  #: server clock minus client clock
        self.uncertainty_us: float | None = None
        self.algorithmic_us: dict[str, int] = {}
        self.last: Latency | None = None
        self._recent: deque[Latency] = deque(maxlen=window)
        self._spikes: dict[str, deque[np.ndarray]] = {c: deque(maxlen=window) for c in CLASSES}

    def set_algorithmic(self, latency_us: dict[str, int]) -> None:
        """The per-class latency the server states (``hello`` / ``subscribed``: ``latency_us``)."""
        self.algorithmic_us = {c: int(v) for c, v in latency_us.items()}

    def add_time_sample(self, t0_us: int, t1_us: int, t2_us: int, t3_us: int) -> None:
        """One ``time`` exchange; the sample with the smallest round trip wins (least asymmetry)."""
        offset, delay = clock_offset(t0_us, t1_us, t2_us, t3_us)
        half = max(delay, 0.0) / 2.0
        if self.uncertainty_us is None or half <= self.uncertainty_us:
            self.offset_us, self.uncertainty_us = offset, half

    def on_frame(self, header: Header, recv_us: int) -> Latency:
        """Latency of a frame received at ``recv_us`` (client wall clock)."""
        recv_server = recv_us + self.offset_us
        delivery = int(round(recv_server - header.emit_us))
        lat = Latency(
            queue_us=int(header.sent_us - header.emit_us),
            network_us=int(round(recv_server - header.sent_us)),
            delivery_us=delivery,
            total_us={c: a + delivery for c, a in self.algorithmic_us.items()},
        )
        self.last = lat
        self._recent.append(lat)
        return lat

    def on_spikes(self, frame: SpikesFrame, recv_us: int, clock: ClockMap, delay_us: dict[str, int]) -> np.ndarray:
        """Per spike of ``frame`` (received at ``recv_us``, client wall clock): receipt minus the
        acquisition of its causing sample (stamp minus its class's delay, mapped by ``clock``), us.
        Empty when the frame has no spikes or no clock point has arrived yet."""
        lat = spike_latency_us(frame, recv_us, clock, delay_us)
        for i, c in enumerate(CLASSES):
            sel = frame.cls == i
            if sel.any():
                self._spikes[c].append(lat[sel])
        return lat

    def summary(self) -> LatencySummary | None:
        if not self._recent:
            return None
        d = np.array([x.delivery_us for x in self._recent], float)
        total = {c: float(np.median(d) + a) for c, a in self.algorithmic_us.items()}
        spikes = {}
        for c, parts in self._spikes.items():
            if parts:
                v = np.concatenate(list(parts))
                spikes[c] = (float(np.median(v)), float(np.percentile(v, 95)), float(v.max()))
        return LatencySummary(len(d), float(np.median(d)), float(np.percentile(d, 99)), total,
                              self.offset_us, self.uncertainty_us, spikes)
