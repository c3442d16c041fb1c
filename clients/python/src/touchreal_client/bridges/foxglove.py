"""A Foxglove live view of a ``/v1/stream``: ``touchreal bridge foxglove --from URL --port 8767``.

Serves the Foxglove WebSocket protocol with foxglove-sdk (extra ``foxglove``) on its own port, one
JSON channel per topic of :mod:`touchreal_client.topics` (JSON Schema advertised): spikes per class,
the channels, the force and each decoder's outputs, one message per spike, channel sample or
decoding step, in the shapes of the ``touchreal record`` MCAP topics, so one Foxglove layout serves
the live view and a recording.

``t_us`` is the wire stamp (sensor clock, integer us). A message's log time is this machine's wall
time (ns) of that stamp by the stream's clock model (``clock`` messages plus the ``time`` offset),
not the time it arrived. Demand-driven: the bridge subscribes upstream to exactly what Foxglove
clients are subscribed to (the SDK's subscribe/unsubscribe callbacks), and to nothing while no
client subscribes, so an idle bridge costs the service nothing. A gateway speaks the same protocol,
so ``--from`` may be a gateway. From a service running an afferent population only the spike
topics are served, their ``taxel`` an afferent id.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from .. import protocol as P
from ..stream import AsyncStream
from ..topics import (CHANNELS_SCHEMA, CHANNELS_TOPIC, DECODED_SCHEMA, FORCE_SCHEMA, FORCE_TOPIC,
                      SPIKE_SCHEMA, decoded_topic, json_lists, spikes_topic, wanted_subscription)
from . import FIRST_SYNC_SAMPLES, follow_demand, forward, publish_by_kind

log = logging.getLogger("touchreal_client.bridges.foxglove")

DEFAULT_PORT = 8767  #: serve uses 8765, the gateway 8766


class DemandListener:
    """foxglove-sdk server listener: which (client, channel) pairs are subscribed. Called on the
    SDK's threads; ``on_change`` is called after every change (it must be thread-safe)."""

    def __init__(self, on_change: Callable[[], None]):
        self._on_change = on_change
        self._lock = threading.Lock()
        self._subs: set[tuple[int, str]] = set()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self._subs.add((client.id, channel.topic))
        self._on_change()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self._subs.discard((client.id, channel.topic))
        self._on_change()

    def topics(self) -> set[str]:
        with self._lock:
            return {topic for _, topic in self._subs}


class FoxgloveBridge:
    """Foxglove WebSocket server on ``host:port`` fed from the stream at ``url`` (``ws://...`` or
    ``http://HOST:PORT``). ``port=0`` binds a free port (:attr:`port` once :attr:`ready` is set).
    ``decimation``: channels at 5 kHz / decimation."""

    def __init__(self, url: str, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, decimation: int = 25,
                 name: str = "TouchReal"):
        self.url, self.host, self.port, self.decimation, self.name = url, host, port, decimation, name
        self.ready = asyncio.Event()  #: set once the Foxglove server listens (then :attr:`port` is bound)
        self.stream: AsyncStream | None = None
        self._context: Any = None  #: the foxglove.Context the channels and the server share (set in run)
        self._channels: dict[str, Any] = {}
        self._changed = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._listener = DemandListener(self._demand_changed)

    # -- life -----------------------------------------------------------------------------------
    async def run(self) -> None:
        """Serve until cancelled or until the upstream stream ends for good (then raises
        :class:`~touchreal_client.errors.StreamClosed`)."""
        import foxglove

        self._loop = asyncio.get_running_loop()
        async with AsyncStream(self.url, wanted_subscription((), self.decimation)) as stream:
            self.stream = stream
            await stream.sync_clock(FIRST_SYNC_SAMPLES)
            self._context = foxglove.Context()
            self._advertise(stream.hello)
            try:
                server = foxglove.start_server(name=self.name, host=self.host, port=self.port,
                                               server_listener=self._listener, context=self._context,
                                               session_id=str(stream.hello.get("session", "")) or None)
            except RuntimeError as exc:  # the SDK reports bind errors as RuntimeError
                raise OSError(f"cannot serve Foxglove on {self.host}:{self.port}: {exc}") from exc
            self.port = server.port
            try:
                await forward(stream, self._publish, self.ready, self._follow_upstream(server))
            finally:
                server.stop()

    # -- channels -------------------------------------------------------------------------------
    def _channel(self, topic: str, schema: dict[str, Any], metadata: dict[str, str]) -> Any:
        import foxglove

        ch = self._channels.get(topic)
        if ch is None:
            data = json.dumps(schema).encode()
            ch = foxglove.Channel(topic, message_encoding="json", context=self._context, metadata=metadata,
                                  schema=foxglove.Schema(name=schema["title"], encoding="jsonschema", data=data))
            self._channels[topic] = ch
        return ch

    def _advertise(self, hello: dict[str, Any]) -> None:
        """Channels for what the service offers (from a hello; those already advertised stay). A
        population's service offers the spikes of its afferents only: ``taxel`` is then an afferent
        id (channel metadata ``addresses``; their positions and models are in the hello)."""
        population = P.hello_afferents(hello) is not None
        addresses = {"addresses": "afferents" if population else "taxels"}
        for c in (c for c in hello.get("classes", P.CLASSES) if c in P.CLASSES):
            self._channel(spikes_topic(c), SPIKE_SCHEMA, {"class": c, **addresses})
        if population:
            return
        rate = {"rate_hz": str(5000 / self.decimation)}
        self._channel(CHANNELS_TOPIC, CHANNELS_SCHEMA, rate)
        self._channel(FORCE_TOPIC, FORCE_SCHEMA, rate)
        for d in hello.get("streams", {}).get("decoded", {}).get("decoders", []):
            self._decoded_channel(str(d.get("name")), [str(o) for o in d.get("outputs", [])])

    def _decoded_channel(self, name: str, outputs: list[str]) -> Any:
        return self._channel(decoded_topic(name), DECODED_SCHEMA, {"decoder": name, "outputs": ", ".join(outputs)})

    # -- demand ---------------------------------------------------------------------------------
    def _demand_changed(self) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._changed.set)

    async def _follow_upstream(self, server: Any) -> None:
        """Keep the upstream subscription equal to what the Foxglove clients subscribe to (retried
        while the stream reconnects), and give Foxglove clients a new session when the service's
        changes (a restarted service: its sensor clock starts afresh, so they drop what they hold).
        A new hello's decoders get their channels."""
        stream = self.stream
        assert stream is not None
        session = stream.hello.get("session")

        def new_hello(hello: dict[str, Any]) -> None:
            nonlocal session
            if hello.get("session") != session:
                session = hello.get("session")
                server.clear_session(str(session))
            self._advertise(hello)

        await follow_demand(stream, self._changed, self._listener.topics, self.decimation, new_hello)

    # -- publishing -----------------------------------------------------------------------------
    def _log_times_ns(self, t_us: np.ndarray) -> list[int | None]:
        """This machine's wall time (ns) of each wire stamp; None (the SDK stamps it now) before
        the stream's first clock point."""
        assert self.stream is not None
        try:
            local = np.atleast_1d(self.stream.to_local(np.asarray(t_us, np.float64)))
        except LookupError:
            return [None] * len(t_us)
        return np.rint(local * 1000.0).astype(np.int64).tolist()

    def _publish(self, frame: P.Frame) -> None:
        publish_by_kind(frame, self._publish_spikes, self._publish_channels, self._publish_decoded)

    def _publish_spikes(self, f: P.SpikesFrame) -> None:
        times = self._log_times_ns(f.t_us)
        tag = _frame_tag(f.header)
        for i, name in enumerate(P.CLASSES):
            ch = self._channels.get(spikes_topic(name))
            if ch is None or not ch.has_sinks():
                continue
            for k in np.flatnonzero(f.cls == i).tolist():
                ch.log({"t_us": int(f.t_us[k]), "taxel": int(f.taxel[k]), "class": name, **tag}, log_time=times[k])

    def _publish_channels(self, f: P.ChannelsFrame) -> None:
        chans, force = self._channels.get(CHANNELS_TOPIC), self._channels.get(FORCE_TOPIC)
        t_us = f.t0_us + f.period_us * np.arange(f.data.shape[0], dtype=np.uint64)
        times = self._log_times_ns(t_us)
        taxels, tag = f.taxels.tolist(), _frame_tag(f.header)
        for k, t in enumerate(t_us.tolist()):
            if chans is not None and chans.has_sinks():
                msg: dict[str, Any] = {"t_us": t, "taxels": taxels}
                msg.update({n: json_lists(f.data[k, :, j]) for j, n in enumerate(P.CHANNELS)})
                chans.log({**msg, **tag}, log_time=times[k])
            if force is not None and force.has_sinks():
                force.log({"t_us": t, "taxels": taxels, "force_N": json_lists(f.data[k, :, 0]), **tag}, log_time=times[k])

    def _publish_decoded(self, f: P.DecodedFrame) -> None:
        assert self.stream is not None
        out = self.stream.name_decoded(f)
        ch = self._decoded_channel(out.name, out.outputs)
        if not ch.has_sinks():
            return
        times = self._log_times_ns(out.t_us)
        taxels, tag = out.taxels.tolist(), _frame_tag(f.header)
        names = out.outputs or [f"#{j}" for j in range(out.values.shape[2])]
        for s, t in enumerate(out.t_us.tolist()):
            values = json_lists(out.values[s])  # [taxel][output]
            ch.log({"t_us": t, "taxels": taxels, "outputs": names, "values": values, **tag}, log_time=times[s])


def _frame_tag(h: P.Header) -> dict[str, int]:
    return {"update": h.update, "params_rev": h.params_rev}
