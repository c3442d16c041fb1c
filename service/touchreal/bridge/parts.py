"""Frames larger than a broker message, cut into parts and put together again (sans-I/O).

A NATS server refuses a message over its ``max_payload`` (1 MB by default), and a frame of a large
skin exceeds it: channels cross the broker at full rate (5 kHz), 2.6 kB per taxel per 32 ms update,
so the channels of some 400 taxels already make a megabyte. The publisher cuts such a frame into
parts of at most ``max_payload - HEADROOM_BYTES`` bytes, each with the header :data:`PART_HEADER`
``k/n`` (1-based); NATS keeps one publisher's messages on a subject in order, so a gateway's
:class:`Reassembler` appends the parts of a subject until the n-th and then has the frame. A part out
of sequence (one lost, a publisher restarted mid-frame, a gateway that joined mid-frame) drops the
frame begun, counted; the frame's own ``seq`` then shows the gap to the clients as any lost frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

PART_HEADER = "Touchreal-Part"
#: room left in each message for the NATS headers (session, part) and the protocol line
HEADROOM_BYTES = 1024
#: the most parts a frame may have (a gateway holds at most this many parts per subject)
MAX_PARTS = 256


def split(data: bytes, max_payload: int) -> list[tuple[str | None, bytes]]:
    """``[(None, data)]`` when it fits in a message of ``max_payload`` bytes, else the parts as
    ``("k/n", bytes)``; ValueError when it would take more than :data:`MAX_PARTS`."""
    room = max_payload - HEADROOM_BYTES
    if room <= 0:
        raise ValueError(f"the broker's max_payload ({max_payload} bytes) leaves no room for a frame")
    if len(data) <= room:
        return [(None, data)]
    n = -(-len(data) // room)
    if n > MAX_PARTS:
        raise ValueError(f"a frame of {len(data)} bytes needs {n} parts of {room} bytes; at most {MAX_PARTS}")
    return [(f"{k + 1}/{n}", data[k * room:(k + 1) * room]) for k in range(n)]


def parse_part(value: str) -> tuple[int, int]:
    """``"k/n"`` -> (k, n) with 1 <= k <= n <= :data:`MAX_PARTS`; ValueError otherwise."""
    k_text, sep, n_text = value.partition("/")
    if not (sep and k_text.isdigit() and n_text.isdigit()):
        raise ValueError(f"part header {value[:32]!r} is not k/n")
    k, n = int(k_text), int(n_text)
    if not 1 <= k <= n <= MAX_PARTS:
        raise ValueError(f"part {k}/{n} is out of range (1 <= k <= n <= {MAX_PARTS})")
    return k, n


@dataclass
class Reassembler:
    """The frames of parted messages, per subject: :meth:`push` each message received (with its part
    header, or None) and get the whole frame's bytes back once complete. ``dropped``: frames begun and
    given up (a part out of sequence or malformed)."""

    dropped: int = 0
    _open: dict[str, tuple[int, list[bytes]]] = field(default_factory=dict)  #: subject -> (n, parts so far)
    _skipping: set[str] = field(default_factory=set)  #: subjects whose current frame is lost (counted)

    def push(self, subject: str, part: str | None, data: bytes) -> bytes | None:
        if part is None:
            self._skipping.discard(subject)
            if self._open.pop(subject, None) is not None:
                self.dropped += 1  # a whole frame came while one was being put together
            return data
        try:
            k, n = parse_part(part)
        except ValueError:  # the gateway counts it as a bad frame; a frame begun is lost with it
            self.dropped += self._open.pop(subject, None) is not None
            self._skipping.add(subject)
            raise
        begun = self._open.get(subject)
        if k == 1:
            self._skipping.discard(subject)
            if begun is not None:
                self.dropped += 1
            begun = self._open[subject] = (n, [])
        elif begun is None or begun[0] != n or len(begun[1]) != k - 1:  # its first part, or one between, never came
            self._lose(subject, last=k == n)
            return None
        begun[1].append(data)
        if k < n:
            return None
        del self._open[subject]
        return b"".join(begun[1])

    def _lose(self, subject: str, last: bool) -> None:
        """The subject's current frame is lost: count it once, and pass over its remaining parts."""
        lost = self._open.pop(subject, None) is not None or subject not in self._skipping
        self.dropped += lost
        if last:
            self._skipping.discard(subject)
        else:
            self._skipping.add(subject)

    @property
    def pending_bytes(self) -> int:
        """Bytes held in frames begun (at most :data:`MAX_PARTS` messages per subject)."""
        return sum(len(p) for _, parts in self._open.values() for p in parts)
