"""The ``/v1/stream`` WebSocket client (asyncio): hello, subscriptions, frames, clock sync, reconnect.

One reader task per stream owns the socket's receiving side. It decodes binary (or JSON) frames,
counts them (:class:`~.stats.StreamStats`, :class:`~.stats.LatencyEstimator`) and puts them on a
bounded queue that :meth:`AsyncStream.frames` drains; control replies (``subscribed``, ``time``,
``error``) resolve the request that asked for them, in order (the server answers in order). When
the consumer falls behind, the queue fills, the reader stops reading and the server's flow control
drops frames for this client (seen as ``seq`` gaps in :attr:`AsyncStream.stats`). A malformed
frame from the server (:class:`~touchreal_client.protocol.ProtocolError`) ends the iteration with
that error.

When the connection drops, the reader reconnects with :class:`~.backoff.Backoff`, reads the new
``hello`` and sends the current subscription again; iteration just continues. Closes that
reconnecting cannot cure (unsupported version, a message too big, too many malformed messages)
end the iteration with :class:`~.errors.StreamClosed`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import time
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import websockets
from websockets.asyncio.client import ClientConnection, connect

from . import protocol as P
from .backoff import Backoff
from .clock import ClockMap
from .errors import ServiceUnavailable, StreamClosed, StreamError
from .stats import LatencyEstimator, StreamStats, spike_latency_us

#: Close codes after which reconnecting would only repeat the failure.
FATAL_CLOSE_CODES = frozenset({P.CLOSE_UNSUPPORTED_VERSION, P.CLOSE_TOO_BIG, P.CLOSE_TOO_MANY_ERRORS})
_END = object()


def wall_us() -> int:
    """The client's wall clock in integer microseconds (Unix epoch)."""
    return time.time_ns() // 1000


def stream_url(base_url: str) -> str:
    """``http://HOST:PORT`` (or ``ws://...``, with or without ``/v1/stream``) -> the stream URL."""
    url = base_url.rstrip("/")
    for http, ws in (("https://", "wss://"), ("http://", "ws://")):
        if url.startswith(http):
            url = ws + url[len(http):]
    if not url.startswith(("ws://", "wss://")):
        url = "ws://" + url
    return url if url.endswith("/v1/stream") else url + "/v1/stream"


@dataclass(frozen=True)
class DecodedOutput:
    """A decoded-output frame with its decoder named: ``values[s, i, j]`` is output ``outputs[j]``
    of taxel ``taxels[i]`` at sensor time ``t_us[s]`` (us, end of the decoding window)."""

    name: str
    outputs: list[str]
    taxels: np.ndarray
    t_us: np.ndarray
    values: np.ndarray
    header: P.Header


class AsyncStream:
    """One stream from a TouchReal service. Use as ``async with AsyncStream(url, sub) as s:``.

    ``subscription``: what to receive (:class:`~touchreal_client.protocol.Subscription`; None = the
    default one: every taxel's and class's spikes, binary). It is sent on every (re)connect. ``reconnect``: reconnect after a dropped
    connection (``backoff`` sets the delays and how many attempts). ``queue_frames``: frames held for
    a slow consumer before the reader stops reading.
    """

    def __init__(self, url: str, subscription: P.Subscription | None = None, *, reconnect: bool = True,
                 backoff: Backoff | None = None, queue_frames: int = 1024, open_timeout_s: float = 10.0,
                 request_timeout_s: float = 10.0):
        self.url = stream_url(url)
        self.subscription = subscription or P.Subscription()
        self.reconnect = reconnect
        self.backoff = backoff or Backoff()
        self.open_timeout_s = open_timeout_s
        self.request_timeout_s = request_timeout_s
        self.hello: dict[str, Any] = {}
        #: the session protocol version agreed with the server at open (the newest both speak)
        self.version = self.subscription.version
        self.subscribed: dict[str, Any] | None = None  #: the server's last ``subscribed`` reply
        self.ended: dict[str, Any] | None = None  #: the server's ``ended`` message (its replay has finished)
        self.stats = StreamStats()
        self.latency = LatencyEstimator()
        self.clock = ClockMap()  #: the server's clock model (``clock`` messages) plus the ``time`` offset
        self.errors: list[dict[str, Any]] = []  #: ``error`` messages that answered no request
        self._queue: asyncio.Queue[Any] = asyncio.Queue(queue_frames)
        self._pending: deque[tuple[str, asyncio.Future[dict[str, Any]]]] = deque()
        self._ws: ClientConnection | None = None
        self._reader: asyncio.Task[None] | None = None
        self._closing = False
        self._ids = itertools.count(1)

    # -- life -----------------------------------------------------------------------------------
    async def __aenter__(self) -> AsyncStream:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def open(self) -> None:
        """Connect and read the hello (raises :class:`ServiceUnavailable` if the first attempt fails);
        sends the subscription without waiting for its reply."""
        await self._connect()
        self._reader = asyncio.create_task(self._read_forever())

    async def close(self) -> None:
        self._closing = True
        if self._ws is not None:
            await self._ws.close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader
        self._fail_pending(StreamClosed(1000, "closed by the client"))
        while not self._queue.empty():  # wake a consumer waiting in frames(): iteration ends
            self._queue.get_nowait()
        self._queue.put_nowait(_END)

    async def _connect(self) -> None:
        try:
            # no size limit: a busy spikes frame of a large skin is megabytes (docs/stream-protocol.md, Frame sizes)
            ws = await connect(self.url, compression=None, open_timeout=self.open_timeout_s, max_size=None)
        except (OSError, asyncio.TimeoutError, websockets.InvalidHandshake) as exc:
            raise ServiceUnavailable(f"cannot open {self.url}: {exc!r}") from exc
        try:
            hello = json.loads(await asyncio.wait_for(ws.recv(), self.open_timeout_s))
        except (asyncio.TimeoutError, websockets.ConnectionClosed, json.JSONDecodeError, TypeError) as exc:
            await ws.close()
            raise ServiceUnavailable(f"{self.url}: no hello from the server ({exc!r})") from exc
        spoken = set(hello.get("versions", [])) & set(P.SUPPORTED_VERSIONS) if isinstance(hello, dict) else set()
        if not isinstance(hello, dict) or hello.get("type") != "hello" or not spoken:
            await ws.close()
            raise StreamClosed(None, f"{self.url} speaks no {P.PROTOCOL} version of {list(P.SUPPORTED_VERSIONS)}: {hello!r:.200}")
        # the newest version both speak (a version-1 server predates populations: it serves taxels)
        self.version = max(spoken)
        self.subscription = replace(self.subscription, version=self.version)
        new_session = hello.get("session") != self.hello.get("session")
        self._ws, self.hello = ws, hello
        self.stats.on_connect(new_session)
        self._on_hello(hello)
        self.backoff.reset()
        self._pending.append(("subscribe", asyncio.get_running_loop().create_future()))
        await ws.send(json.dumps(self.subscription.to_json()))

    # -- requests -------------------------------------------------------------------------------
    async def subscribe(self, subscription: P.Subscription | None = None, **changes: Any) -> dict[str, Any]:
        """Replace the subscription (a new one, or the current one with ``changes``, e.g.
        ``taxels=[0, 1]``, ``classes=["SA1"]``, ``streams=["spikes", "decoded"]``) and wait for the
        server's ``subscribed`` reply. Raises :class:`StreamError` if the server refuses it."""
        new = replace(subscription or self.subscription, **changes)
        new = replace(new, version=self.version)  # the version agreed at open
        reply = await self._request("subscribe", new.to_json())
        self.subscription = new  # only once accepted: a reconnect sends it again
        return reply

    async def sync_clock(self, samples: int = 5) -> float:
        """NTP-style ``time`` exchanges; keeps the one with the least round trip. Returns the
        offset (server minus client clock, us) the latency figures now use."""
        for _ in range(samples):
            t0 = wall_us()
            reply = await self._request("time", {"type": "time", "id": next(self._ids), "t0_us": t0})
            self.latency.add_time_sample(t0, reply["t1_us"], reply["t2_us"], reply["_t3_us"])
        self.clock.set_offset(self.latency.offset_us, self.latency.uncertainty_us)
        return self.latency.offset_us

    # -- time -----------------------------------------------------------------------------------
    def to_local(self, t_us: Any) -> Any:
        """This client's wall time (us, float; scalar or array) at which the sample stamped ``t_us``
        (wire clock) was acquired, by the server's clock model and the ``time`` offset
        (:meth:`sync_clock`; 0 until then). For a spike, subtract its class's ``delay_us`` from the
        stamp first to place its causing sample; the stamp itself places the spike. LookupError
        before the first clock point."""
        return self.clock.to_local_us(t_us)

    def spike_latency_us(self, frame: P.SpikesFrame) -> np.ndarray:
        """Per spike of a received frame: its receipt minus the acquisition of its causing sample,
        on this client's clock (us). Empty before the first clock point."""
        if frame.header.recv_us is None:
            raise ValueError("the frame carries no receive time (it was not received by this stream)")
        return spike_latency_us(frame, frame.header.recv_us, self.clock, self.delay_us)

    @property
    def delay_us(self) -> dict[str, int]:
        """Per class: the delay (us) its stamps carry past their causing sample (``hello.delay_us``)."""
        return {str(c): int(v) for c, v in self.hello.get("delay_us", {}).items()}

    def _on_hello(self, hello: dict[str, Any]) -> None:
        self.latency.set_algorithmic(hello.get("latency_us", {}))
        if hello.get("session") != getattr(self, "_clock_session", None):
            self.clock = ClockMap()  # a new server session: its sensor clock starts afresh
            self.clock.set_offset(self.latency.offset_us, self.latency.uncertainty_us)
            self._clock_session = hello.get("session")
        if hello.get("clock") is not None:
            self.clock.update(hello["clock"])

    async def _request(self, kind: str, message: dict[str, Any]) -> dict[str, Any]:
        if self._ws is None or self._closing:
            raise StreamClosed(None, "the stream is not open")
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending.append((kind, fut))
        await self._ws.send(json.dumps(message))
        return await asyncio.wait_for(fut, self.request_timeout_s)

    def _fail_pending(self, exc: Exception) -> None:
        while self._pending:
            _, fut = self._pending.popleft()
            if not fut.done():
                fut.set_exception(exc)
                fut.exception()  # retrieved here: nobody may be waiting for it any more

    # -- reading --------------------------------------------------------------------------------
    async def _read_forever(self) -> None:
        try:
            while True:
                assert self._ws is not None
                try:
                    async for msg in self._ws:
                        await self._dispatch(msg)
                    code, reason = self._close_info()
                except websockets.ConnectionClosed:
                    code, reason = self._close_info()
                if self._closing:
                    return
                self._fail_pending(StreamClosed(code, reason or "connection lost"))
                if code in FATAL_CLOSE_CODES or not self.reconnect:
                    await self._queue.put(StreamClosed(code, reason or "connection lost"))
                    return
                await self._reconnect(code, reason)
        except StreamClosed as exc:
            await self._queue.put(exc)
        except Exception as exc:  # a malformed frame or message: the consumer sees it, never a silent hang
            self._fail_pending(exc)
            await self._queue.put(exc)
            if self._ws is not None:
                await self._ws.close()

    def _close_info(self) -> tuple[int | None, str]:
        ws = self._ws
        if ws is None or ws.close_code is None or ws.close_code == 1006:  # 1006: no close frame came
            return None, "connection lost"
        return ws.close_code, ws.close_reason or ""

    async def _reconnect(self, code: int | None, reason: str) -> None:
        while not self._closing:
            if self.backoff.exhausted:
                raise StreamClosed(code, f"{reason or 'connection lost'}; gave up after {self.backoff.attempt} reconnect attempts")
            await asyncio.sleep(self.backoff.next_delay())
            try:
                await self._connect()
                return
            except ServiceUnavailable:
                continue

    async def _dispatch(self, msg: str | bytes) -> None:
        recv = wall_us()
        if isinstance(msg, bytes):
            await self._on_frame(P.decode_frame(msg), recv)
            return
        m = json.loads(msg)
        kind = m.get("type")
        if kind in ("spikes", "channels", "decoded"):
            await self._on_frame(P.frame_from_json(m), recv)
        elif kind == "hello":
            self.hello = m
            self._on_hello(m)
        elif kind == "clock":
            self.clock.update(m)
        elif kind == "ended":
            self.ended = m
        elif kind in ("subscribed", "time", "error"):
            if kind == "subscribed":
                self.subscribed = m
                self.latency.set_algorithmic(m.get("latency_us", self.latency.algorithmic_us))
            if kind == "time":
                m["_t3_us"] = recv
            self._resolve(m)

    def _resolve(self, m: dict[str, Any]) -> None:
        if not self._pending:
            if m["type"] == "error":
                self.errors.append(m)
            return
        _, fut = self._pending.popleft()
        if fut.done():
            return
        if m["type"] == "error":
            fut.set_exception(StreamError(m.get("code", "?"), m.get("message", "")))
            fut.exception()
        else:
            fut.set_result(m)

    async def _on_frame(self, frame: P.Frame, recv_us: int) -> None:
        frame.header.recv_us = recv_us
        n_ev = frame.t_us.size if isinstance(frame, P.SpikesFrame) else 0
        n_steps = frame.t_us.size if isinstance(frame, P.DecodedFrame) else 0
        self.stats.on_frame(frame.header, n_ev, n_steps)
        self.latency.on_frame(frame.header, recv_us)
        if isinstance(frame, P.SpikesFrame):
            self.latency.on_spikes(frame, recv_us, self.clock, self.delay_us)
        await self._queue.put(frame)

    # -- iteration ------------------------------------------------------------------------------
    async def frames(self) -> AsyncIterator[P.Frame]:
        """Every frame in arrival order (spikes, channels, decoded), across reconnects. Ends with
        :class:`StreamClosed` when the stream ends for good; stops after :meth:`close`."""
        while True:
            item = await self._queue.get()
            if item is _END:
                return
            if isinstance(item, Exception):
                raise item
            yield item

    async def spikes(self) -> AsyncIterator[P.SpikesFrame]:
        """Spike frames only: ``t_us`` (uint64, sensor clock), ``taxel`` (uint16), ``cls`` (uint8,
        index into ``CLASSES``) as numpy arrays, and ``final_us`` per class."""
        async for f in self.frames():
            if isinstance(f, P.SpikesFrame):
                yield f

    async def decoded(self) -> AsyncIterator[DecodedOutput]:
        """Decoded-output frames with their decoder's name and output names (from the hello)."""
        async for f in self.frames():
            if isinstance(f, P.DecodedFrame):
                yield self.name_decoded(f)

    def name_decoded(self, f: P.DecodedFrame) -> DecodedOutput:
        """A decoded frame with its decoder's name and output names (``#i`` for an index the hello lacks
        or describes in a shape it should not: a hello is input like any other)."""
        streams = self.hello.get("streams")
        decoded = streams.get("decoded") if isinstance(streams, dict) else None
        decoders = decoded.get("decoders") if isinstance(decoded, dict) else None
        d = decoders[f.decoder] if isinstance(decoders, list) and f.decoder < len(decoders) else None
        d = d if isinstance(d, dict) else {}
        outputs = d.get("outputs")
        return DecodedOutput(str(d.get("name", f"#{f.decoder}")), [str(o) for o in outputs] if isinstance(outputs, list) else [],
                             f.taxels, f.t_us, f.values, f.header)
