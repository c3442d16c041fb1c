"""The NATS client life cycle shared by the publisher and the gateway.

Owners create their ``nats.NATS()`` before :func:`connect`, so whoever stops them can always close
it: a task cancelled in the middle of its first connect, or a drain that times out, must not leave
the client's reconnect loop running after its owner has gone.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import nats
from nats.errors import Error as NatsError

from .auth import NatsAuth

DRAIN_S = 5.0  #: how long a stop waits for buffered messages to reach the server


async def connect(nc: nats.NATS, servers: str | list[str], name: str, auth: NatsAuth,
                  on_error: Callable[[Exception], Awaitable[None]], on_conn: Callable[[], Awaitable[None]],
                  **options) -> None:
    """Connect ``nc``; it reconnects for ever, every second, and reports through the callbacks."""
    await nc.connect(servers, name=name, max_reconnect_attempts=-1, reconnect_time_wait=1, error_cb=on_error,
                     disconnected_cb=on_conn, reconnected_cb=on_conn, **options, **auth.connect_options())


async def close(nc: nats.NATS | None) -> None:
    """Drain ``nc`` for up to :data:`DRAIN_S`, then make sure it is closed whatever the drain did."""
    if nc is None or nc.is_closed:
        return
    try:
        await asyncio.wait_for(nc.drain(), DRAIN_S)
    except (asyncio.TimeoutError, NatsError, OSError):
        pass
    if not nc.is_closed:
        await nc.close()
