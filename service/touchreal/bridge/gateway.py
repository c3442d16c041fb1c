"""``touchreal gateway --nats URL --sensor-id ID``: /v1/stream for many clients, fed from NATS.

A gateway is stateless: it reads the publisher's hello (a NATS request), subscribes to the frames
subject and feeds every frame, as an :class:`~touchreal.server.runtime.Update`, into the same
:class:`~touchreal.server.hub.Hub` and ``/v1/stream`` WebSocket layer the service uses (so
subscriptions, per-client queues, slow-consumer closes and stamping are one code). What its clients
subscribe to is forwarded to the publisher as demand (:mod:`.demand`), on the demand subject of
its own ``gateway_id`` (a setting, stable across restarts, so a restarted gateway renews its own
place at the publisher; the broker lets its credentials announce under that id only). Its decoder routes
(``/v1/decoders``...) ask the publisher over NATS, so clients that download a model work through it.

Losses on the broker hop stay honest: a jump in the publisher's ``seq`` (frames the broker or this
gateway's bounded pending buffer dropped) advances every spikes subscriber's ``seq`` and ``dropped``
by the frames it lost (``Hub.skip``), exactly as if its own queue had dropped them; the same holds
for the channels subject and channels subscribers, and for each decoder's subject and the subscribers
to that decoder's outputs. The decoders offered are the publisher's whose names are subject tokens.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from contextlib import asynccontextmanager
from typing import Any

import nats
from fastapi import APIRouter, FastAPI, Request, Response
from fastapi.responses import JSONResponse
from nats.errors import Error as NatsError
from nats.errors import SlowConsumerError
from prometheus_client import CONTENT_TYPE_LATEST, Counter, Gauge, generate_latest
from starlette.middleware.trustedhost import TrustedHostMiddleware
from touchreal_client import protocol as P
from touchreal_client.clock import ClockPoint
from touchreal_client.events import wait_set

from .. import __version__
from ..redaction import redact
from ..server import ws
from ..server.api_docs import add_docs
from ..server.browser import SecurityHeaders, server_error
from ..server.hub import Hub, limits
from ..server.metrics import Metrics
from . import connection, parts, subjects
from .auth import NatsAuth, servers
from .demand import DEFAULT_TTL_S, Announced, announcement
from .settings import GatewaySettings
from .upstream import UpstreamTracker, update_from_frame

log = logging.getLogger("touchreal.bridge")
HELLO_RETRY_S = 0.5  #: how often a gateway asks for the hello until the publisher answers (s)
UPSTREAM_REQUEST_S = 5.0  #: how long a decoders/model request waits for the publisher (s)


class UpstreamUnavailable(RuntimeError):
    """The publisher did not answer a request (not connected, not running, or too slow)."""


class AnnouncingHub(Hub):
    """The gateway's hub: every change of its demand also wakes the demand announcer, and its
    :attr:`announced` is what it forwards: the spikes its clients want as spikes (not the classes
    their decoders read: the publisher computes those for the decoders itself), channels, decoders."""

    def __init__(self, capacity: int, slow_timeout_s: float, changed: asyncio.Event, max_age_s: float | None):
        self.changed = changed
        super().__init__(capacity, slow_timeout_s, max_age_s)

    @property
    def announced(self) -> Announced:
        d = self.demand
        return Announced(dict(d.spikes), d.channel_taxels, dict(d.decoders))

    def refresh_demand(self) -> None:
        super().refresh_demand()
        self.changed.set()


class Gateway:
    """What ``/v1/stream`` (server/ws.py) needs from a service (``hub``, ``settings``, ``metrics``,
    ``ended``, ``hello()``, ``latency_us()``), backed by NATS instead of a pipeline."""

    def __init__(self, settings: GatewaySettings, auth: NatsAuth | None = None):
        self.settings = settings
        self.auth = auth or NatsAuth()
        self.sensor_id = subjects.check_sensor_id(settings.sensor_id)
        self.id = settings.gateway_id
        self.servers = servers(settings.nats)
        self.where = redact(",".join(self.servers))  #: the broker(s), as shown (no secrets)
        self.auth.check(self.servers)
        self.demand_subject = subjects.demand(self.sensor_id, self.id)  #: the only subject it announces on
        self._demand_dirty = asyncio.Event()
        self.hub = AnnouncingHub(settings.queue_frames, settings.slow_timeout_s, self._demand_dirty,
                                 settings.max_frame_age_ms / 1000 or None)
        self.metrics = Metrics()
        self.hub.on_drop = self.metrics.count_drop
        r = self.metrics.registry
        self.m_lost = Counter("touchreal_gateway_upstream_lost_frames", "frames lost between publisher and gateway "
                              "(seq jumps on any subject: spikes, channels, decoded)", registry=r)
        self.m_slow = Counter("touchreal_gateway_nats_slow_consumer", "frames NATS dropped because this gateway's "
                              "pending buffer was full", registry=r)
        self.m_connected = Gauge("touchreal_gateway_nats_connected", "1 while connected to NATS", registry=r)
        self.upstream = UpstreamTracker()  #: the spikes subject
        self.upstream_channels = UpstreamTracker()
        self.upstream_decoded: dict[str, UpstreamTracker] = {}  #: per decoder subject
        self.upstream_hello: dict[str, Any] | None = None
        self.clock: ClockPoint | None = None  #: the publisher's clock model, as last told
        self.ended: dict[str, Any] | None = None  #: what ws.py says after hello once a stream has ended (not relayed yet)
        self.last_frame_mono: float | None = None
        self.bad_frames = 0
        self.parts = parts.Reassembler()  #: frames over the broker's max_payload arrive in parts
        self.loop: asyncio.AbstractEventLoop | None = None
        self.nc: nats.NATS | None = None
        self._tasks: list[asyncio.Task] = []

    # -- lifecycle ------------------------------------------------------------------------------
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._tasks.append(asyncio.create_task(self._run(), name="touchreal-gateway-nats"))

    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.nc is not None and self.nc.is_connected:
            try:  # tell the publisher at once that our demand is gone
                await self.nc.publish(self.demand_subject, announcement(self.id, Announced({})))
            except (NatsError, OSError):
                pass
        await connection.close(self.nc)

    async def _run(self) -> None:
        s = self.settings
        self.nc = nats.NATS()
        await connection.connect(self.nc, self.servers, f"touchreal-gateway-{self.sensor_id}-{self.id}", self.auth,
                                 self._on_error, self._on_conn)
        self.m_connected.set(1)
        await self.nc.subscribe(subjects.hello(self.sensor_id), cb=self._on_hello)
        await self.nc.subscribe(subjects.clock(self.sensor_id), cb=self._on_clock)
        for subject in (subjects.frames(self.sensor_id), subjects.channels(self.sensor_id),
                        subjects.decoded_any(self.sensor_id)):
            await self.nc.subscribe(subject, cb=self._on_frame, pending_msgs_limit=s.pending_frames,
                                    pending_bytes_limit=s.pending_frames * 65536)
        self._tasks.append(asyncio.create_task(self._announce_demand(), name="touchreal-gateway-demand"))
        await self._fetch_hello()

    async def _fetch_hello(self) -> None:
        while True:
            try:
                msg = await self.nc.request(subjects.hello_request(self.sensor_id), b"", timeout=HELLO_RETRY_S)
                self._set_hello(json.loads(msg.data))
                return
            except (NatsError, asyncio.TimeoutError, ValueError) as exc:
                log.debug("no hello from %s yet: %s", self.sensor_id, redact(repr(exc)))
                await asyncio.sleep(HELLO_RETRY_S)

    def _set_hello(self, hello: dict[str, Any]) -> None:
        if (self.upstream_hello or {}).get("session") != hello.get("session"):
            self.clock = None  # a new publisher session: its clock model starts afresh
        self.upstream_hello = hello
        if hello.get("clock") is not None:
            self._take_clock(hello["clock"])
        try:
            positions = P.hello_positions(hello)
            afferents = P.hello_afferents(hello)
        except P.ProtocolError as exc:
            log.error("the publisher's hello describes no skin (%s); kept the previous one", exc)
            return
        if afferents is not None:  # the publisher runs a population: ids are its afferents
            self.hub.configure(len(afferents.cls), hello.get("classes", list(P.CLASSES)), {}, afferents.xy_mm,
                               addresses="afferents")
        else:
            self.hub.configure(len(positions), hello.get("classes", list(P.CLASSES)),
                               {d["name"]: d["classes"] for d in self._decoders()}, positions, addresses="taxels")
        # clients connected before (to the placeholder, or to the previous session) learn the new one
        self.hub.broadcast(json.dumps(self.hello(), separators=(",", ":")))

    def _decoders(self) -> list[dict[str, Any]]:
        """The publisher's decoders this gateway offers: those that have a subject (token names)."""
        decs = (self.upstream_hello or {}).get("streams", {}).get("decoded", {}).get("decoders", [])
        return [d for d in decs if subjects.token_ok(d.get("name", ""))]

    def _take_clock(self, msg: dict[str, Any]) -> bool:
        """Keep a clock point of the publisher (ValueError if malformed); True if it is news."""
        point = ClockPoint.from_json(msg)
        old = self.clock
        if old is not None and (point.epoch, point.sensor_us) <= (old.epoch, old.sensor_us):
            return False
        self.clock = point
        return True

    async def _on_clock(self, msg) -> None:
        try:
            if self._take_clock(json.loads(msg.data)):
                self.hub.broadcast(self.clock_message())
        except ValueError as exc:
            log.warning("bad clock on %s: %s", msg.subject, exc)

    def clock_message(self) -> str | None:
        """The publisher's current ``clock`` message (None before it told one)."""
        return None if self.clock is None else json.dumps(self.clock.to_json(), separators=(",", ":"))

    async def _on_hello(self, msg) -> None:
        if not msg.data:
            return
        try:
            self._set_hello(json.loads(msg.data))
        except ValueError as exc:
            log.warning("bad hello on %s: %s", msg.subject, exc)

    # -- frames ---------------------------------------------------------------------------------
    async def _on_frame(self, msg) -> None:
        try:
            data = self.parts.push(msg.subject, (msg.headers or {}).get(parts.PART_HEADER), msg.data)
            if data is None:  # a part of a frame still being put together, or of one given up
                return
            frame = P.decode_frame(data)
        except (P.ProtocolError, ValueError) as exc:
            self.bad_frames += 1
            log.warning("bad frame on %s: %s", msg.subject, exc)
            return
        decoder = None
        if isinstance(frame, P.DecodedFrame):
            decoder = subjects.last_token(msg.subject)
            tracker = self.upstream_decoded.setdefault(decoder, UpstreamTracker())
            stream = "decoded"
        elif isinstance(frame, P.SpikesFrame):
            tracker, stream = self.upstream, "spikes"
        else:
            tracker, stream = self.upstream_channels, "channels"
        seen = tracker.observe((msg.headers or {}).get(subjects.SESSION_HEADER), frame.header.seq)
        if seen.new_session and self.upstream_hello is not None and \
                self.upstream_hello.get("session") != tracker.session:
            self._tasks.append(asyncio.create_task(self._fetch_hello()))  # the service restarted
        if decoder is not None and decoder not in self.hub.decoder_classes:
            self.bad_frames += 1  # not in the hello we have (a newer one is on its way): no client can have it
            log.warning("decoded frame of %r, which the publisher's hello does not list", decoder)
            return
        if seen.lost:
            self.m_lost.inc(seen.lost)
            self.hub.skip(seen.lost, stream, decoder)
        upd = update_from_frame(frame, self.hub.n_taxels, decoder)
        self.last_frame_mono = time.monotonic()
        self.metrics.updates.inc()
        self.hub.publish(upd)

    # -- demand ---------------------------------------------------------------------------------
    async def _announce_demand(self) -> None:
        while True:
            await wait_set(self._demand_dirty, self.settings.demand_interval_s)
            self._demand_dirty.clear()
            ttl = max(DEFAULT_TTL_S, 3 * self.settings.demand_interval_s)
            try:
                await self.nc.publish(self.demand_subject, announcement(self.id, self.hub.announced, ttl))
            except (NatsError, OSError) as exc:
                log.debug("demand announcement failed: %s", redact(repr(exc)))

    async def _on_error(self, exc: Exception) -> None:
        if isinstance(exc, SlowConsumerError):
            self.m_slow.inc()  # the loss itself shows as the next frame's seq jump
        else:
            log.warning("nats: %s", redact(repr(exc)))

    async def _on_conn(self) -> None:
        self.m_connected.set(1 if self.nc is not None and self.nc.is_connected else 0)

    # -- what ws.py and the routes read -----------------------------------------------------------
    def hello(self) -> dict[str, Any]:
        """The publisher's hello, as this gateway serves it: the decoders it offers (:meth:`_decoders`),
        its own queue limits, the publisher's latest clock model. Before the publisher answered: no taxels,
        ``session`` null."""
        up = self.upstream_hello or {"session": None, "taxels": [], "classes": [], "latency_us": {}, "window_us": {},
                                     "update_us": 0, "params": None, "units": {}}
        s = self.settings
        return {**up, "type": "hello", "protocol": P.PROTOCOL, "version": P.VERSION,
                "versions": list(P.SUPPORTED_VERSIONS), "server": f"touchreal-gateway {__version__} (NATS {self.sensor_id})",
                "clock": None if self.clock is None else {k: v for k, v in self.clock.to_json().items() if k != "type"},
                "streams": {**up.get("streams", {"spikes": {"event_bytes": P.EVENT_DTYPE.itemsize}}),
                            "decoded": {"decoders": self._decoders()}},
                "encodings": list(P.ENCODINGS), "default_encoding": "binary",
                "limits": limits(s)}

    def latency_us(self) -> dict[str, int]:
        return dict((self.upstream_hello or {}).get("latency_us", {}))

    async def _ask(self, subject: str, payload: bytes = b""):
        if self.nc is None or not self.nc.is_connected:
            raise UpstreamUnavailable(f"not connected to NATS at {self.where}")
        try:
            return await self.nc.request(subject, payload, timeout=UPSTREAM_REQUEST_S)
        except (NatsError, asyncio.TimeoutError) as exc:
            raise UpstreamUnavailable(f"the publisher of sensor {self.sensor_id!r} did not answer "
                                      f"({redact(repr(exc))})") from exc

    async def decoders(self) -> list[dict[str, Any]]:
        """The publishing service's ``GET /v1/decoders``, asked over NATS."""
        return json.loads((await self._ask(subjects.decoders_request(self.sensor_id))).data)

    async def model(self, name: str) -> bytes:
        """The publishing service's decoder model ``name`` (ONNX bytes); LookupError if it has none."""
        msg = await self._ask(subjects.model_request(self.sensor_id), name.encode())
        error = (msg.headers or {}).get(subjects.ERROR_HEADER)
        if error:
            raise LookupError(error)
        return msg.data

    def ready(self) -> tuple[bool, str]:
        if self.nc is None or not self.nc.is_connected:
            return False, f"not connected to NATS at {self.where}"
        if self.upstream_hello is None:
            return False, f"no hello from sensor {self.sensor_id!r} yet (is its publisher running?)"
        return True, "ok"

    def status(self) -> dict[str, Any]:
        u = self.upstream
        return {"gateway": self.id, "sensor_id": self.sensor_id, "nats": self.where,
                "auth": self.auth.describe(self.servers),
                "connected": bool(self.nc and self.nc.is_connected), "ready": self.ready()[1],
                "last_frame_age_s": None if self.last_frame_mono is None else round(time.monotonic() - self.last_frame_mono, 3),
                "upstream": {"session": u.session, "frames": u.frames, "lost": u.lost, "sessions": u.sessions,
                             "channels_frames": self.upstream_channels.frames, "channels_lost": self.upstream_channels.lost,
                             "decoded": {n: {"frames": t.frames, "lost": t.lost} for n, t in self.upstream_decoded.items()},
                             "bad_frames": self.bad_frames, "slow_consumer": int(self.m_slow._value.get()),
                             "parted_frames_dropped": self.parts.dropped},
                "demand": {"columns": {c: P.id_ranges(t) for c, t in self.hub.announced.columns.items()},
                           "channel_taxels": P.id_ranges(self.hub.announced.channels),
                           "decoders": {n: P.id_ranges(t) for n, t in self.hub.announced.decoders.items()}},
                "clients": [{"id": c.id, "seq": c.seq, "sent": c.sent, "dropped": c.dropped, "queued": len(c.queue)}
                            for c in self.hub.subscribers.values()]}


router = APIRouter()


@router.get("/v1/health", tags=["health"])
def health(request: Request) -> dict[str, str]:
    return {"status": "ok", "gateway": request.app.state.service.id}


@router.get("/v1/ready", tags=["health"])
def ready(request: Request) -> Any:
    ok, reason = request.app.state.service.ready()
    return JSONResponse({"ready": ok, "reason": reason}, status_code=200 if ok else 503)


@router.get("/v1/status", tags=["status"])
def status(request: Request) -> dict[str, Any]:
    return request.app.state.service.status()


@router.get("/v1/decoders", tags=["decoders"], responses={503: {"description": "the publisher does not answer"}})
async def decoders(request: Request) -> Any:
    """The publishing service's installed decoders (asked over NATS; docs/decoders.md)."""
    try:
        return await request.app.state.service.decoders()
    except UpstreamUnavailable as exc:
        return JSONResponse({"detail": str(exc)}, status_code=503)


@router.get("/v1/decoders/{name}", tags=["decoders"], responses={404: {"description": "no such decoder"}})
async def decoder(name: str, request: Request) -> Any:
    found = await decoders(request)
    if isinstance(found, Response):
        return found
    for m in found:
        if m["name"] == name:
            return m
    return JSONResponse({"detail": f"no decoder model named {name[:64]!r}"}, status_code=404)


@router.get("/v1/decoders/{name}/model.onnx", tags=["decoders"],
            responses={200: {"content": {"application/octet-stream": {}}}, 404: {"description": "no such decoder"}})
async def decoder_onnx(name: str, request: Request) -> Response:
    """The publishing service's ONNX file of decoder ``name`` (asked over NATS)."""
    if len(name) > 128:
        return JSONResponse({"detail": "no decoder model of that name"}, status_code=404)
    try:
        data = await request.app.state.service.model(name)
    except UpstreamUnavailable as exc:
        return JSONResponse({"detail": str(exc)}, status_code=503)
    except LookupError as exc:
        return JSONResponse({"detail": str(exc)}, status_code=404)
    return Response(data, media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="{name}.onnx"'} if subjects.token_ok(name) else {})


@router.get("/metrics", tags=["status"])
def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.service.metrics.registry), media_type=CONTENT_TYPE_LATEST)


def create_gateway_app(gateway: Gateway) -> FastAPI:
    """The gateway's app: /v1/stream and its REST routes, the offline /docs, the browser security headers."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        await gateway.start()
        try:
            yield
        finally:
            await gateway.stop()

    app = FastAPI(title="TouchReal gateway", version=__version__, lifespan=lifespan,
                  summary="The /v1/stream spike stream of one sensor, served from NATS (docs/scale-out.md)",
                  docs_url=None, redoc_url=None)  # add_docs: an offline Swagger UI under a strict CSP
    app.state.service = app.state.view = gateway  # server/ws.py reads them under these names
    app.state.allowed_origins = gateway.settings.allowed_origins  # /v1/stream's Origin check (security.admit)
    app.add_exception_handler(Exception, server_error)
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=gateway.settings.allowed_hosts)
    app.add_middleware(SecurityHeaders)  # outermost: a refused Host's 400 carries the headers too
    app.include_router(router)
    app.include_router(ws.router)
    add_docs(app)
    return app
