"""Record a ``/v1/stream`` session into an MCAP file (https://mcap.dev), chunked and indexed, that the
Foxglove app and the ``mcap`` library read (extra ``[mcap]``).

Topics carry JSON messages described by JSON Schemas (``message_encoding`` ``json``, schema encoding
``jsonschema``), one message per event so that Foxglove plots them directly:

* ``/touchreal/spikes/<CLASS>`` (SA1, RA, PC): one message per spike: ``t_us`` (wire clock, integer
  us, exactly as on the stream), ``taxel``, ``class``, ``update``, ``params_rev``.
* ``/touchreal/channels``: one message per received (decimated) 5 kHz grid sample: ``t_us`` and, per
  taxel of ``taxels``, ``ST`` [N], ``dST`` [N/s], ``PVDF`` [V], ``dPVDF`` [V/s] (null = NaN).
* ``/touchreal/decoded/<DECODER>``: one message per decoder step: ``t_us`` (end of the decoding
  window), ``taxels``, ``outputs`` (names), ``values[taxel][output]`` (null = NaN).
* ``/touchreal/clock``: the stream's clock points (the ``clock`` messages, docs/stream-protocol.md).

``log_time`` (ns) is when it happened on the recorder's wall clock: the stamp mapped by the
stream's clock model (:class:`~.clock.ClockMap`) to the server's wall clock, minus the ``time``
offset measured at the start (for a spike the stamp is the spike itself; for channels and decoded
outputs the sample or the end of the window); a clock point's is its ``wall_us``. ``publish_time`` is
the frame's receipt. Attachments: ``hello.json`` for every ``hello`` received, ``params/rev-<N>.json``
for every parameter revision a frame carries (``GET /v1/params`` / ``/v1/params/history``).
Metadata: ``touchreal.recording`` (source, subscription, offset) and ``touchreal.recording.end``
(stop reason and counts). :mod:`.recording` reads such a file back.
"""

from __future__ import annotations

import asyncio
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

from . import __version__
from . import protocol as P
from .client import AsyncClient
from .clock import ClockMap, ClockPoint
from .errors import RequestError, ServiceUnavailable, StreamClosed
from .session import Coverage
from .stream import AsyncStream, DecodedOutput, wall_us
from .topics import (CHANNELS_SCHEMA, CHANNELS_TOPIC, CLOCK_SCHEMA, CLOCK_TOPIC, DECODED_SCHEMA, PROFILE,
                     SPIKE_SCHEMA, decoded_topic, spikes_topic)
from .topics import json_lists as _lists

IDLE_POLL_S = 0.2  #: with no frame for this long, the recorder checks whether the stream has ended


class McapRecorder:
    """Sans-I/O: the messages of one stream in, MCAP records out (``mcap``'s chunked, indexed
    writer, zstd). ``clock``: the stream's clock map (reassign it when the stream replaces it, as on
    a new server session). Call :meth:`finish` once; the file is valid only after it."""

    def __init__(self, fp: IO[bytes], clock: ClockMap, chunk_size: int = 1 << 20):
        self.clock = clock
        self._w = Writer(fp, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._w.start(profile=PROFILE, library=f"touchreal-client {__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq = 0
        self._clock_seen: set[tuple[int, int]] = set()
        self.params_revs: set[int] = set()
        self.coverage = Coverage()
        self.counts = {"frames": 0, "spikes": 0, "channel_samples": 0, "decoded_steps": 0, "clock_points": 0,
                       "hellos": 0, "log_time_from_receipt": 0}

    # -- records ----------------------------------------------------------------------------------
    def _channel(self, topic: str, schema: dict[str, Any]) -> int:
        if topic not in self._channels:
            name = schema["title"]
            if name not in self._schemas:
                self._schemas[name] = self._w.register_schema(name, "jsonschema", json.dumps(schema).encode())
            self._channels[topic] = self._w.register_channel(topic, "json", self._schemas[name])
        return self._channels[topic]

    def _write(self, channel: int, log_ns: int, publish_ns: int, payload: dict[str, Any]) -> None:
        self._w.add_message(channel, log_ns, json.dumps(payload, separators=(",", ":"), allow_nan=False).encode(),
                            publish_ns, self._seq & 0xFFFFFFFF)
        self._seq += 1

    def _log_ns(self, t_us: np.ndarray, recv_us: int) -> np.ndarray:
        """Stamps (wire clock, us) -> log times (ns, recorder's wall clock); the receipt time for
        stamps that no clock point maps yet (a server without a clock model)."""
        try:
            local = np.atleast_1d(self.clock.to_local_us(t_us))
        except LookupError:
            self.counts["log_time_from_receipt"] += int(np.size(t_us))
            local = np.full(np.size(t_us), float(recv_us))
        return np.maximum(np.round(local), 0).astype(np.int64) * 1000

    def add_metadata(self, name: str, values: dict[str, Any]) -> None:
        """A metadata record; values are stored as strings (JSON for anything but a string)."""
        self._w.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def add_hello(self, hello: dict[str, Any], recv_us: int) -> None:
        self.counts["hellos"] += 1
        self.coverage.update_us = int(hello.get("update_us", self.coverage.update_us))
        self._w.add_attachment(recv_us * 1000, recv_us * 1000, "hello.json", "application/json",
                               json.dumps(hello).encode())

    def add_params(self, info: dict[str, Any], recv_us: int) -> None:
        """One parameter revision: ``{"rev", "sha256", "params" (or None), "source"}``."""
        self.params_revs.add(int(info["rev"]))
        self._w.add_attachment(recv_us * 1000, recv_us * 1000, f"params/rev-{info['rev']}.json", "application/json",
                               json.dumps(info).encode())

    def add_clock_points(self, points: list[ClockPoint], recv_us: int) -> None:
        """The clock points not written yet."""
        ch = None
        for p in points:
            key = (p.epoch, p.sensor_us)
            if key in self._clock_seen:
                continue
            self._clock_seen.add(key)
            ch = ch or self._channel(CLOCK_TOPIC, CLOCK_SCHEMA)
            log_ns = max(round(p.wall_us - self.clock.offset_us), 0) * 1000
            self._write(ch, log_ns, recv_us * 1000, p.to_json())
            self.counts["clock_points"] += 1

    def add_frame(self, frame: P.SpikesFrame | P.ChannelsFrame | DecodedOutput, recv_us: int) -> None:
        h = frame.header
        meta = {"update": h.update, "params_rev": h.params_rev}
        pub = recv_us * 1000
        self.counts["frames"] += 1
        if isinstance(frame, P.SpikesFrame):
            logs = self._log_ns(frame.t_us, recv_us)
            for t, taxel, k, log in zip(frame.t_us.tolist(), frame.taxel.tolist(), frame.cls.tolist(), logs.tolist()):
                cls = P.CLASSES[k]
                self._write(self._channel(spikes_topic(cls), SPIKE_SCHEMA), log, pub,
                            {"t_us": t, "taxel": taxel, "class": cls, **meta})
            self.counts["spikes"] += frame.t_us.size
            self.coverage.push(frame)
        elif isinstance(frame, P.ChannelsFrame):
            ch = self._channel(CHANNELS_TOPIC, CHANNELS_SCHEMA)
            t = frame.t0_us + frame.period_us * np.arange(frame.data.shape[0], dtype=np.uint64)
            taxels = frame.taxels.tolist()
            rows = _lists(frame.data.transpose(0, 2, 1))  # [sample][channel][taxel]
            for t_k, log, row in zip(t.tolist(), self._log_ns(t, recv_us).tolist(), rows):
                self._write(ch, log, pub, {"t_us": t_k, "taxels": taxels, **dict(zip(P.CHANNELS, row)), **meta})
            self.counts["channel_samples"] += t.size
        else:
            ch = self._channel(decoded_topic(frame.name), DECODED_SCHEMA)
            taxels = frame.taxels.tolist()
            rows = _lists(frame.values)  # [step][taxel][output]
            for t_s, log, values in zip(frame.t_us.tolist(), self._log_ns(frame.t_us, recv_us).tolist(), rows):
                self._write(ch, log, pub, {"t_us": t_s, "taxels": taxels, "outputs": frame.outputs, "values": values, **meta})
            self.counts["decoded_steps"] += frame.t_us.size

    def finish(self) -> None:
        self._w.finish()


@dataclass
class RecordSummary:
    """What :func:`record` wrote: counts per kind, why it stopped, frames the server dropped for us."""

    path: Path
    stop_reason: str
    counts: dict[str, int] = field(default_factory=dict)
    missed_frames: int = 0
    params_revs: list[int] = field(default_factory=list)


def http_base(url: str) -> str:
    """``ws://HOST:PORT/v1/stream`` or ``http://HOST:PORT`` -> ``http://HOST:PORT`` (REST base)."""
    u = url.rstrip("/").removesuffix("/v1/stream")
    for ws, http in (("wss://", "https://"), ("ws://", "http://")):
        if u.startswith(ws):
            return http + u[len(ws):]
    return u if u.startswith(("http://", "https://")) else "http://" + u


async def _params_at(tr: AsyncClient, rev: int, hello: dict[str, Any]) -> dict[str, Any]:
    """The parameter set of revision ``rev``: in full if it is the active one (``GET /v1/params``), else
    its history entry; through a gateway (no REST) what the hello says."""
    try:
        active = await tr.params()
        if active.get("rev") == rev:
            return {"rev": rev, "sha256": active["sha256"], "params": active["params"], "source": "GET /v1/params"}
        for r in (await tr.params_history()).get("revisions", []):
            if r.get("rev") == rev:
                return {"rev": rev, "sha256": r.get("sha256"), "params": None, "source": "GET /v1/params/history"}
    except (ServiceUnavailable, RequestError):
        pass
    said = hello.get("params") or {}
    return {"rev": rev, "sha256": said.get("sha256") if said.get("rev") == rev else None, "params": None, "source": "hello"}


async def record(url: str, out: str | Path, *, seconds: float | None = None,
                 streams: tuple[str, ...] = P.STREAMS, decimation: int = 25,
                 taxels: list[int] | None = None) -> RecordSummary:
    """Record the stream at ``url`` (``http://HOST:PORT`` or ``ws://HOST:PORT/v1/stream``, a service or
    a gateway) into the MCAP file ``out`` for ``seconds`` (None: until the stream closes or the task
    is cancelled, e.g. Ctrl-C). ``streams``: any of spikes, channels, decoded (every decoder);
    ``decimation``: channels, one 5 kHz sample in this many. The file is complete however it stops."""
    if not streams:
        raise ValueError(f"streams must name some of {list(P.STREAMS)}")
    sub = P.Subscription(taxels=taxels, streams=list(streams), decimation=decimation)
    P.parse_subscribe(sub.to_json())  # the server's own validation (ProtocolError, a ValueError), before connecting
    out = Path(out)
    stop = ""
    async with AsyncClient(http_base(url)) as tr:
        s = tr.stream(sub, queue_frames=8192)
        await s.open()
        try:
            if P.hello_afferents(s.hello) is not None and set(sub.streams) - {"spikes"}:
                # a population's afferents have spikes only (channels and decoders are per taxel)
                if "spikes" not in sub.streams:
                    raise ValueError(f"{url} serves a population, whose afferents have spikes only: record spikes")
                sub = replace(sub, streams=["spikes"])
            await s.subscribe(sub)  # waiting for the server's answer: StreamError if refused
            await s.sync_clock()
            with out.open("wb") as fp:
                rec = McapRecorder(fp, s.clock)
                rec.add_metadata("touchreal.recording", {
                    "url": url, "session": str(s.hello.get("session")), "server": str(s.hello.get("server")),
                    "subscription": sub.to_json(), "started_wall_us": wall_us(), "clock_offset_us": s.clock.offset_us,
                    "clock_offset_error_us": s.clock.offset_error_us})
                try:
                    stop = await _pump(s, tr, rec, seconds)
                except BaseException as exc:  # Ctrl-C (a cancelled task) or a malformed message: still a complete file
                    stop = f"aborted: {type(exc).__name__} {exc}".strip()
                    raise
                finally:
                    rec.add_metadata("touchreal.recording.end", {
                        "stop_reason": stop, "ended_wall_us": wall_us(), "missed_frames": s.stats.missed_frames,
                        "server_dropped": s.stats.server_dropped, "coverage_us": rec.coverage.spans, **rec.counts})
                    rec.finish()
        finally:
            await s.close()
    return RecordSummary(out, stop, dict(rec.counts), s.stats.missed_frames, sorted(rec.params_revs))


async def _pump(s: AsyncStream, tr: AsyncClient, rec: McapRecorder, seconds: float | None) -> str:
    """Frames into the recorder until ``seconds`` pass, the server says the stream has ``ended`` (a
    replay finished: it comes after the last frame, so nothing is left once the queue is empty) or
    the stream closes for good; returns the stop reason."""
    loop = asyncio.get_running_loop()
    deadline = math.inf if seconds is None else loop.time() + seconds
    frames = s.frames().__aiter__()
    nxt: asyncio.Future[P.Frame] | None = None
    hello_seen: dict[str, Any] | None = None
    try:
        while loop.time() < deadline:
            nxt = nxt or asyncio.ensure_future(anext(frames))
            done, _ = await asyncio.wait({nxt}, timeout=min(IDLE_POLL_S, max(deadline - loop.time(), 0.0)))
            if not done:
                if getattr(s, "ended", None) is not None:  # AsyncStream.ended: the server's `ended` message
                    return "ended"
                continue
            f, nxt = nxt.result(), None
            recv = f.header.recv_us
            rec.clock = s.clock  # a new server session comes with a new map
            if s.hello is not hello_seen:
                hello_seen = s.hello
                rec.add_hello(hello_seen, recv)
            rec.add_clock_points(s.clock.points, recv)
            if f.header.params_rev not in rec.params_revs:
                rec.add_params(await _params_at(tr, f.header.params_rev, s.hello), recv)
            rec.add_frame(s.name_decoded(f) if isinstance(f, P.DecodedFrame) else f, recv)
        return "seconds"
    except StopAsyncIteration:
        return "stream ended"
    except StreamClosed as exc:
        return f"stream closed: {exc}"
    finally:
        if nxt is not None:
            nxt.cancel()
