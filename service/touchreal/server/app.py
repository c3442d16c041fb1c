"""FastAPI wiring: routers over one :class:`~.service.Service`, started and stopped with the app."""

from __future__ import annotations

import threading
import time
from contextlib import asynccontextmanager, contextmanager
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Protocol

import uvicorn
from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.staticfiles import StaticFiles
from starlette.middleware.trustedhost import TrustedHostMiddleware
from touchreal_client.protocol import MAX_CLIENT_MESSAGE_BYTES

from .. import __version__
from . import rest, ws
from .api_docs import add_docs
from .browser import SecurityHeaders, server_error
from .limits import uvicorn_limits
from .security import BodyGuard, validation_error
from .service import Service

#: The live dashboard: plain static files (no build step), package data of the wheel.
DASHBOARD_DIR = Path(__file__).with_name("dashboard")
STOP_TIMEOUT_S = 20.0  #: how long serving_app waits for its server (lifespan shutdown included) to stop


class Companion(Protocol):
    """Something that runs beside the service on its event loop (e.g. the NATS publisher)."""

    async def start(self) -> None: ...
    async def stop(self) -> None: ...


def create_app(service: Service, companions: Sequence[Companion] = ()) -> FastAPI:
    """The service's app; ``companions`` start after the service and stop before it."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        await service.start()
        for c in companions:
            await c.start()
        try:
            yield
        finally:
            for c in reversed(companions):
                await c.stop()
            await service.stop()

    app = FastAPI(
        title="TouchReal",
        version=__version__,
        summary="Biomimetic SA1/RA/PC afferent spikes from a tactile sensor, online",
        description="REST configuration and parameter uploads; the spike stream is the WebSocket `/v1/stream` "
        "(docs/stream-protocol.md).",
        lifespan=lifespan,
        docs_url=None,  # add_docs: an offline Swagger UI under a strict CSP
        redoc_url=None,
    )
    app.state.service = service
    app.state.view = service.view  # what /v1/stream and the read routes report
    app.state.allowed_origins = service.settings.allowed_origins  # /v1/stream's Origin check (security.admit)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(Exception, server_error)
    app.add_middleware(BodyGuard, token=lambda: service.settings.token, max_body_bytes=service.settings.max_body_bytes,
                       on_auth=service.metrics.count_auth)
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=service.settings.allowed_hosts)  # first check
    app.add_middleware(SecurityHeaders)  # outermost: a refused Host's 400 carries the headers too
    app.include_router(rest.router)
    app.include_router(ws.router)
    add_docs(app)
    # last: routes match in order, so /v1, /metrics, /docs and /openapi.json are never shadowed
    app.mount("/", StaticFiles(directory=DASHBOARD_DIR, html=True), name="dashboard")
    return app


def uvicorn_config(app: FastAPI, host: str, port: int, log_level: str = "warning") -> uvicorn.Config:
    """The server configuration (``touchreal serve``, ``touchreal gateway``, the tests and the benchmark
    use this one): websockets' sans-I/O implementation, client messages capped at the protocol's
    limit, permessage-deflate only for clients that offer it, and the connection limits
    (:mod:`.limits`) and keepalive pings of the app's settings (``app.state.service.settings``, a
    :class:`~.settings.ServerSettings`; a client that stops reading is closed with 1011 after at most
    interval + timeout). The event loop is uvloop where it is installed (a dependency on POSIX):
    fanning a frame out to a hundred subscribers is a hundred socket writes, and on asyncio's own loop
    those dominated the event loop's time (docs/benchmarks.md, fan-out)."""
    s = app.state.service.settings
    return uvicorn.Config(app, host=host, port=port, loop="auto", ws="websockets-sansio", ws_max_size=MAX_CLIENT_MESSAGE_BYTES,
                          ws_per_message_deflate=True, ws_ping_interval=s.ping_interval_s,
                          ws_ping_timeout=s.ping_timeout_s, log_level=log_level, lifespan="on", **uvicorn_limits(s))


@contextmanager
def serving(service: Service, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning",
            companions: Sequence[Companion] = ()) -> Iterator[str]:
    """Run the service's uvicorn server on its own thread; yields ``host:port`` once it accepts and
    the service has warmed up and opened its source.

    For benchmarks and tests that need the real server next to their own code (``port=0``: a free port).
    """
    with serving_app(create_app(service, companions), host, port, log_level) as addr:
        if not service.opened.wait(120.0):
            raise RuntimeError("the service did not finish its warm-up within 120 s")
        yield addr


@contextmanager
def serving_app(app: FastAPI, host: str = "127.0.0.1", port: int = 0, log_level: str = "warning") -> Iterator[str]:
    """Run any of our apps (the service, a gateway) under uvicorn on its own thread; yields ``host:port``."""
    config = uvicorn_config(app, host, port, log_level)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="touchreal-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + 60.0
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            server.should_exit = True
            raise RuntimeError("the server did not start (see its log)")
        time.sleep(0.02)
    bound = server.servers[0].sockets[0].getsockname()
    try:
        yield f"{bound[0]}:{bound[1]}"
    finally:
        server.should_exit = True
        thread.join(STOP_TIMEOUT_S)
        if thread.is_alive():  # its companions or its source would run on under whoever called us
            raise RuntimeError(f"the server did not stop within {STOP_TIMEOUT_S:g} s")
