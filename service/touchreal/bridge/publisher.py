"""``touchreal serve --publish nats://HOST:PORT --sensor-id ID``: the service's frames onto NATS.

Demand comes from ``demand.<gateway_id>``: the subject names the sender (:mod:`.demand`).

The publisher is more subscribers of the service's :class:`~touchreal.server.hub.Hub` (so the
acquisition thread never sees it), one per subject (a *lane*): spikes for the demand the gateways
forward (:mod:`.demand`; every class and taxel with ``publish_all``), full-rate channels for the
channel taxels they forward, and one lane per decoder they forward (``decoded.<name>``, created on
first demand), each with its own ``seq``. A task on the event loop drains their bounded queues into ``nc.publish`` (nats-py buffers writes and flushes them itself; while the broker
is unreachable it keeps up to ``pending_bytes`` and reconnects on its own; a publish it refuses is
counted and dropped, the next frame's ``seq`` jump shows the loss downstream). If the loop ever lets
the queue overflow, the hub drops frames for the publisher alone, again visible as a ``seq`` jump.

It also answers ``hello`` requests with the service's current hello (once its source is open) and announces a new one when
the parameter revision, taxels, classes or decoders change, and publishes the service's ``clock``
messages (its clock model) as the service tells them to its own clients.

With ``retain_s`` it keeps the last seconds of everything it publishes in a small in-memory
JetStream stream (:func:`.subjects.stream_name`), so a late joiner reading NATS can catch up; the
broker stores the core publishes itself, the publishing path does not change. A broker without
JetStream is reported in ``status()`` and publishing goes on without retention.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time

import nats
from nats.errors import Error as NatsError
from nats.js.api import DiscardPolicy, StorageType, StreamConfig
from nats.js.errors import BadRequestError
from prometheus_client import Counter, Gauge
from touchreal_client import protocol as P
from touchreal_client.events import wait_set

from ..decoding.model import DecoderModelError
from ..redaction import redact
from ..server.hub import Subscriber
from ..server.service import Service
from . import connection, parts, subjects
from .auth import NatsAuth, servers
from .demand import MAX_GATEWAYS, REJECT_REASONS, ForwardedDemand, Rejected, parse_announcement

log = logging.getLogger("touchreal.bridge")
EXPIRE_EVERY_S = 0.25  #: how often forwarded demand is checked for expiry (s)


class NatsPublisher:
    """Publishes one service's frames under ``touchreal.<sensor_id>.`` (a Companion of the app). Its
    hub subscribers (lanes) show in the service's ``/v1/status`` clients like any other."""

    def __init__(self, service: Service, url: str, sensor_id: str, publish_all: bool = False,
                 pending_bytes: int = 8 << 20, retain_s: float = 0.0, retain_bytes: int = 64 << 20,
                 auth: NatsAuth | None = None, max_gateways: int = MAX_GATEWAYS):
        """``url``: the broker's URL(s), comma-separated; ``pending_bytes``: what nats-py buffers while
        disconnected; ``retain_s`` (s) and ``retain_bytes``: the JetStream retention (0 s: none)."""
        self.service, self.sensor_id = service, subjects.check_sensor_id(sensor_id)
        self.servers = servers(url)
        self.url = redact(",".join(self.servers))  #: the broker(s), as shown (no secrets)
        self.auth = auth or NatsAuth()
        self.auth.check(self.servers)
        self.publish_all, self.pending_bytes = publish_all, pending_bytes
        if retain_s < 0 or retain_bytes <= 0:
            raise ValueError("retain_s must be >= 0 and retain_bytes > 0")
        self.retain_s, self.retain_bytes = retain_s, retain_bytes
        self.retain_error: str | None = None
        self.demand = ForwardedDemand(max_gateways)
        self.nc: nats.NATS | None = None
        self.spikes_subject, self.channels_subject = subjects.frames(sensor_id), subjects.channels(sensor_id)
        self.lanes: dict[str, Subscriber] = {}  #: subject -> the hub subscriber feeding it
        self.published = 0
        self._announced: tuple | None = None
        self._task: asyncio.Task | None = None
        r = service.metrics.registry
        self.m_published = Counter("touchreal_nats_published_frames", "frames published to NATS", registry=r)
        self.m_failed = Counter("touchreal_nats_publish_failures", "frames NATS refused (disconnected and its "
                                "buffer full, or closed) or too large to publish in parts", registry=r)
        self.m_parted = Counter("touchreal_nats_parted_frames", "frames over the broker's max_payload, "
                                "published in parts", registry=r)
        self.m_connected = Gauge("touchreal_nats_connected", "1 while the publisher is connected to NATS", registry=r)
        self.m_gateways = Gauge("touchreal_nats_gateways", "gateways whose forwarded demand is live", registry=r)
        self.m_rejected = Counter("touchreal_nats_demand_rejected", "demand announcements dropped (oversized, "
                                  "malformed, out_of_range taxels, identity_mismatch: the body names another "
                                  "gateway than the subject, too_many_gateways)", ["reason"], registry=r)
        for reason in REJECT_REASONS:
            self.m_rejected.labels(reason)

    async def start(self) -> None:
        self._wakeup = asyncio.Event()
        for subject in (self.spikes_subject, self.channels_subject):
            self._lane(subject)
        self._apply_demand()
        self.service.status_sections["nats"] = self.status
        self._task = asyncio.create_task(self._run(), name="touchreal-nats-publisher")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
        self.service.status_sections.pop("nats", None)
        for sub in self.lanes.values():
            self.service.hub.remove(sub)
        await connection.close(self.nc)

    def status(self) -> dict:
        """The ``nats`` section of the service's ``/v1/status``."""
        return {"url": self.url, "sensor_id": self.sensor_id, "auth": self.auth.describe(self.servers),
                "connected": bool(self.nc and self.nc.is_connected),
                "published": self.published, "failures": int(self.m_failed._value.get()),
                "parted": int(self.m_parted._value.get()),
                "max_payload": self.nc.max_payload if self.nc and self.nc.is_connected else None,
                "gateways": self.demand.gateways,
                "demand_rejected": {r: int(self.m_rejected.labels(r)._value.get()) for r in REJECT_REASONS},
                "retain": {"seconds": self.retain_s, "max_bytes": self.retain_bytes,
                           "stream": subjects.stream_name(self.sensor_id), "error": self.retain_error}
                if self.retain_s else None,
                "lanes": {subject: {"seq": sub.seq, "dropped": sub.dropped,
                                    "subscription": sub.subscription.to_json() if sub.subscription else None}
                          for subject, sub in self.lanes.items()}}

    # -- the loop -------------------------------------------------------------------------------
    async def _run(self) -> None:
        self.nc = nats.NATS()
        await connection.connect(self.nc, self.servers, f"touchreal-publisher-{self.sensor_id}", self.auth,
                                 self._on_error, self._on_conn, pending_size=self.pending_bytes)
        self.m_connected.set(1)
        await self.nc.subscribe(subjects.hello_request(self.sensor_id), cb=self._on_hello_request)
        await self.nc.subscribe(subjects.demand_any(self.sensor_id), cb=self._on_demand)
        await self.nc.subscribe(subjects.decoders_request(self.sensor_id), cb=self._on_decoders_request)
        await self.nc.subscribe(subjects.model_request(self.sensor_id), cb=self._on_model_request)
        self.service.clock_listeners.append(self._on_clock)
        if self.retain_s:
            await self._retain()
        log.info("publishing %s to %s", subjects.frames(self.sensor_id), self.url)
        headers = {subjects.SESSION_HEADER: self.service.session}
        while True:
            await wait_set(self._wakeup, EXPIRE_EVERY_S)
            self._wakeup.clear()
            self._expire()
            for subject, sub in list(self.lanes.items()):  # a demand callback may add a lane meanwhile
                if sub.kick is not None:  # the loop starved it for slow_timeout_s: keep publishing (losses are counted)
                    log.warning("publisher fell behind on %s: %s", subject, sub.kick[1])
                    sub.kick, sub.full_since = None, None
                    sub.kicked.clear()
                while sub.queue:
                    item = sub.queue.popleft()
                    data, _ = sub.render(item)
                    await self._announce_if_changed(P.decode_header(data).params_rev)
                    await self._publish_frame(subject, data, headers)

    async def _publish_frame(self, subject: str, data: bytes, headers: dict[str, str]) -> None:
        """Publish one frame, in parts when it exceeds the broker's ``max_payload`` (:mod:`.parts`);
        a frame NATS refuses (disconnected, or too large for :data:`.parts.MAX_PARTS` parts) is counted
        as a failure, and its ``seq`` gap tells the gateways' clients."""
        try:
            pieces = parts.split(data, self.nc.max_payload)
        except ValueError as exc:
            self.m_failed.inc()
            log.warning("frame on %s not published: %s", subject, exc)
            return
        try:
            for part, piece in pieces:
                await self.nc.publish(subject, piece, headers=headers if part is None else
                                      {**headers, parts.PART_HEADER: part})
            self.published += 1
            self.m_published.inc()
            if len(pieces) > 1:
                self.m_parted.inc()
        except (NatsError, OSError) as exc:
            self.m_failed.inc()
            log.debug("publish failed: %s", redact(repr(exc)))

    async def _retain(self) -> None:
        """Create (or reconfigure) the in-memory stream over this sensor's frame subjects."""
        cfg = StreamConfig(name=subjects.stream_name(self.sensor_id), subjects=subjects.retained(self.sensor_id),
                           storage=StorageType.MEMORY, max_age=self.retain_s, max_bytes=self.retain_bytes,
                           discard=DiscardPolicy.OLD, num_replicas=1)
        js = self.nc.jetstream()
        try:
            try:
                await js.add_stream(cfg)
            except BadRequestError:  # it exists with another configuration (a previous run's)
                await js.update_stream(cfg)
            self.retain_error = None
            log.info("retaining the last %g s of %s in JetStream stream %s", self.retain_s, self.sensor_id, cfg.name)
        except (NatsError, asyncio.TimeoutError) as exc:
            self.retain_error = f"no JetStream stream ({redact(repr(exc))}); is nats-server running with -js?"
            log.warning("publishing without retention: %s", self.retain_error)

    # -- demand and hello -----------------------------------------------------------------------
    async def _on_demand(self, msg) -> None:
        """An announcement on ``demand.<gateway_id>``: counted against that gateway, whatever its body says."""
        sender = subjects.last_token(msg.subject)
        try:
            announced, ttl = parse_announcement(sender, msg.data, self.service.view.n_taxels)
            self.demand.announce(sender, announced, ttl, time.monotonic())
        except Rejected as exc:
            self.m_rejected.labels(exc.reason).inc()
            log.debug("%s: %s", msg.subject, exc)  # counted; a flood must not flood the log
            return
        self._apply_demand()

    def _expire(self) -> None:
        before = self.demand.gateways
        self.demand.expire(time.monotonic())
        if self.demand.gateways != before:
            self._apply_demand()

    def _lane(self, subject: str) -> Subscriber:
        sub = self.lanes.get(subject)
        if sub is None:
            sub = self.lanes[subject] = self.service.hub.add()
            sub.wakeup = self._wakeup  # one drain task serves every lane
            sub.takes_control = False  # hello and clock cross the broker on subjects of their own
        return sub

    def _apply_demand(self) -> None:
        """Subscribe each lane to what is wanted downstream (None: no frames, nothing computed for us).
        A decoder lane is created when its decoder is first wanted and kept (idle) afterwards, so its
        ``seq`` runs on; announced decoders the service does not have are ignored."""
        self.m_gateways.set(len(self.demand.gateways))
        wants: dict[str, P.Subscription | None] = {subject: None for subject in self.lanes}
        wants[self.spikes_subject] = P.Subscription() if self.publish_all else self.demand.spikes()
        wants[self.channels_subject] = self.demand.channels()
        for name, want in self.demand.decoded().items():
            if name in self.service.hub.decoder_classes:
                wants[subjects.decoded(self.sensor_id, name)] = want
        for subject, want in wants.items():
            sub = self._lane(subject) if want is not None else self.lanes[subject]
            if (sub.subscription and sub.subscription.to_json()) != (want and want.to_json()):
                self.service.hub.subscribe(sub, want)

    def _on_clock(self, text: str) -> None:
        """Called on the event loop with each clock message the service tells its clients."""
        if self.nc is not None and self.nc.is_connected:
            asyncio.ensure_future(self._publish_clock(text.encode()))

    async def _publish_clock(self, data: bytes) -> None:
        try:
            await self.nc.publish(subjects.clock(self.sensor_id), data)
        except (NatsError, OSError) as exc:  # the next one (within a second) restates it
            log.debug("clock publish failed: %s", redact(repr(exc)))

    async def _on_hello_request(self, msg) -> None:
        # our own announcements arrive here too: they have no reply subject. Until the service's source
        # is open its hello has no taxels: a gateway that took it would keep an empty demand, so it
        # gets no answer and asks again
        if msg.reply and self.service.runtime is not None:
            await self.nc.publish(msg.reply, self._hello_bytes())

    async def _on_decoders_request(self, msg) -> None:
        if msg.reply:
            await self.nc.publish(msg.reply, json.dumps(self.service.view.decoders_view()).encode())

    async def _on_model_request(self, msg) -> None:
        """Reply with the named model's ONNX bytes, or with :data:`.subjects.ERROR_HEADER` saying why not."""
        if not msg.reply:
            return
        try:
            data = await asyncio.to_thread(self.service.models.path(msg.data.decode(errors="replace")).read_bytes)
        except (DecoderModelError, OSError) as exc:
            await self.nc.publish(msg.reply, b"", headers={subjects.ERROR_HEADER: str(exc)[:300]})
            return
        if len(data) > self.nc.max_payload:
            await self.nc.publish(msg.reply, b"", headers={subjects.ERROR_HEADER: f"model of {len(data)} bytes exceeds "
                                                           f"the broker's max_payload ({self.nc.max_payload})"})
            return
        await self.nc.publish(msg.reply, data)

    def _hello_bytes(self) -> bytes:
        return json.dumps(self.service.view.hello(), separators=(",", ":")).encode()

    async def _announce_if_changed(self, params_rev: int) -> None:
        key = (params_rev, self.service.view.n_taxels, tuple(self.service.config.classes), tuple(self.service.hub.decoder_names))
        if key != self._announced:
            if self._announced is not None:
                try:
                    await self.nc.publish(subjects.hello(self.sensor_id), self._hello_bytes())
                except (NatsError, OSError):
                    return  # try again with the next frame
            self._announced = key

    async def _on_error(self, exc: Exception) -> None:
        log.warning("nats: %s", redact(repr(exc)))

    async def _on_conn(self) -> None:
        self.m_connected.set(1 if self.nc is not None and self.nc.is_connected else 0)
