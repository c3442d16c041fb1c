"""The ``/v1/stream`` wire protocol, sans-I/O: bytes and JSON texts in, typed messages out, and back.

Shared by the service (which depends on this package) and every client, so both sides read one
definition. Nothing here touches a socket; docs/stream-protocol.md is the normative description.

* Binary frames (WebSocket binary messages, also the payload published to a broker): a 48-byte
  header (:data:`HEADER`) followed by a payload of kind spikes, channels or decoded outputs.
  All integers little-endian; times are integer microseconds, ``*_us`` on the sensor clock except
  ``emit_us`` / ``sent_us`` (server wall clock, Unix epoch).
* JSON messages (WebSocket text messages): ``hello``, ``subscribe``, ``subscribed``, ``time``, ``ended``,
  ``error``, and the JSON encoding of the three frame kinds.

Per-connection fields (``seq``, ``dropped``, ``sent_us``) sit at fixed offsets of the header so a
frame rendered once can be stamped for each connection (:func:`stamp`) without re-encoding.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

PROTOCOL = "touchreal.stream"
#: Session protocol (hello and subscribe). Version 2 adds the hello's ``addresses`` ("taxels", or
#: "afferents": the ids of spikes and subscriptions are a population's afferents, listed in the hello's
#: ``population``); a server whose spikes address afferents refuses a version-1 subscriber, which
#: would read them as taxels. Over taxels both versions mean the same.
VERSION = 2
SUPPORTED_VERSIONS = (1, 2)
FRAME_VERSION = 1  #: the binary frame layout (header byte 2), the same in both session versions
CLASSES = ("SA1", "RA", "PC")
CHANNELS = ("ST", "dST", "PVDF", "dPVDF")
CHANNEL_UNITS = ("N", "N/s", "V", "V/s")
ENCODINGS = ("binary", "json")
STREAMS = ("spikes", "channels", "decoded")
MAGIC = b"TR"
MAX_CLIENT_MESSAGE_BYTES = 65536  #: larger client messages are refused (close 1009)
MAX_TAXELS = 65536  #: taxel ids are uint16 on the wire: 0..65535
#: a hello lists every taxel (``taxels``) up to this many; a larger skin on a grid is described by its
#: ``layout`` alone (``taxels`` null): 4096 listed taxels make a hello of about 160 KB
HELLO_LISTED_TAXELS = 4096
GRID_TOLERANCE_MM = 1e-6  #: a skin is a grid when its layout gives every listed centre to within this (mm)
MAX_FRAME_TAXELS = 65535  #: a channels or decoded frame carries at most this many taxels (a u16 count)
MAX_REGION_RANGES = 1024  #: a subscription's ``region`` holds at most this many id ranges
MAX_REGION_RECTS = 16  #: and at most this many rectangles
MAX_INT_DIGITS = 20  #: a JSON integer literal of a client message has at most this many digits
MAX_TIME_ID_CHARS = 128  #: a ``time`` request's string ``id`` has at most this many characters
MAX_ERROR_CHARS = 300  #: an ``error`` message's text is cut to this many characters
MAX_ERRORS_IN_A_ROW = 10  #: this many refused messages in a row close the connection (4400)
#: A client's unsent replies (``hello``, ``subscribed``, ``time``, ``error``) are bounded by count and by
#: bytes; a client that sends requests faster than it reads the replies is closed (CLOSE_FLOODING).
CONTROL_QUEUE_MESSAGES = 256
CONTROL_QUEUE_BYTES = 1 << 20
#: The server reads a client's messages no faster than this budget (a token bucket per connection, in
#: messages and in bytes: rate per second, burst); beyond it the messages wait in the network, nothing
#: is dropped or closed, so one client's requests cannot take another's share of the server.
CONTROL_RATE_PER_S = 50
CONTROL_BURST = 100
CONTROL_BYTES_PER_S = 256 * 1024
CONTROL_BURST_BYTES = 256 * 1024

# frame kinds
KIND_SPIKES = 1
KIND_CHANNELS = 2
KIND_DECODED = 3
KIND_NAMES = {KIND_SPIKES: "spikes", KIND_CHANNELS: "channels", KIND_DECODED: "decoded"}

# header flags
FLAG_SOURCE_GAP = 1  #: the source reported missing or repaired samples during this update
FLAG_PARAMS_CHANGED = 2  #: first frame made with a new parameter set (see params_rev)
FLAG_RESTARTED = 4  #: the pipeline restarted from rest before this frame (warm-up follows)
FLAG_NAMES = {FLAG_SOURCE_GAP: "source_gap", FLAG_PARAMS_CHANGED: "params_changed", FLAG_RESTARTED: "restarted"}

# close codes (RFC 6455 + application range)
CLOSE_NORMAL = 1000
CLOSE_GOING_AWAY = 1001  #: server shutting down
CLOSE_TOO_BIG = 1009  #: a client message over MAX_CLIENT_MESSAGE_BYTES
CLOSE_INTERNAL = 1011
CLOSE_TRY_AGAIN = 1013  #: too many connections
CLOSE_UNSUPPORTED_VERSION = 4001  #: subscribe asked for a protocol version the server does not speak
CLOSE_SLOW_CONSUMER = 4008  #: the client did not read its frames fast enough; its queue overflowed
CLOSE_FLOODING = 4029  #: the client sent requests faster than it read the replies; its reply queue overflowed
CLOSE_TOO_MANY_ERRORS = 4400  #: too many malformed messages in a row

#: Common header: magic, version, kind, flags, header_len, seq, dropped, update, emit_us, sent_us,
#: params_rev, reserved (48 bytes).
HEADER = struct.Struct("<2sBBHHIIQQQII")
HEADER_LEN = HEADER.size
_SEQ_DROPPED = struct.Struct("<II")  # at offset 8
_SENT = struct.Struct("<Q")  # at offset 32
OFF_SEQ, OFF_SENT = 8, 32

#: Spikes payload head: n_events, class mask, 3 reserved bytes, final_us per class (SA1, RA, PC).
SPIKES_HEAD = struct.Struct("<IB3x3Q")
#: One address-event: sensor time (us), taxel, class index, reserved.
EVENT_DTYPE = np.dtype([("t_us", "<u8"), ("taxel", "<u2"), ("cls", "u1"), ("_r", "u1")])
#: Channels payload head: t0_us, period_us, n_samples, n_taxels, n_channels, reserved.
CHANNELS_HEAD = struct.Struct("<QIIHBx")
#: Decoded payload head: decoder index, n_taxels, n_values, n_steps.
DECODED_HEAD = struct.Struct("<HHHH")


class ProtocolError(ValueError):
    """A message that does not follow the protocol; ``code`` is the error code sent to the peer."""

    def __init__(self, message: str, code: str = "bad_message"):
        super().__init__(message)
        self.code = code


@dataclass
class Header:
    """The common frame header. ``kind`` is KIND_*; ``flags`` a bit set of FLAG_*."""

    kind: int
    update: int = 0  #: the encoder update that made the frame (the same in every client's copy)
    emit_us: int = 0  #: server wall clock (us) when the update left the encoder
    params_rev: int = 0  #: revision of the parameter set that made the frame
    flags: int = 0
    seq: int = 0  #: per connection: 0, 1, 2, ... for every frame meant for this client; a jump = frames dropped
    dropped: int = 0  #: per connection: frames dropped for this client so far
    sent_us: int = 0  #: per connection: server wall clock (us) when the frame went to this client's socket
    version: int = FRAME_VERSION
    recv_us: int | None = None  #: client side only (not on the wire): this client's wall clock when it received the frame

    def flag_names(self) -> list[str]:
        return [name for bit, name in FLAG_NAMES.items() if self.flags & bit]


@dataclass
class SpikesFrame:
    """Spike events sorted by time. ``final_us[c]``: every spike of class c (for the subscribed
    taxels) stamped before it has been sent; ``None`` for classes not in this stream."""

    header: Header
    t_us: np.ndarray  # (n,) uint64, sensor clock
    taxel: np.ndarray  # (n,) uint16
    cls: np.ndarray  # (n,) uint8, index into CLASSES
    final_us: dict[str, int | None] = field(default_factory=dict)


@dataclass
class ChannelsFrame:
    """``data[k, i, c]``: channel c of taxel ``taxels[i]`` at sensor time ``t0_us + k * period_us``."""

    header: Header
    t0_us: int
    period_us: int
    taxels: np.ndarray  # (n_taxels,) uint16
    data: np.ndarray  # (n_samples, n_taxels, 4) float32


@dataclass
class DecodedFrame:
    """Decoder outputs: ``values[s, i, j]`` is output j for taxel ``taxels[i]`` at step time ``t_us[s]``."""

    header: Header
    decoder: int  # index into hello.streams.decoded.decoders
    taxels: np.ndarray  # (n_taxels,) uint16
    t_us: np.ndarray  # (n_steps,) uint64, sensor clock (end of each decoding window)
    values: np.ndarray  # (n_steps, n_taxels, n_values) float32


Frame = SpikesFrame | ChannelsFrame | DecodedFrame


# -- binary frames ---------------------------------------------------------------------------------
def _pack_header(h: Header) -> bytes:
    return HEADER.pack(
        MAGIC, h.version, h.kind, h.flags, HEADER_LEN, h.seq, h.dropped, h.update, h.emit_us, h.sent_us, h.params_rev, 0
    )


def _pad4(n: int) -> int:
    return (-n) % 4


def encode_spikes(header: Header, t_us, taxel, cls, final_us: dict[str, int | None]) -> bytes:
    """Binary spikes frame; events must be sorted by ``t_us``."""
    ev = np.zeros(len(t_us), EVENT_DTYPE)
    ev["t_us"], ev["taxel"], ev["cls"] = t_us, taxel, cls
    mask = 0
    finals = []
    for i, c in enumerate(CLASSES):
        f = final_us.get(c)
        if f is not None:
            mask |= 1 << i
        finals.append(int(f or 0))
    return _pack_header(header) + SPIKES_HEAD.pack(ev.size, mask, *finals) + ev.tobytes()


def encode_channels(header: Header, t0_us: int, period_us: int, taxels, data: np.ndarray) -> bytes:
    data = np.ascontiguousarray(data, dtype="<f4")
    n_s, n_t, n_c = data.shape
    tx = np.asarray(taxels, "<u2").tobytes()
    return (
        _pack_header(header)
        + CHANNELS_HEAD.pack(int(t0_us), int(period_us), n_s, n_t, n_c)
        + tx
        + b"\0" * _pad4(len(tx))
        + data.tobytes()
    )


def encode_decoded(header: Header, decoder: int, taxels, t_us, values: np.ndarray) -> bytes:
    values = np.ascontiguousarray(values, dtype="<f4")
    n_s, n_t, n_v = values.shape
    tx = np.asarray(taxels, "<u2").tobytes()
    return (
        _pack_header(header)
        + DECODED_HEAD.pack(decoder, n_t, n_v, n_s)
        + tx
        + b"\0" * _pad4(len(tx))
        + np.asarray(t_us, "<u8").tobytes()
        + values.tobytes()
    )


def stamp(frame: bytes | bytearray, seq: int, dropped: int, sent_us: int) -> bytearray:
    """A copy of a binary frame with this connection's ``seq``, ``dropped`` and ``sent_us``."""
    out = bytearray(frame)
    _SEQ_DROPPED.pack_into(out, OFF_SEQ, seq & 0xFFFFFFFF, min(dropped, 0xFFFFFFFF))
    _SENT.pack_into(out, OFF_SENT, sent_us)
    return out


def decode_header(buf: bytes | bytearray | memoryview) -> Header:
    if len(buf) < HEADER_LEN:
        raise ProtocolError(f"frame of {len(buf)} bytes is shorter than the {HEADER_LEN}-byte header")
    magic, ver, kind, flags, hlen, seq, dropped, update, emit, sent, rev, _ = HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {magic!r}")
    if ver != FRAME_VERSION:
        raise ProtocolError(f"unsupported frame version {ver}", "unsupported_version")
    if kind not in KIND_NAMES:
        raise ProtocolError(f"unknown frame kind {kind}")
    if hlen < HEADER_LEN or hlen > len(buf):
        raise ProtocolError(f"bad header length {hlen}")
    return Header(kind, update, emit, rev, flags, seq, dropped, sent, ver)


def decode_frame(buf: bytes | bytearray | memoryview) -> Frame:
    """Parse one binary frame; raises :class:`ProtocolError` on anything malformed."""
    buf = memoryview(buf).cast("B")
    h = decode_header(buf)
    p = HEADER.unpack_from(buf, 0)[4]  # header_len: later versions may extend the header
    try:
        if h.kind == KIND_SPIKES:
            n, mask, *finals = SPIKES_HEAD.unpack_from(buf, p)
            p += SPIKES_HEAD.size
            _need(buf, p + n * EVENT_DTYPE.itemsize)
            ev = np.frombuffer(buf, EVENT_DTYPE, n, p)
            final = {c: (finals[i] if mask >> i & 1 else None) for i, c in enumerate(CLASSES)}
            return SpikesFrame(h, ev["t_us"].copy(), ev["taxel"].copy(), ev["cls"].copy(), final)
        if h.kind == KIND_CHANNELS:
            t0, period, n_s, n_t, n_c = CHANNELS_HEAD.unpack_from(buf, p)
            p += CHANNELS_HEAD.size
            taxels, p = _taxels(buf, p, n_t)
            _need(buf, p + 4 * n_s * n_t * n_c)
            data = np.frombuffer(buf, "<f4", n_s * n_t * n_c, p).reshape(n_s, n_t, n_c).copy()
            return ChannelsFrame(h, t0, period, taxels, data)
        dec, n_t, n_v, n_s = DECODED_HEAD.unpack_from(buf, p)
        p += DECODED_HEAD.size
        taxels, p = _taxels(buf, p, n_t)
        _need(buf, p + 8 * n_s + 4 * n_s * n_t * n_v)
        t_us = np.frombuffer(buf, "<u8", n_s, p).copy()
        values = np.frombuffer(buf, "<f4", n_s * n_t * n_v, p + 8 * n_s).reshape(n_s, n_t, n_v).copy()
        return DecodedFrame(h, dec, taxels, t_us, values)
    except struct.error as exc:
        raise ProtocolError(f"truncated {KIND_NAMES[h.kind]} frame: {exc}") from exc


def _need(buf: memoryview, n: int) -> None:
    if len(buf) < n:
        raise ProtocolError(f"truncated frame: {len(buf)} bytes, payload needs {n}")


def _taxels(buf: memoryview, p: int, n_t: int) -> tuple[np.ndarray, int]:
    _need(buf, p + 2 * n_t)
    return np.frombuffer(buf, "<u2", n_t, p).copy(), p + 2 * n_t + _pad4(2 * n_t)


# -- JSON frames -----------------------------------------------------------------------------------
def frame_json_body(frame: Frame) -> dict[str, Any]:
    """The JSON encoding of a frame without the per-connection fields (seq, dropped, sent_us)."""
    h = frame.header
    out: dict[str, Any] = {
        "type": KIND_NAMES[h.kind],
        "update": h.update,
        "emit_us": h.emit_us,
        "params_rev": h.params_rev,
        "flags": h.flag_names(),
    }
    if isinstance(frame, SpikesFrame):
        out["final_us"] = {c: v for c, v in frame.final_us.items() if v is not None}
        out["t_us"] = frame.t_us.tolist()
        out["taxel"] = frame.taxel.tolist()
        out["class"] = [CLASSES[i] for i in frame.cls.tolist()]
    elif isinstance(frame, ChannelsFrame):
        out.update(t0_us=frame.t0_us, period_us=frame.period_us, taxels=frame.taxels.tolist(), channels=list(CHANNELS))
        out["data"] = np.round(frame.data.astype(np.float64), 7).tolist()
    else:
        out.update(decoder=frame.decoder, taxels=frame.taxels.tolist(), t_us=frame.t_us.tolist())
        out["values"] = np.round(frame.values.astype(np.float64), 7).tolist()
    return out


def render_json(body_text: str, seq: int, dropped: int, sent_us: int) -> str:
    """Prefix a JSON body (``json.dumps(frame_json_body(...))``) with the per-connection fields."""
    return f'{{"seq":{seq},"dropped":{dropped},"sent_us":{sent_us},{body_text[1:]}'


def frame_from_json(msg: dict[str, Any]) -> Frame:
    """Inverse of the JSON encoding (for clients that chose ``"encoding": "json"``)."""
    try:
        kind = {v: k for k, v in KIND_NAMES.items()}[msg["type"]]
        flags = sum(bit for bit, name in FLAG_NAMES.items() if name in msg.get("flags", []))
        h = Header(kind, msg["update"], msg["emit_us"], msg["params_rev"], flags, msg["seq"], msg["dropped"], msg["sent_us"])
        if kind == KIND_SPIKES:
            cls = np.array([CLASSES.index(c) for c in msg["class"]], np.uint8)
            final = {c: msg["final_us"].get(c) for c in CLASSES}
            return SpikesFrame(h, np.array(msg["t_us"], np.uint64), np.array(msg["taxel"], np.uint16), cls, final)
        if kind == KIND_CHANNELS:
            taxels = np.array(msg["taxels"], np.uint16)
            data = np.array(msg["data"], np.float32).reshape(-1, taxels.size, len(CHANNELS))
            return ChannelsFrame(h, msg["t0_us"], msg["period_us"], taxels, data)
        taxels = np.array(msg["taxels"], np.uint16)
        t_us = np.array(msg["t_us"], np.uint64)
        values = np.array(msg["values"], np.float32).reshape(t_us.size, taxels.size, -1)
        return DecodedFrame(h, msg["decoder"], taxels, t_us, values)
    except (KeyError, TypeError, ValueError) as exc:
        raise ProtocolError(f"malformed JSON frame: {exc!r}") from exc


# -- control messages --------------------------------------------------------------------------------
def id_ranges(ids: Iterable[int]) -> list[list[int]]:
    """Taxel ids as sorted half-open ranges ``[[start, stop], ...]`` (the form of a region's
    ``ranges``): ``[0, 1, 2, 5]`` -> ``[[0, 3], [5, 6]]``. A set of ids that a large skin makes
    (every taxel, a patch) stays a few numbers: ``/v1/status`` and the gateways' demand use it."""
    a = np.unique(np.fromiter(ids, np.int64))
    if a.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(a) != 1) + 1
    starts, stops = a[np.r_[0, cuts]], a[np.r_[cuts - 1, a.size - 1]] + 1
    return np.stack([starts, stops], axis=1).tolist()


@dataclass(frozen=True)
class Region:
    """A part of the skin: the taxels in any of its id ranges or rectangles.

    ``ranges``: half-open id ranges ``(start, stop)`` (:func:`parse_subscribe` sorts and merges them and
    drops empty ones). ``rects``:
    rectangles ``(x_min, x_max, y_min, y_max)`` in mm, closed, over the taxel centres the hello gives
    (:func:`hello_positions`)."""

    ranges: tuple[tuple[int, int], ...] = ()
    rects: tuple[tuple[float, float, float, float], ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"ranges": [[a, b] for a, b in self.ranges],
                "rects": [{"x_mm": [x0, x1], "y_mm": [y0, y1]} for x0, x1, y0, y1 in self.rects]}

    def mask(self, n_taxels: int, positions_mm: np.ndarray | None = None) -> np.ndarray:
        """(n_taxels,) bool: the taxels in the region. Without ``positions_mm`` ((n_taxels, 2) centres,
        mm) the rectangles cover no taxel."""
        m = np.zeros(n_taxels, bool)
        for a, b in self.ranges:
            m[a:b] = True
        if self.rects and positions_mm is not None:
            x, y = np.asarray(positions_mm, float)[:n_taxels].T
            for x0, x1, y0, y1 in self.rects:
                m[: x.size] |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        return m


@dataclass
class Subscription:
    """What a connection wants. Its taxels are those of ``taxels`` (ids) and ``region`` together; both
    ``None``: every taxel. ``classes`` ``None``: every class the service serves (its ``subscribed``
    reply names them); empty lists mean none."""

    taxels: list[int] | None = None
    classes: list[str] | None = None
    streams: list[str] = field(default_factory=lambda: ["spikes"])
    encoding: str = "binary"
    decimation: int = 25  #: channels: one 5 kHz sample in this many (25 -> 200 Hz)
    decoders: list[str] | None = None  #: decoded: names, None = every installed decoder
    region: Region | None = None  #: a part of the skin by id ranges or rectangles (mm)
    version: int = VERSION  #: the session protocol version the subscriber speaks

    def to_json(self) -> dict[str, Any]:
        """The ``subscribe`` message; ``region`` only when set (a server older than regions refuses the field)."""
        out = {
            "type": "subscribe",
            "version": self.version,
            "taxels": self.taxels,
            "classes": self.classes,
            "streams": self.streams,
            "encoding": self.encoding,
            "channels": {"decimation": self.decimation},
            "decoders": self.decoders,
        }
        if self.region is not None:
            out["region"] = self.region.to_json()
        return out

    def taxel_ids(self, n_taxels: int, positions_mm: np.ndarray | None = None) -> np.ndarray | None:
        """The sorted ids (int64) of the subscribed taxels of a skin of ``n_taxels`` (``positions_mm``:
        its (n_taxels, 2) centres, mm, for rectangles); None when it names none, i.e. wants every taxel."""
        if self.taxels is None and self.region is None:
            return None
        m = np.zeros(n_taxels, bool) if self.region is None else self.region.mask(n_taxels, positions_mm)
        ids = np.asarray(self.taxels or [], np.int64)
        m[ids[ids < n_taxels]] = True
        return np.flatnonzero(m)


def parse_subscribe(msg: dict[str, Any]) -> Subscription:
    """Validate a subscribe message (every field but ``type`` optional); raise :class:`ProtocolError`."""
    version = msg.get("version", VERSION)
    if version not in SUPPORTED_VERSIONS:
        raise ProtocolError(f"protocol version {version!r} is not supported (supported: {list(SUPPORTED_VERSIONS)})", "unsupported_version")
    unknown = set(msg) - {"type", "version", "taxels", "region", "classes", "streams", "encoding", "channels", "decoders"}
    if unknown:
        raise ProtocolError(f"unknown subscribe fields {sorted(unknown)}")
    sub = Subscription(version=version)
    taxels = msg.get("taxels")
    if taxels is not None:
        if not isinstance(taxels, list) or not all(_is_int(t) and 0 <= t < MAX_TAXELS for t in taxels):
            raise ProtocolError("taxels must be null or a list of taxel ids (integers)")
        sub.taxels = sorted(set(taxels))
    sub.region = _parse_region(msg.get("region"))
    sub.classes = None if msg.get("classes") is None else _names(msg, "classes", CLASSES, [])
    sub.streams = _names(msg, "streams", STREAMS, sub.streams)
    enc = msg.get("encoding", sub.encoding)
    if enc not in ENCODINGS:
        raise ProtocolError(f"encoding must be one of {list(ENCODINGS)}, got {enc!r}")
    sub.encoding = enc
    ch = msg.get("channels") or {}
    if not isinstance(ch, dict) or set(ch) - {"decimation"}:
        raise ProtocolError('channels must be an object {"decimation": int}')
    dec = ch.get("decimation", sub.decimation)
    if not isinstance(dec, int) or isinstance(dec, bool) or not 1 <= dec <= 5000:
        raise ProtocolError("channels.decimation must be an integer in 1..5000")
    sub.decimation = dec
    decoders = msg.get("decoders")
    if decoders is not None and (not isinstance(decoders, list) or not all(isinstance(d, str) for d in decoders)):
        raise ProtocolError("decoders must be null or a list of decoder names")
    sub.decoders = decoders
    return sub


_REGION_SHAPE = ('region must be null or {"ranges": [[start, stop], ...], '
                 '"rects": [{"x_mm": [min, max], "y_mm": [min, max]}, ...]}')


def _parse_region(v: Any) -> Region | None:
    """A subscription's ``region`` (None: none), validated: at most :data:`MAX_REGION_RANGES` id ranges
    ``0 <= start <= stop <= MAX_TAXELS`` and :data:`MAX_REGION_RECTS` rectangles of finite ``min <= max``."""
    if v is None:
        return None
    if not isinstance(v, dict) or set(v) - {"ranges", "rects"}:
        raise ProtocolError(_REGION_SHAPE)
    ranges, rects = v.get("ranges") or [], v.get("rects") or []
    if not isinstance(ranges, list) or not isinstance(rects, list):
        raise ProtocolError(_REGION_SHAPE)
    if len(ranges) > MAX_REGION_RANGES or len(rects) > MAX_REGION_RECTS:
        raise ProtocolError(f"a region has at most {MAX_REGION_RANGES} ranges and {MAX_REGION_RECTS} rects")
    spans = []
    for r in ranges:
        if not (isinstance(r, list) and len(r) == 2 and all(_is_int(x) for x in r) and 0 <= r[0] <= r[1] <= MAX_TAXELS):
            raise ProtocolError(f"region.ranges holds [start, stop] id ranges, 0 <= start <= stop <= {MAX_TAXELS}")
        spans.append((r[0], r[1]))
    boxes = []
    for r in rects:
        if not isinstance(r, dict) or set(r) != {"x_mm", "y_mm"}:
            raise ProtocolError('region.rects holds {"x_mm": [min, max], "y_mm": [min, max]} rectangles')
        box = [_interval_mm(r[k], f"region.rects {k}") for k in ("x_mm", "y_mm")]
        boxes.append((*box[0], *box[1]))
    return Region(_merged(spans), tuple(boxes))


def _interval_mm(v: Any, what: str) -> tuple[float, float]:
    if not (isinstance(v, list) and len(v) == 2 and all(_is_mm(x) for x in v) and v[0] <= v[1]):
        raise ProtocolError(f"{what} must be [min, max]: finite numbers (mm), min <= max")
    return float(v[0]), float(v[1])


def _merged(spans: list[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
    """Half-open ranges sorted, overlapping or adjacent ones merged, empty ones dropped."""
    out: list[tuple[int, int]] = []
    for a, b in sorted(s for s in spans if s[0] < s[1]):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return tuple(out)


def _names(msg: dict[str, Any], key: str, allowed: tuple[str, ...], default: list[str]) -> list[str]:
    v = msg.get(key)
    if v is None:
        return list(default)
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ProtocolError(f"{key} must be a list of names from {list(allowed)}")
    bad = [x for x in v if x not in allowed]
    if bad:
        raise ProtocolError(f"unknown {key} {bad}; expected names from {list(allowed)}")
    return [x for x in allowed if x in v]


def _refuse_constant(name: str) -> Any:
    raise ProtocolError(f"{name} is not valid JSON: numbers must be finite")


#: a run of more digits than an integer literal may have (str and bytes messages)
_LONG_DIGITS = {str: re.compile("[0-9]{%d}" % (MAX_INT_DIGITS + 1)), bytes: re.compile(b"[0-9]{%d}" % (MAX_INT_DIGITS + 1))}


def _bounded_int(literal: str) -> int:
    if len(literal.lstrip("-")) > MAX_INT_DIGITS:
        raise ProtocolError(f"an integer of {len(literal)} digits; at most {MAX_INT_DIGITS} are accepted")
    return int(literal)


def _finite_float(literal: str) -> float:
    v = float(literal)
    if not math.isfinite(v):
        raise ProtocolError(f"the number {literal[:40]} overflows: numbers must be finite")
    return v


def parse_client_message(text: str | bytes) -> dict[str, Any]:
    """Decode a client's text message: a JSON object with a known ``type``. Strict JSON: no
    ``NaN``/``Infinity``, finite numbers, integers of at most :data:`MAX_INT_DIGITS` digits, bounded
    nesting; anything else raises :class:`ProtocolError` (``bad_message``), never another exception."""
    if len(text) > MAX_CLIENT_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(text)} bytes exceeds {MAX_CLIENT_MESSAGE_BYTES}", "too_big")
    # the integer hook costs a Python call per integer (5 ms for a 64 KiB taxel list): only texts with a
    # run of more digits than an integer may have need it
    long_digits = _LONG_DIGITS[str if isinstance(text, str) else bytes].search(text)
    bounded = {"parse_int": _bounded_int} if long_digits else {}
    try:
        msg = json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float, **bounded)
    except ProtocolError:
        raise
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError; nesting past the stack limit
        raise ProtocolError(f"not valid JSON: {exc}") from exc
    if not isinstance(msg, dict) or msg.get("type") not in ("subscribe", "time"):
        raise ProtocolError('expected a JSON object with "type": "subscribe" or "time"')
    if msg["type"] == "time":
        if not _is_uint(msg.get("t0_us", 0)):
            raise ProtocolError("time.t0_us must be a non-negative integer (client clock, us)")
        if not _time_id_ok(msg.get("id")):
            raise ProtocolError(f"time.id must be null, a string of at most {MAX_TIME_ID_CHARS} characters or an "
                                "integer in [-2^63, 2^64)")
    return msg


def _time_id_ok(v: Any) -> bool:
    if v is None:
        return True
    if isinstance(v, str):
        return len(v) <= MAX_TIME_ID_CHARS
    return isinstance(v, int) and not isinstance(v, bool) and -(2**63) <= v < 2**64


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_uint(v: Any) -> bool:
    return _is_int(v) and 0 <= v < 2**64


def time_reply(request: dict[str, Any], t1_us: int, t2_us: int) -> dict[str, Any]:
    """Answer to an NTP-style time request: the client's t0 back with the server's receive (t1) and
    send (t2) wall-clock times (us)."""
    return {"type": "time", "id": request.get("id"), "t0_us": request.get("t0_us", 0), "t1_us": t1_us, "t2_us": t2_us}


def clock_offset(t0_us: int, t1_us: int, t2_us: int, t3_us: int) -> tuple[float, float]:
    """(server minus client clock offset, round-trip delay) in us from one time exchange; the offset's
    uncertainty is at most half the delay."""
    return ((t1_us - t0_us) + (t2_us - t3_us)) / 2.0, float((t3_us - t0_us) - (t2_us - t1_us))


def error_message(code: str, message: str) -> dict[str, Any]:
    """An ``error`` message; its text is cut to :data:`MAX_ERROR_CHARS` (it may quote the client)."""
    if len(message) > MAX_ERROR_CHARS:
        message = message[: MAX_ERROR_CHARS - 1] + "…"
    return {"type": "error", "code": code, "message": message}


# -- the skin in the hello -------------------------------------------------------------------------------
def hello_skin(positions_mm: np.ndarray) -> dict[str, Any]:
    """The hello's description of a skin of (n, 2) taxel centres (mm): ``n_taxels``; ``layout``, the grid
    they form (None when they form none: :func:`grid_layout`); ``taxels``, every taxel as ``{"id", "x_mm",
    "y_mm"}``, or None for a grid of more than :data:`HELLO_LISTED_TAXELS` taxels (its layout says it all)."""
    xy = np.asarray(positions_mm, float).reshape(-1, 2)
    layout = grid_layout(xy)
    listed = layout is None or len(xy) <= HELLO_LISTED_TAXELS
    return {"n_taxels": len(xy), "layout": layout,
            "taxels": [{"id": i, "x_mm": x, "y_mm": y} for i, (x, y) in enumerate(xy.tolist())] if listed else None}


def grid_layout(positions_mm: np.ndarray) -> dict[str, Any] | None:
    """The grid (n, 2) taxel centres (mm) form, as the hello's ``layout``: taxel i at ``(x0_mm + (i mod
    cols) * dx_mm, y0_mm + (i div cols) * dy_mm)``, row-major, the last row possibly short; None when
    the centres are no such grid to within :data:`GRID_TOLERANCE_MM`."""
    xy = np.asarray(positions_mm, float).reshape(-1, 2)
    n = len(xy)
    if n == 0 or not np.isfinite(xy).all():
        return None
    off_row = np.flatnonzero(xy[:, 1] != xy[0, 1])
    cols = int(off_row[0]) if off_row.size else n  # the first row ends where y first changes
    rows = -(-n // cols)
    layout = {"kind": "grid", "rows": rows, "cols": cols, "x0_mm": float(xy[0, 0]), "y0_mm": float(xy[0, 1]),
              "dx_mm": float(xy[1, 0] - xy[0, 0]) if cols > 1 else 0.0,
              "dy_mm": float(xy[cols, 1] - xy[0, 1]) if rows > 1 else 0.0}
    return layout if np.abs(_grid_positions(layout, n) - xy).max() <= GRID_TOLERANCE_MM else None


def _grid_positions(layout: dict[str, Any], n: int) -> np.ndarray:
    i = np.arange(n)
    return np.stack([layout["x0_mm"] + (i % layout["cols"]) * layout["dx_mm"],
                     layout["y0_mm"] + (i // layout["cols"]) * layout["dy_mm"]], axis=1)


def hello_positions(hello: dict[str, Any]) -> np.ndarray:
    """(n_taxels, 2) taxel centres (mm, row = taxel id) a hello describes: its ``taxels`` list, else its
    grid ``layout`` (a skin of more than :data:`HELLO_LISTED_TAXELS` taxels lists none). Raises
    :class:`ProtocolError` for a description that is malformed or names no skin."""
    listed = hello.get("taxels")
    if listed is not None:
        if not isinstance(listed, list) or len(listed) > MAX_TAXELS:
            raise ProtocolError(f"hello.taxels must be a list of at most {MAX_TAXELS} taxels")
        if not all(isinstance(t, dict) and _is_int(t.get("id")) and _is_mm(t.get("x_mm")) and _is_mm(t.get("y_mm"))
                   for t in listed):
            raise ProtocolError("hello.taxels holds {id, x_mm, y_mm} objects (an integer, finite numbers)")
        pos = {t["id"]: (t["x_mm"], t["y_mm"]) for t in listed}
        if sorted(pos) != list(range(len(listed))):
            raise ProtocolError("hello.taxels must list the ids 0..n-1 once each")
        return np.array([pos[i] for i in range(len(listed))], float).reshape(-1, 2)
    n, g = hello.get("n_taxels"), hello.get("layout")
    if not (_is_int(n) and 0 <= n <= MAX_TAXELS) or not isinstance(g, dict) or g.get("kind") != "grid":
        raise ProtocolError("a hello without taxels must give n_taxels and a grid layout")
    if not (all(_is_int(g.get(k)) and 1 <= g[k] <= MAX_TAXELS for k in ("rows", "cols")) and g["rows"] * g["cols"] >= n
            and all(_is_mm(g.get(k)) for k in ("x0_mm", "y0_mm", "dx_mm", "dy_mm"))):
        raise ProtocolError("hello.layout must be {kind: grid, rows, cols >= 1 covering n_taxels, finite x0_mm, "
                            "y0_mm, dx_mm, dy_mm}")
    return _grid_positions(g, n)


def hello_taxels(hello: dict[str, Any]) -> list[dict[str, Any]]:
    """Every taxel of a hello as ``{"id", "x_mm", "y_mm"}`` (mm), listed or from its grid ``layout``
    (:func:`hello_positions`, whose errors it raises)."""
    return [{"id": i, "x_mm": x, "y_mm": y} for i, (x, y) in enumerate(hello_positions(hello).tolist())]


@dataclass(frozen=True)
class Afferents:
    """A population's afferents as a version-2 hello lists them (row = afferent id): ``cls`` (index
    into CLASSES), position (mm) and ``model`` (the TouchSim single-unit model within its class)."""

    cls: np.ndarray  # (A,) int64
    xy_mm: np.ndarray  # (A, 2) float64
    model: np.ndarray  # (A,) int64
    plan: dict[str, Any]

    def ids(self, cls: str) -> np.ndarray:
        return np.flatnonzero(self.cls == CLASSES.index(cls))


def hello_afferents(hello: dict[str, Any]) -> Afferents | None:
    """The afferents of a hello whose ``addresses`` are "afferents" (None for a skin of taxels); raises
    :class:`ProtocolError` for a ``population`` that is malformed."""
    if hello.get("addresses", "taxels") == "taxels":
        return None
    pop = hello.get("population")
    if hello.get("addresses") != "afferents" or not isinstance(pop, dict):
        raise ProtocolError("hello.addresses must be 'taxels' or 'afferents' (with a population object)")
    n = pop.get("n_afferents")
    if not (_is_int(n) and 0 < n <= MAX_TAXELS):
        raise ProtocolError(f"hello.population.n_afferents must be an integer in 1..{MAX_TAXELS}")
    cols = [pop.get(k) for k in ("x_mm", "y_mm", "model")]
    if not all(isinstance(c, list) and len(c) == n for c in cols) or not all(_is_mm(v) for v in cols[0] + cols[1]) \
            or not all(_is_int(v) and 0 <= v < 64 for v in cols[2]):
        raise ProtocolError("hello.population needs x_mm, y_mm (finite numbers) and model (small integers), one per afferent")
    cls = np.full(n, -1, np.int64)
    classes = pop.get("classes")
    if not isinstance(classes, dict) or not set(classes) <= set(CLASSES):
        raise ProtocolError(f"hello.population.classes maps classes of {list(CLASSES)} to id ranges")
    for name, ranges in classes.items():
        if not isinstance(ranges, list) or not all(isinstance(r, list) and len(r) == 2 and all(_is_int(v) for v in r)
                                                   and 0 <= r[0] < r[1] <= n for r in ranges):
            raise ProtocolError(f"hello.population.classes[{name!r}] must be id ranges [[start, stop], ...] within 0..{n}")
        for a, b in ranges:
            cls[a:b] = CLASSES.index(name)
    if (cls < 0).any():
        raise ProtocolError("hello.population.classes must give every afferent a class")
    plan = pop.get("plan") if isinstance(pop.get("plan"), dict) else {}
    return Afferents(cls, np.array([cols[0], cols[1]], float).T.reshape(n, 2), np.array(cols[2], np.int64), plan)


def _is_mm(v: Any) -> bool:
    """A finite JSON number (a coordinate in mm)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and -1e300 < v < 1e300
