"""A gateway's view of the published stream, sans-I/O.

:class:`UpstreamTracker` follows the publisher's ``seq`` on the frames subject: a jump of k means k
frames (= k updates) were lost between publisher and gateway (the broker dropped them for a slow
consumer, or the gateway's own pending buffer overflowed); a new session means the service
restarted (sequence numbers start again; the sensor clock may too). The gateway keeps one tracker per
subject (spikes, channels, each decoder). :func:`update_from_frame` turns a
published frame back into the hub's :class:`~touchreal.server.runtime.Update` so the gateway's
hub renders each client's subscription from it exactly as the service's hub does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from touchreal_client import protocol as P

from ..preprocess.pipeline import Channels
from ..server.runtime import Update

GRID_US = 200  #: the channels' 5 kHz grid (us per sample)

_U32 = 1 << 32


@dataclass
class Observed:
    lost: int  #: frames lost just before this one (0 when consecutive)
    new_session: bool  #: first frame of a (new) publisher session: re-read its hello


class UpstreamTracker:
    """Counts frames lost on the broker hop from the publisher's per-subject ``seq`` (u32, wraps)."""

    def __init__(self) -> None:
        self.session: str | None = None
        self.next_seq: int | None = None
        self.frames = 0  #: frames received
        self.lost = 0  #: frames lost upstream, this gateway's lifetime
        self.sessions = 0  #: publisher sessions seen

    def observe(self, session: str | None, seq: int) -> Observed:
        new = session != self.session or self.next_seq is None
        lost = 0
        if new:
            self.session = session
            self.sessions += 1
        else:
            ahead = (seq - self.next_seq) % _U32
            lost = ahead if ahead < _U32 // 2 else 0  # behind: the publisher restarted its count; resync
        self.next_seq = (seq + 1) % _U32
        self.frames += 1
        self.lost += lost
        return Observed(lost, new)


def update_from_frame(frame: P.Frame, n_taxels: int, decoder: str | None = None) -> Update:
    """The hub update a published frame stands for (wall times from the publisher).

    A decoded frame becomes a decoded-only update carrying ``decoder``'s outputs (its name: the
    frame's index refers to the publisher's hello, the subject names it).

    A channels frame (decimation 1) becomes a channels-only update whose data spans all ``n_taxels``
    (NaN for taxels the publisher did not send); its 5 kHz grid index is counted from the wire
    clock's zero, so a client's decimation picks samples on that grid."""
    h = frame.header
    if isinstance(frame, P.DecodedFrame):
        if decoder is None:
            raise ValueError("a decoded frame needs its decoder's name")
        return Update.without_spikes(h.update, h.params_rev, h.flags, h.emit_us, h.emit_us,
                                     decoded=[(decoder, tuple(int(t) for t in frame.taxels), frame.t_us, frame.values)])
    if isinstance(frame, P.ChannelsFrame):
        data = np.full((frame.data.shape[0], n_taxels, len(P.CHANNELS)), np.nan, np.float32)
        keep = frame.taxels < n_taxels
        data[:, frame.taxels[keep].astype(int), :] = frame.data[:, keep, :]
        k0, offset = divmod(int(frame.t0_us), GRID_US)
        return Update.without_spikes(h.update, h.params_rev, h.flags, h.emit_us, h.emit_us, Channels(k0, data), offset)
    final = {c: v for c, v in frame.final_us.items() if v is not None}
    return Update(h.update, h.params_rev, h.flags, h.emit_us, h.emit_us, frame.t_us, frame.taxel, frame.cls, final)
