"""Live bridges from a ``/v1/stream`` (a service or a gateway) into other tools' protocols.

* :mod:`.foxglove`: a Foxglove WebSocket server (extra ``foxglove``: foxglove-sdk), demand-driven.
* :mod:`.lsl`: Lab Streaming Layer outlets (extra ``lsl``: pylsl).
* :mod:`.ros2`: ROS 2 topics over DDS (extra ``ros2``: cyclonedds, rosbags), demand-driven.

All stamp what they forward with the stream's clock model (:mod:`touchreal_client.clock`): a
sample stamped ``t_us`` on the wire clock is placed at this machine's wall time of its acquisition,
not at the time it arrived. They import their library only when used, so the base client stays light.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine, Iterable
from typing import Any

import websockets

from .. import protocol as P
from ..errors import StreamClosed, StreamError, TouchRealError
from ..events import wait_set
from ..stream import AsyncStream
from ..topics import wanted_subscription

log = logging.getLogger("touchreal_client.bridges")

#: Exchanges of the first ``time`` sync, before a bridge forwards anything.
FIRST_SYNC_SAMPLES = 8
#: How often a bridge repeats the ``time`` exchange that maps the server's wall clock onto its own (s).
CLOCK_SYNC_PERIOD_S = 10.0
#: How often a demand-driven bridge looks at its demand, the upstream session and a failed subscription again (s).
FOLLOW_PERIOD_S = 0.5


async def keep_clock_synced(stream: AsyncStream, period_s: float = CLOCK_SYNC_PERIOD_S) -> None:
    """Repeat :meth:`AsyncStream.sync_clock` every ``period_s`` until cancelled (a failed exchange,
    e.g. during a reconnect, is retried at the next period). The exchange with the least round trip
    so far is the one in use, so the offset only gets better."""
    while True:
        await asyncio.sleep(period_s)
        try:
            await stream.sync_clock(5)
        except (TouchRealError, asyncio.TimeoutError) as exc:
            log.info("clock sync failed (%r); retrying in %.0f s", exc, period_s)


async def resubscribe(stream: AsyncStream, want: P.Subscription, refused: P.Subscription | None) -> P.Subscription | None:
    """Subscribe ``stream`` upstream to ``want`` unless it is already, or the server refused that very
    subscription before; returns the subscription refused so far (tried again only once the demand
    changes). A failure while the stream reconnects is logged and retried at the next call."""
    if want == stream.subscription or want == refused:
        return refused
    try:
        await stream.subscribe(want)
        return None
    except StreamError as exc:
        log.warning("upstream refused subscription %s: %s", want.to_json(), exc)
        return want
    except (StreamClosed, websockets.ConnectionClosed, asyncio.TimeoutError) as exc:
        log.info("upstream subscribe failed (%r); retrying while the stream reconnects", exc)
        return refused


async def forward(stream: AsyncStream, publish: Callable[[P.Frame], None], ready: asyncio.Event,
                  *helpers: Coroutine[Any, Any, None]) -> None:
    """Hand every frame of ``stream`` to ``publish`` until the stream ends for good (then raises
    :class:`~touchreal_client.errors.StreamClosed`) or this is cancelled. :func:`keep_clock_synced` and
    the ``helpers`` run beside it as tasks, ``ready`` is set once they are started, and they are
    cancelled (and awaited) on the way out."""
    tasks = [asyncio.create_task(keep_clock_synced(stream)), *(asyncio.create_task(h) for h in helpers)]
    ready.set()
    try:
        async for frame in stream.frames():
            publish(frame)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def publish_by_kind(frame: P.Frame, spikes: Callable[[P.SpikesFrame], None], channels: Callable[[P.ChannelsFrame], None],
                    decoded: Callable[[P.DecodedFrame], None]) -> None:
    """Hand ``frame`` to the publisher of its kind: ``spikes``, ``channels`` or ``decoded``."""
    if isinstance(frame, P.SpikesFrame):
        spikes(frame)
    elif isinstance(frame, P.ChannelsFrame):
        channels(frame)
    else:
        decoded(frame)


async def follow_demand(stream: AsyncStream, changed: asyncio.Event, demanded: Callable[[], Iterable[str]],
                        decimation: int, on_hello: Callable[[dict[str, Any]], None]) -> None:
    """Keep ``stream``'s upstream subscription equal to what the topics ``demanded()`` names need (channels
    at 5 kHz / ``decimation``), looked at whenever ``changed`` is set and every :data:`FOLLOW_PERIOD_S`
    (:func:`resubscribe`: retried while the stream reconnects). A new hello (after a reconnect) goes to
    ``on_hello`` first. Runs until cancelled."""
    hello = stream.hello
    refused: P.Subscription | None = None
    while True:
        await wait_set(changed, FOLLOW_PERIOD_S)
        changed.clear()
        if stream.hello is not hello:
            hello = stream.hello
            on_hello(hello)
        want = wanted_subscription(demanded(), decimation, stream.hello)
        refused = await resubscribe(stream, want, refused)
