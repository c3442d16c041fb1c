"""The client objects: :class:`AsyncClient` (asyncio) and :class:`Client` (blocking, same API).

``AsyncClient`` is the REST helpers (:class:`~.rest.AsyncRest`) plus :meth:`AsyncClient.stream`,
which opens a ``/v1/stream`` connection (:class:`~.stream.AsyncStream`). ``Client`` runs an
``AsyncClient`` on an event loop in a background thread and blocks on each call, so a plain script
or a robot control loop needs no asyncio; its streams iterate with ordinary ``for`` loops.
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import AsyncIterator, Awaitable, Iterator
from typing import Any, TypeVar

import numpy as np

from . import protocol as P
from .backoff import Backoff
from .clock import ClockMap
from .rest import JSON, AsyncRest
from .stats import LatencyEstimator, StreamStats
from .stream import AsyncStream, DecodedOutput

T = TypeVar("T")
DEFAULT_URL = "http://127.0.0.1:8765"


class AsyncClient(AsyncRest):
    """A TouchReal service at ``base_url`` (``http://HOST:PORT``); ``token`` for write endpoints.

    >>> async with AsyncClient("http://127.0.0.1:8765") as tr:
    ...     async with tr.stream(Subscription(classes=["SA1"])) as s:
    ...         async for frame in s.spikes(): ...
    """

    def __init__(self, base_url: str = DEFAULT_URL, token: str | None = None, timeout_s: float = 10.0):
        super().__init__(base_url, token, timeout_s)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def stream(self, subscription: P.Subscription | None = None, *, reconnect: bool = True,
               backoff: Backoff | None = None, queue_frames: int = 1024) -> AsyncStream:
        """A stream (not yet open: use ``async with`` or ``await s.open()``)."""
        return AsyncStream(self.base_url, subscription, reconnect=reconnect, backoff=backoff, queue_frames=queue_frames)


class _LoopThread:
    """An event loop on a daemon thread; :meth:`call` runs a coroutine there and waits for it."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="touchreal-client", daemon=True)
        self._thread.start()

    def call(self, coro: Awaitable[T], timeout_s: float | None = None) -> T:
        async def run() -> T:
            return await coro

        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(timeout_s)

    def iterate(self, agen: AsyncIterator[T]) -> Iterator[T]:
        try:
            while True:
                try:
                    yield self.call(agen.__anext__())
                except StopAsyncIteration:
                    return
        finally:
            if not self.loop.is_closed():  # an iterator outliving its client has nothing to close
                self.call(agen.aclose())  # type: ignore[attr-defined]

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5)
        self.loop.close()


class Stream:
    """Blocking view of an :class:`~.stream.AsyncStream` (see there for the semantics)."""

    def __init__(self, runner: _LoopThread, stream: AsyncStream):
        self._run, self._s = runner, stream

    def __enter__(self) -> Stream:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        self._run.call(self._s.open())

    def close(self) -> None:
        self._run.call(self._s.close())

    @property
    def hello(self) -> dict[str, Any]:
        return self._s.hello

    @property
    def subscribed(self) -> dict[str, Any] | None:
        return self._s.subscribed

    @property
    def subscription(self) -> P.Subscription:
        return self._s.subscription

    @property
    def stats(self) -> StreamStats:
        return self._s.stats

    @property
    def latency(self) -> LatencyEstimator:
        return self._s.latency

    def subscribe(self, subscription: P.Subscription | None = None, **changes: Any) -> dict[str, Any]:
        return self._run.call(self._s.subscribe(subscription, **changes))

    def sync_clock(self, samples: int = 5) -> float:
        return self._run.call(self._s.sync_clock(samples))

    @property
    def clock(self) -> ClockMap:
        return self._s.clock

    def to_local(self, t_us: Any) -> Any:
        """See :meth:`AsyncStream.to_local`."""
        return self._s.to_local(t_us)

    def spike_latency_us(self, frame: P.SpikesFrame) -> np.ndarray:
        """See :meth:`AsyncStream.spike_latency_us`."""
        return self._s.spike_latency_us(frame)

    def frames(self) -> Iterator[P.Frame]:
        return self._run.iterate(self._s.frames())

    def spikes(self) -> Iterator[P.SpikesFrame]:
        return self._run.iterate(self._s.spikes())

    def decoded(self) -> Iterator[DecodedOutput]:
        return self._run.iterate(self._s.decoded())


class Client:
    """Blocking client: the methods of :class:`AsyncClient`, called without ``await``.

    >>> with Client("http://127.0.0.1:8765", token="...") as tr:
    ...     tr.patch_config(window_ms=64)
    ...     with tr.stream() as s:
    ...         for frame in s.spikes(): ...
    """

    def __init__(self, base_url: str = DEFAULT_URL, token: str | None = None, timeout_s: float = 10.0):
        self._run = _LoopThread()
        self._c: AsyncClient = self._run.call(_make(base_url, token, timeout_s))
        self.base_url = self._c.base_url

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._run.call(self._c.aclose())
        self._run.stop()

    def stream(self, subscription: P.Subscription | None = None, *, reconnect: bool = True,
               backoff: Backoff | None = None, queue_frames: int = 1024) -> Stream:
        return Stream(self._run, self._c.stream(subscription, reconnect=reconnect, backoff=backoff,
                                                queue_frames=queue_frames))

    def health(self) -> JSON:
        return self._run.call(self._c.health())

    def ready(self) -> tuple[bool, str]:
        return self._run.call(self._c.ready())

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        self._run.call(self._c.wait_ready(timeout_s))

    def status(self) -> JSON:
        return self._run.call(self._c.status())

    def metrics(self) -> str:
        return self._run.call(self._c.metrics())

    def config(self) -> JSON:
        return self._run.call(self._c.config())

    def patch_config(self, **changes: Any) -> JSON:
        return self._run.call(self._c.patch_config(**changes))

    def params(self) -> JSON:
        return self._run.call(self._c.params())

    def put_params(self, params: JSON | str | os.PathLike[str]) -> JSON:
        return self._run.call(self._c.put_params(params))

    def params_history(self) -> JSON:
        return self._run.call(self._c.params_history())

    def rollback(self, rev: int) -> JSON:
        return self._run.call(self._c.rollback(rev))

    def decoders(self) -> list[JSON]:
        return self._run.call(self._c.decoders())

    def decoder(self, name: str) -> JSON:
        return self._run.call(self._c.decoder(name))

    def download_model(self, name: str, dest: str | os.PathLike[str] | None = None) -> bytes:
        return self._run.call(self._c.download_model(name, dest))


async def _make(base_url: str, token: str | None, timeout_s: float) -> AsyncClient:
    return AsyncClient(base_url, token, timeout_s)  # created on the loop thread that will use it
