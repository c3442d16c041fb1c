"""Waiting on an :class:`asyncio.Event` with a timeout, without losing a cancellation.

``asyncio.wait_for(event.wait(), t)`` on Python 3.10 and 3.11 swallows a cancellation that arrives as
the event is set (CPython gh-86296): a loop that waits that way on an often-set event may never stop.
``asyncio.wait`` lets the cancellation through.
"""

from __future__ import annotations

import asyncio


async def wait_set(event: asyncio.Event, timeout_s: float) -> bool:
    """Wait until ``event`` is set or ``timeout_s`` seconds pass; True if it was set."""
    waiter = asyncio.ensure_future(event.wait())
    try:
        done, _ = await asyncio.wait({waiter}, timeout=timeout_s)
    finally:
        waiter.cancel()
    return bool(done)
