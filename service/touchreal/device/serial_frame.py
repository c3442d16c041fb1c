"""The microcontroller's serial frame (layout, CRCs, C struct: docs/serial-protocol.md), sans-I/O.

A frame is a 22-byte header (sync ``A5 5A``, version, channel, per-channel ``seq``, boot
``session``, ``t0_us`` device time of the first sample, ``n_taxels``, ``n_samples``, CRC-16 of the
header), ``n_samples x n_taxels`` little-endian float32 samples (N for the SingleTact at 100 Hz,
V for the PVDF at 2 kHz; sample k at ``t0_us + k * period_us``), and a CRC-32 of everything before
it. The header CRC lets the parser reject a corrupted length field as soon as the header is in,
and :data:`MAX_VALUES` bounds what a header may announce (4 KiB of samples), so a bad length never
makes it wait for a frame that is not there.

:func:`encode_frame` writes a frame; :class:`FrameParser` turns bytes into events
(:class:`Frame`, :class:`Gap`, :class:`Restart`, :class:`CrcError`, :class:`Resync`) and keeps
:class:`ParserStats`. It never blocks, sleeps or does I/O, and its events do not depend on how
the byte stream is split into ``feed`` calls.
"""

from __future__ import annotations

import binascii
import struct
import zlib
from dataclasses import asdict, dataclass
from enum import IntEnum

import numpy as np

SYNC = b"\xa5\x5a"
VERSION = 1
HEADER = struct.Struct("<2sBBHHQHH")  # sync, version, channel, seq, session, t0_us, n_taxels, n_samples
HEADER_SIZE = HEADER.size + 2  # + header CRC-16
CRC_SIZE = 4
MAX_TAXELS = 256
MAX_VALUES = 1024  #: largest n_taxels * n_samples a frame may carry (4 KiB of float32)
MAX_FRAME_SIZE = HEADER_SIZE + 4 * MAX_VALUES + CRC_SIZE
SEQ_MOD = 1 << 16
_CRC16 = struct.Struct("<H")
_CRC32 = struct.Struct("<I")
_SAMPLE = np.dtype("<f4")


class Channel(IntEnum):
    """Sensor channel id of a frame."""

    SINGLETACT = 1  #: force, N, 100 Hz
    PVDF = 2  #: voltage, V, 2 kHz


#: Sample period (us) implied by each channel.
PERIOD_US: dict[Channel, int] = {Channel.SINGLETACT: 10_000, Channel.PVDF: 500}


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True)
class Frame:
    """A decoded frame: ``samples`` (n_samples, n_taxels) float32 in N or V."""

    channel: Channel
    seq: int
    session: int
    t0_us: int
    samples: np.ndarray

    @property
    def times_us(self) -> np.ndarray:
        """Device time (us, int64) of every sample."""
        return self.t0_us + PERIOD_US[self.channel] * np.arange(self.samples.shape[0], dtype=np.int64)


@dataclass(frozen=True)
class Gap:
    """``missing`` frames of ``channel`` were lost before the frame numbered ``seq``."""

    channel: Channel
    seq: int
    missing: int


@dataclass(frozen=True)
class Restart:
    """The device's session id changed (it rebooted): sequence numbers and its clock restarted."""

    old_session: int
    new_session: int


@dataclass(frozen=True)
class CrcError:
    """A candidate frame failed its ``"header"`` or ``"frame"`` CRC and was skipped."""

    part: str


@dataclass(frozen=True)
class Resync:
    """The parser found a valid frame again after discarding ``discarded`` bytes."""

    discarded: int


Event = Frame | Gap | Restart | CrcError | Resync


@dataclass
class ParserStats:
    """Cumulative counters of a :class:`FrameParser`."""

    frames: int = 0  #: valid frames decoded
    crc_errors: int = 0  #: header or frame CRC failures
    bad_headers: int = 0  #: header CRC fine but version, channel or sizes not acceptable
    gaps: int = 0  #: sequence-number jumps
    frames_missed: int = 0  #: frames lost in those jumps
    restarts: int = 0  #: session changes (device reboots)
    resyncs: int = 0  #: times the parser lost sync and had to discard bytes
    bytes_discarded: int = 0  #: bytes that were not part of a valid frame

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def encode_frame(
    channel: Channel | int, seq: int, session: int, t0_us: int, samples: np.ndarray
) -> bytes:
    """One frame of ``samples`` (n_samples, n_taxels) or (n_samples,), in N or V, as bytes."""
    channel = Channel(channel)
    values = np.asarray(samples, dtype=_SAMPLE)
    if values.ndim == 1:
        values = values[:, None]
    n_samples, n_taxels = values.shape
    if not (1 <= n_taxels <= MAX_TAXELS and n_samples >= 1 and n_samples * n_taxels <= MAX_VALUES):
        raise ValueError(
            f"a frame holds 1..{MAX_TAXELS} taxels and 1..{MAX_VALUES} values in all, got {n_samples} x {n_taxels}"
        )
    if not 0 <= t0_us < 1 << 64:
        raise ValueError(f"t0_us must fit in u64, got {t0_us}")
    head = HEADER.pack(SYNC, VERSION, channel, seq % SEQ_MOD, session & 0xFFFF, int(t0_us), n_taxels, n_samples)
    body = head + _CRC16.pack(crc16(head)) + np.ascontiguousarray(values).tobytes()
    return body + _CRC32.pack(zlib.crc32(body))


class FrameParser:
    """Sans-I/O frame parser: ``feed(bytes) -> list[Event]``; counters in :attr:`stats`.

    On anything that is not a valid frame (garbage, a failed CRC, an unacceptable header) it drops
    one byte and searches for the next sync word, so a valid frame following the damage is never
    lost. Sequence numbers are tracked per channel within a session: a frame numbered ``d``
    (mod 65536) after the expected one is a :class:`Gap` of ``d`` missing frames (a serial line
    does not reorder, so any other number means frames were lost; losses of 65536 frames or more,
    over 5 min of PVDF, are undercounted modulo 65536, the timestamps still place the samples).
    """

    def __init__(self) -> None:
        self.stats = ParserStats()
        self._buf = bytearray()
        self._discarding = 0  # bytes discarded since the last valid frame (0: in sync)
        self._session: int | None = None
        self._next_seq: dict[Channel, int] = {}

    def reset_buffer(self) -> None:
        """Forget buffered bytes (after a reconnect); sequence and session tracking continue."""
        self._drop(len(self._buf))

    def feed(self, data: bytes) -> list[Event]:
        self._buf += data
        events: list[Event] = []
        buf = self._buf
        while True:
            i = buf.find(SYNC)
            if i < 0:  # keep a trailing first sync byte, it may start a frame
                self._drop(len(buf) - (1 if buf.endswith(SYNC[:1]) else 0))
                break
            self._drop(i)
            if len(buf) < HEADER_SIZE:
                break
            _, version, channel, seq, session, t0_us, n_taxels, n_samples = HEADER.unpack_from(buf)
            if _CRC16.unpack_from(buf, HEADER.size)[0] != crc16(bytes(buf[: HEADER.size])):
                self.stats.crc_errors += 1
                events.append(CrcError("header"))
                self._drop(1)
                continue
            n_values = n_taxels * n_samples
            if version != VERSION or channel not in PERIOD_US or not (1 <= n_taxels <= MAX_TAXELS) or not (
                1 <= n_values <= MAX_VALUES
            ):
                self.stats.bad_headers += 1
                self._drop(1)
                continue
            size = HEADER_SIZE + 4 * n_values + CRC_SIZE
            if len(buf) < size:
                break
            if _CRC32.unpack_from(buf, size - CRC_SIZE)[0] != zlib.crc32(bytes(buf[: size - CRC_SIZE])):
                self.stats.crc_errors += 1
                events.append(CrcError("frame"))
                self._drop(1)
                continue
            samples = np.frombuffer(bytes(buf[HEADER_SIZE : size - CRC_SIZE]), _SAMPLE).reshape(n_samples, n_taxels)
            del buf[:size]
            if self._discarding:
                events.append(Resync(self._discarding))
                self._discarding = 0
            events.extend(self._sequence(Channel(channel), seq, session))
            self.stats.frames += 1
            events.append(Frame(Channel(channel), seq, session, t0_us, samples.astype(np.float32)))
        return events

    def _drop(self, n: int) -> None:
        if n <= 0:
            return
        if not self._discarding:
            self.stats.resyncs += 1
        self._discarding += n
        self.stats.bytes_discarded += n
        del self._buf[:n]

    def _sequence(self, channel: Channel, seq: int, session: int) -> list[Event]:
        events: list[Event] = []
        if session != self._session:
            if self._session is not None:
                self.stats.restarts += 1
                events.append(Restart(self._session, session))
            self._session = session
            self._next_seq.clear()
        expected = self._next_seq.get(channel)
        if expected is not None and seq != expected:
            missing = (seq - expected) % SEQ_MOD
            self.stats.gaps += 1
            self.stats.frames_missed += missing
            events.append(Gap(channel, seq, missing))
        self._next_seq[channel] = (seq + 1) % SEQ_MOD
        return events
