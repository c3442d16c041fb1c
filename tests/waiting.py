"""The one way tests wait for something: poll a predicate until it holds, with a deadline.

The deadline only bounds a failure: a test that passes returns as soon as the predicate holds, and one
that fails says what it was waiting for. Nothing else in the tests sleeps to let something happen; what
a WebSocket client receives is waited for the same way by ``server_harness.collect(ws, seconds,
until=...)`` (``server_harness.covers(s)``: a stretch of ``s`` seconds of the stream).

``what`` names what is awaited; it may be a string or a callable returning one, called only on failure
(for a message that shows the last state seen, e.g. ``lambda: f"ready; status: {last}"``).
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import Any

#: how often a predicate is polled (s)
POLL_S = 0.02


def _describe(what: str | Callable[[], str]) -> str:
    return what() if callable(what) else what


def wait_until(predicate: Callable[[], Any], seconds: float, what: str | Callable[[], str],
               interval: float = POLL_S) -> Any:
    """Poll ``predicate()`` every ``interval`` s until it returns something truthy, and return that;
    raise AssertionError naming ``what`` if it has not after ``seconds``."""
    end = time.monotonic() + seconds
    while not (value := predicate()):
        if time.monotonic() > end:
            raise AssertionError(f"not within {seconds} s: {_describe(what)}")
        time.sleep(interval)
    return value


async def until(predicate: Callable[[], Any], seconds: float, what: str | Callable[[], str],
                interval: float = POLL_S) -> Any:
    """:func:`wait_until` for a coroutine: the event loop runs on between polls. ``predicate`` may also
    return an awaitable (e.g. an ``async def`` that asks a server), awaited at each poll."""
    end = time.monotonic() + seconds
    while True:
        value = predicate()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"not within {seconds} s: {_describe(what)}")
        await asyncio.sleep(interval)
